// Prometheus metrics of the server (prometheus-cpp), exposed on /metrics.
#include "server/metrics.h"

namespace kinetri::server {

prometheus::Histogram::BucketBoundaries LatencyBuckets() {
  prometheus::Histogram::BucketBoundaries b;
  for (double v = 1e-5; v < 50.0; v *= 2) b.push_back(v);
  return b;
}

Metrics::Metrics() : registry_(std::make_shared<prometheus::Registry>()) {
  using namespace prometheus;
  update_seconds_ = &BuildHistogram()
                         .Name("kinetri_update_duration_seconds")
                         .Help("Time to apply one displacement step")
                         .Register(*registry_);
  query_seconds_ = &BuildHistogram()
                        .Name("kinetri_query_duration_seconds")
                        .Help("Time to answer one query batch")
                        .Register(*registry_);
  steps_ = &BuildCounter()
                .Name("kinetri_steps_total")
                .Help("Applied steps by update path")
                .Register(*registry_);
  flips_ = &BuildCounter()
                .Name("kinetri_flips_total")
                .Help("Edge flips by kind")
                .Register(*registry_);
  reinserted_ = &BuildCounter()
                     .Name("kinetri_reinserted_vertices_total")
                     .Help("Vertices removed and re-inserted locally")
                     .Register(*registry_);
  sessions_ = &BuildGauge()
                   .Name("kinetri_sessions")
                   .Help("Open sessions")
                   .Register(*registry_)
                   .Add({});
  points_ = &BuildGauge()
                 .Name("kinetri_points")
                 .Help("Points held by all sessions")
                 .Register(*registry_)
                 .Add({});
  expired_ = &BuildCounter()
                  .Name("kinetri_sessions_expired_total")
                  .Help("Sessions deleted by their idle TTL")
                  .Register(*registry_)
                  .Add({});
  restore_ = &BuildGauge()
                  .Name("kinetri_restore")
                  .Help(
                      "Last start's restore from --data_dir: sessions "
                      "restored, sessions unavailable (corrupt snapshot), "
                      "journal bytes cut (corrupt or truncated tail), "
                      "seconds")
                  .Register(*registry_);
  rpc_started_ = &BuildCounter()
                      .Name("grpc_server_started_total")
                      .Help("RPCs started on the server")
                      .Register(*registry_);
  rpc_handled_ = &BuildCounter()
                      .Name("grpc_server_handled_total")
                      .Help("RPCs completed on the server, by status code")
                      .Register(*registry_);
  rpc_seconds_ = &BuildHistogram()
                      .Name("grpc_server_handling_seconds")
                      .Help("RPC handling latency")
                      .Register(*registry_);
}

int Metrics::Expose(const std::string& address) {
  try {
    exposer_ = std::make_unique<prometheus::Exposer>(address);
  } catch (const std::exception&) {
    return -1;
  }
  exposer_->RegisterCollectable(registry_);
  const auto ports = exposer_->GetListeningPorts();
  return ports.empty() ? -1 : ports.front();
}

void Metrics::ObserveStep(const std::string& backend,
                          const core::StepReport& r) {
  update_seconds_->Add({{"backend", backend}}, LatencyBuckets())
      .Observe(r.seconds);
  steps_->Add({{"path", core::UpdatePathName(r.path)}}).Increment();
  flips_->Add({{"kind", "interior_fix"}})
      .Increment(static_cast<double>(r.flips.interior_fix));
  flips_->Add({{"kind", "hull_absorb"}})
      .Increment(static_cast<double>(r.flips.hull_absorb));
  flips_->Add({{"kind", "hull_release"}})
      .Increment(static_cast<double>(r.flips.hull_release));
  flips_->Add({{"kind", "delaunay"}})
      .Increment(static_cast<double>(r.flips.delaunay));
  reinserted_->Add({}).Increment(static_cast<double>(r.reinserted));
}

void Metrics::ObserveQuery(const std::string& op, const std::string& backend,
                           double seconds) {
  query_seconds_->Add({{"op", op}, {"backend", backend}}, LatencyBuckets())
      .Observe(seconds);
}

void Metrics::SetRestore(double sessions, double unavailable, double cut_bytes,
                         double seconds) {
  restore_->Add({{"what", "sessions"}}).Set(sessions);
  restore_->Add({{"what", "unavailable"}}).Set(unavailable);
  restore_->Add({{"what", "journal_bytes_cut"}}).Set(cut_bytes);
  restore_->Add({{"what", "seconds"}}).Set(seconds);
}

void Metrics::SessionsExpired(double count) { expired_->Increment(count); }

void Metrics::SetSessions(double sessions, double points) {
  sessions_->Set(sessions);
  points_->Set(points);
}

void Metrics::RpcStarted(const std::string& service, const std::string& method,
                         const std::string& type) {
  rpc_started_
      ->Add({{"grpc_service", service},
             {"grpc_method", method},
             {"grpc_type", type}})
      .Increment();
}

void Metrics::RpcHandled(const std::string& service, const std::string& method,
                         const std::string& type, const std::string& code,
                         double seconds) {
  rpc_handled_
      ->Add({{"grpc_service", service},
             {"grpc_method", method},
             {"grpc_type", type},
             {"grpc_code", code}})
      .Increment();
  rpc_seconds_
      ->Add({{"grpc_service", service},
             {"grpc_method", method},
             {"grpc_type", type}},
            LatencyBuckets())
      .Observe(seconds);
}

}  // namespace kinetri::server
