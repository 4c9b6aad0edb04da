#include "server/rpc_metrics.h"

#include <google/protobuf/descriptor.h>

#include <chrono>
#include <utility>

namespace kinetri::server {
namespace {

using Clock = std::chrono::steady_clock;
using grpc::experimental::InterceptionHookPoints;
using grpc::experimental::ServerRpcInfo;

// One per call: counts it as started when created (before the handler
// runs) and as handled, with its code and duration, when its status goes
// out.
class RpcMetricsInterceptor : public grpc::experimental::Interceptor {
 public:
  RpcMetricsInterceptor(Metrics* metrics,
                        RpcMetricsInterceptorFactory::Labels labels)
      : metrics_(metrics), labels_(std::move(labels)), start_(Clock::now()) {
    metrics_->RpcStarted(labels_.service, labels_.method, labels_.type);
  }

  void Intercept(
      grpc::experimental::InterceptorBatchMethods* methods) override {
    if (methods->QueryInterceptionHookPoint(
            InterceptionHookPoints::PRE_SEND_STATUS)) {
      metrics_->RpcHandled(
          labels_.service, labels_.method, labels_.type,
          StatusCodeName(methods->GetSendStatus().error_code()),
          std::chrono::duration<double>(Clock::now() - start_).count());
    }
    methods->Proceed();
  }

 private:
  Metrics* metrics_;
  const RpcMetricsInterceptorFactory::Labels labels_;
  Clock::time_point start_;
};

}  // namespace

grpc::experimental::Interceptor*
RpcMetricsInterceptorFactory::CreateServerInterceptor(ServerRpcInfo* info) {
  return new RpcMetricsInterceptor(metrics_, LabelsOf(info->method()));
}

RpcMetricsInterceptorFactory::Labels RpcMetricsInterceptorFactory::LabelsOf(
    const char* full_method) {
  const std::string full = full_method != nullptr ? full_method : "";
  absl::MutexLock lock(&mu_);
  auto it = labels_.find(full);
  if (it != labels_.end()) return it->second;
  auto [service, method] = SplitMethodName(full);
  const char* type = ProtoMethodType(service, method);
  if (type == nullptr && service == "grpc.health.v1.Health") {
    // gRPC's own health service has no descriptor in the generated pool.
    if (method == "Check") type = "unary";
    if (method == "Watch") type = "server_stream";
  }
  if (type == nullptr) {
    // Calls of methods the server does not have reach the interceptor too,
    // under whatever name a caller sends: one label set for all of them
    // (and nothing remembered), so that names cannot grow the metrics.
    return Labels{"unknown", "unknown", "unknown"};
  }
  Labels labels{service, method, type};
  // Bounded: methods with a descriptor linked into the server.
  labels_.emplace(full, labels);
  return labels;
}

const char* ProtoMethodType(const std::string& service,
                            const std::string& method) {
  const google::protobuf::MethodDescriptor* m =
      google::protobuf::DescriptorPool::generated_pool()->FindMethodByName(
          service + "." + method);
  if (m == nullptr) return nullptr;
  if (m->client_streaming()) {
    return m->server_streaming() ? "bidi_stream" : "client_stream";
  }
  return m->server_streaming() ? "server_stream" : "unary";
}

std::pair<std::string, std::string> SplitMethodName(const std::string& full) {
  const size_t slash = full.rfind('/');
  if (full.size() < 4 || full[0] != '/' || slash == 0 ||
      slash + 1 == full.size()) {
    return {"unknown", full};
  }
  return {full.substr(1, slash - 1), full.substr(slash + 1)};
}

const char* StatusCodeName(grpc::StatusCode code) {
  static const char* kNames[] = {"OK",
                                 "CANCELLED",
                                 "UNKNOWN",
                                 "INVALID_ARGUMENT",
                                 "DEADLINE_EXCEEDED",
                                 "NOT_FOUND",
                                 "ALREADY_EXISTS",
                                 "PERMISSION_DENIED",
                                 "RESOURCE_EXHAUSTED",
                                 "FAILED_PRECONDITION",
                                 "ABORTED",
                                 "OUT_OF_RANGE",
                                 "UNIMPLEMENTED",
                                 "INTERNAL",
                                 "UNAVAILABLE",
                                 "DATA_LOSS",
                                 "UNAUTHENTICATED"};
  const int i = static_cast<int>(code);
  return (i >= 0 && i <= 16) ? kNames[i] : "UNKNOWN";
}

}  // namespace kinetri::server
