// Per-RPC metrics (grpc_server_started_total, grpc_server_handled_total,
// grpc_server_handling_seconds) recorded by a server interceptor, for every
// method of every service on the server, whatever path a handler returns
// by: no handler records anything itself.
//
// Labels follow the usual grpc_server_* shape: grpc_service and grpc_method
// from the call's full method name ("/kinetri.v1.KinetriService/Query"),
// grpc_type from the method's proto definition (unary, client_stream,
// server_stream, bidi_stream; the registration cannot tell: methods taken
// over as raw bytes are registered as bidirectional streams), grpc_code
// from the status the server sends.
#ifndef KINETRI_SERVER_RPC_METRICS_H_
#define KINETRI_SERVER_RPC_METRICS_H_

#include <grpcpp/support/server_interceptor.h>

#include <string>
#include <utility>

#include "absl/container/flat_hash_map.h"
#include "absl/synchronization/mutex.h"
#include "server/metrics.h"

namespace kinetri::server {

class RpcMetricsInterceptorFactory
    : public grpc::experimental::ServerInterceptorFactoryInterface {
 public:
  explicit RpcMetricsInterceptorFactory(Metrics* metrics) : metrics_(metrics) {}
  grpc::experimental::Interceptor* CreateServerInterceptor(
      grpc::experimental::ServerRpcInfo* info) override;

  struct Labels {
    std::string service;
    std::string method;
    const char* type;
  };
  // The labels of a full method name (looked up once per method); a
  // method the server does not serve is {"unknown", "unknown", "unknown"}.
  Labels LabelsOf(const char* full_method);

 private:
  Metrics* metrics_;
  absl::Mutex mu_;
  absl::flat_hash_map<std::string, Labels> labels_ ABSL_GUARDED_BY(mu_);
};

// The grpc_type label of a method of the generated descriptor pool
// ("kinetri.v1.KinetriService", "Query" -> "server_stream"); nullptr if the
// pool does not know it.
const char* ProtoMethodType(const std::string& service,
                            const std::string& method);

// "/pkg.Service/Method" -> {"pkg.Service", "Method"}; anything else ->
// {"unknown", the whole name}.
std::pair<std::string, std::string> SplitMethodName(const std::string& full);

// The grpc_code label of a status code ("OK", "NOT_FOUND", ...).
const char* StatusCodeName(grpc::StatusCode code);

}  // namespace kinetri::server

#endif  // KINETRI_SERVER_RPC_METRICS_H_
