// Prometheus metrics of the server (prometheus-cpp), exposed on /metrics.
#ifndef KINETRI_SERVER_METRICS_H_
#define KINETRI_SERVER_METRICS_H_

#include <prometheus/counter.h>
#include <prometheus/exposer.h>
#include <prometheus/gauge.h>
#include <prometheus/histogram.h>
#include <prometheus/registry.h>

#include <chrono>
#include <memory>
#include <string>

#include "core/triangulation.h"

namespace kinetri::server {

class Metrics {
 public:
  Metrics();

  // Starts the HTTP exposer on `address` ("host:port", port 0 = any).
  // Returns the bound port, or -1 if it could not listen.
  int Expose(const std::string& address);

  void ObserveStep(const std::string& backend, const core::StepReport& r);
  void ObserveQuery(const std::string& op, const std::string& backend,
                    double seconds);
  void SetSessions(double sessions, double points);
  void SessionsExpired(double count);
  // What the start-up restore from --data_dir found.
  void SetRestore(double sessions, double unavailable, double cut_bytes,
                  double seconds);

  // Per-RPC accounting in the grpc_server_* shape (recorded by the
  // interceptor of server/rpc_metrics.h).
  void RpcStarted(const std::string& service, const std::string& method,
                  const std::string& type);
  void RpcHandled(const std::string& service, const std::string& method,
                  const std::string& type, const std::string& code,
                  double seconds);

  prometheus::Registry& registry() { return *registry_; }

 private:
  std::shared_ptr<prometheus::Registry> registry_;
  std::unique_ptr<prometheus::Exposer> exposer_;
  prometheus::Family<prometheus::Histogram>* update_seconds_;
  prometheus::Family<prometheus::Histogram>* query_seconds_;
  prometheus::Family<prometheus::Counter>* steps_;
  prometheus::Family<prometheus::Counter>* flips_;
  prometheus::Family<prometheus::Counter>* reinserted_;
  prometheus::Gauge* sessions_;
  prometheus::Gauge* points_;
  prometheus::Counter* expired_;
  prometheus::Family<prometheus::Gauge>* restore_;
  prometheus::Family<prometheus::Counter>* rpc_started_;
  prometheus::Family<prometheus::Counter>* rpc_handled_;
  prometheus::Family<prometheus::Histogram>* rpc_seconds_;
};

// Latency buckets from 10 us to ~40 s, x2 apart.
prometheus::Histogram::BucketBoundaries LatencyBuckets();

}  // namespace kinetri::server

#endif  // KINETRI_SERVER_METRICS_H_
