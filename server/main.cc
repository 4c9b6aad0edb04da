// kinetri-server: serves kinetic Delaunay sessions over gRPC.
#include <grpcpp/ext/proto_server_reflection_plugin.h>
#include <grpcpp/grpcpp.h>
#include <grpcpp/health_check_service_interface.h>
#include <grpcpp/security/server_credentials.h>
#include <grpcpp/security/tls_certificate_provider.h>
#include <grpcpp/security/tls_credentials_options.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <csignal>
#include <cstdio>
#include <cstdlib>
#include <memory>
#include <string>
#include <thread>

#include "absl/flags/flag.h"
#include "absl/time/clock.h"
#include "absl/time/time.h"
#include "core/device/device_executor.h"
#include "core/program_flags.h"
#include "server/auth.h"
#include "server/metrics.h"
#include "server/query_pool.h"
#include "server/reflection_v1.h"
#include "server/rpc_metrics.h"
#include "server/service.h"
#include "server/session_registry.h"
#ifdef KINETRI_SERVER_CUDA
#include "core/device/cuda_backend.h"
#endif

ABSL_FLAG(std::string, listen, "127.0.0.1:50051",
          "gRPC listen address host:port (port 0 picks a free port; use "
          "0.0.0.0:50051 to serve other hosts)");
ABSL_FLAG(std::string, metrics_listen, "127.0.0.1:9464",
          "Prometheus /metrics address host:port (port 0: a free port; empty: "
          "no metrics endpoint)");
ABSL_FLAG(uint32_t, max_sessions, 64, "most sessions held at once");
ABSL_FLAG(uint64_t, max_points, 50000000, "most points in one session");
ABSL_FLAG(uint64_t, max_query_results, 200000000,
          "most result ids one query may return");
ABSL_FLAG(int, max_message_mb, 4,
          "largest gRPC message accepted, MiB (clients chunk to fit)");
ABSL_FLAG(int, threads, 0,
          "worker threads per session on the CPU backend (0: all cores)");
ABSL_FLAG(int, query_threads, 0,
          "threads that compute query rows, for all sessions (0: all "
          "cores); more queries wait in line for one");
ABSL_FLAG(int, query_nice, 10,
          "how much the query threads' nice value is raised (0-19): a step "
          "takes a core from queries as soon as it wakes");
ABSL_FLAG(bool, query_sched_idle, true,
          "run the query threads under SCHED_IDLE (Linux): a waking step "
          "preempts them at once, queries use the CPU steps leave; false: "
          "--query_nice alone");
ABSL_FLAG(std::string, tls_cert, "",
          "PEM certificate chain of the gRPC port (TLS on when set, with "
          "--tls_key); re-read when the files change");
ABSL_FLAG(std::string, tls_key, "", "PEM private key for --tls_cert");
ABSL_FLAG(std::string, tls_client_ca, "",
          "PEM CA bundle: require client certificates signed by it (mutual "
          "TLS)");
ABSL_FLAG(int, tls_reload_seconds, 10,
          "how often the TLS files are checked for changes");
ABSL_FLAG(std::string, auth_tokens_file, "",
          "bearer tokens, one per line: TOKEN TENANT [sessions=N] [points=N]; "
          "each tenant sees only its own sessions; re-read on SIGHUP and when "
          "the file changes (empty: no authentication)");
ABSL_FLAG(std::string, health_listen, "",
          "extra plaintext port serving only grpc.health.v1 (for probes that "
          "cannot speak TLS, e.g. Kubernetes gRPC probes); empty: none");
ABSL_FLAG(bool, insecure, false,
          "allow listening on a non-loopback address without TLS and tokens "
          "(protected mode refuses to start otherwise)");
ABSL_FLAG(uint64_t, session_idle_ttl_seconds, 0,
          "delete sessions no call has touched for this long, unless they "
          "set their own SessionOptions.idle_ttl_seconds (0: never)");
ABSL_FLAG(std::string, data_dir, "",
          "keep sessions on disk here (a snapshot + journal per session) and "
          "restore them at start; empty: sessions live in memory only");
ABSL_FLAG(std::string, fsync, "always",
          "with --data_dir: always (an acknowledged step is on disk), "
          "everysec (at most about one second of steps lost), no (the OS "
          "decides)");
ABSL_FLAG(uint64_t, snapshot_interval_steps, 0,
          "with --data_dir: write a new snapshot every that many steps (0: "
          "when the journal outgrows 4x the snapshot)");
ABSL_FLAG(std::string, device, "auto",
          "device executor for sessions asking BACKEND_AUTO or BACKEND_CUDA: "
          "cuda (the GPU; this build and machine must have one), emulated "
          "(the device source on CPU threads: tests), none, or auto: none "
          "for now, since on the GPUs measured the CPU executor is faster "
          "(docs/DEVICE.md)");
ABSL_FLAG(uint32_t, max_threads, 256,
          "most worker threads a client may ask for in SessionOptions.threads");
ABSL_FLAG(int, stream_idle_timeout_seconds, 600,
          "cancel a step or creation stream that sends nothing for this long "
          "(0: never); frees its thread and what it buffered");
ABSL_FLAG(int, max_calls, 512,
          "most calls served at once (each holds a server thread); more get "
          "RESOURCE_EXHAUSTED");
ABSL_FLAG(int, max_streams_per_connection, 100,
          "most concurrent calls on one client connection (HTTP/2 streams)");
ABSL_FLAG(int, keepalive_seconds, 60,
          "ping idle connections this often; a peer that does not answer "
          "within 20 s is dropped and its calls cancelled");
ABSL_FLAG(int64_t, max_memory_mb, 0,
          "memory budget for sessions and their step copies, MiB; creations "
          "beyond it get RESOURCE_EXHAUSTED before allocating (0: 80% of the "
          "cgroup's or machine's memory; -1: no budget)");
ABSL_FLAG(bool, reuse_port, false,
          "let another process listen on the same port (SO_REUSEPORT); off: "
          "a second server on an occupied port refuses to start");
ABSL_FLAG(int, shutdown_grace_seconds, 10,
          "on SIGTERM/SIGINT: how long running calls may finish");
ABSL_FLAG(double, drain_delay_seconds, 0.0,
          "on SIGTERM/SIGINT: report NOT_SERVING on the health service for "
          "this long, still accepting calls, before shutting down (lets load "
          "balancers and readiness probes notice)");

namespace {
std::atomic<bool> g_stop{false};
std::atomic<bool> g_reload{false};
void OnSignal(int) { g_stop = true; }
void OnHangup(int) { g_reload = true; }
}  // namespace

int main(int argc, char** argv) {
  kinetri::ParseProgramFlags(
      argc, argv,
      "Serves Kinetri sessions (kinetic Delaunay triangulations of moving 2D "
      "points) over gRPC (kinetri.v1.KinetriService), with the gRPC health "
      "service, server reflection and Prometheus metrics. Defaults serve on "
      "loopback out of the box.");
  // From the start: a SIGTERM that comes while the server starts (or as
  // soon as it has said it listens) drains it like any other, instead of
  // killing it by default.
  std::signal(SIGTERM, OnSignal);
  std::signal(SIGINT, OnSignal);
  std::signal(SIGHUP, OnHangup);

  kinetri::server::ServerLimits limits;
  limits.max_sessions = absl::GetFlag(FLAGS_max_sessions);
  limits.max_points_per_session = absl::GetFlag(FLAGS_max_points);
  limits.max_query_results = absl::GetFlag(FLAGS_max_query_results);
  limits.default_threads = absl::GetFlag(FLAGS_threads);
  limits.max_threads = absl::GetFlag(FLAGS_max_threads);
  limits.default_idle_ttl_seconds =
      std::min<uint64_t>(absl::GetFlag(FLAGS_session_idle_ttl_seconds),
                         uint64_t{100} * 365 * 24 * 3600);
  if (limits.default_threads < 0 || limits.max_threads < 1 ||
      limits.max_threads > 4096 ||
      static_cast<uint32_t>(limits.default_threads) > limits.max_threads) {
    std::fprintf(stderr,
                 "kinetri-server: --threads must be in [0, --max_threads] and "
                 "--max_threads in [1, 4096]\n");
    return 2;
  }
  {
    namespace dev = kinetri::core::device;
#ifdef KINETRI_SERVER_CUDA
    dev::RegisterCudaBackend();
#endif
    const std::string device = absl::GetFlag(FLAGS_device);
    // AUTO keeps sessions on the CPU executor: on the one GPU the typed
    // suites have passed on (an H100, docs/DEVICE.md) the CUDA backend's
    // kinetic steps at 1M points were 1.3-16x slower than the CPU executor
    // on the same machine's 16 cores and its radius rows 1.6-4.8x slower;
    // only its k-NN rows were faster. --device=cuda asks for it anyway.
    if (device == "auto") {
      if (dev::DeviceBackendAvailable(dev::DeviceBackend::kCuda)) {
        std::printf(
            "kinetri-server: a GPU is present; sessions stay on the CPU "
            "executor, faster there for now (--device=cuda uses the GPU; "
            "docs/DEVICE.md)\n");
      }
    } else if (device == "cuda" || device == "emulated") {
      limits.device = device == "cuda" ? dev::DeviceBackend::kCuda
                                       : dev::DeviceBackend::kEmulated;
      if (!dev::DeviceBackendAvailable(limits.device)) {
        std::fprintf(stderr,
                     "kinetri-server: --device=%s: this build or machine has "
                     "no such backend\n",
                     device.c_str());
        return 2;
      }
      limits.has_device = true;
    } else if (device != "none") {
      std::fprintf(stderr,
                   "kinetri-server: --device must be auto, cuda, emulated or "
                   "none, not \"%s\"\n",
                   device.c_str());
      return 2;
    }
    std::printf("kinetri-server: device executor: %s\n",
                limits.has_device ? dev::DeviceBackendName(limits.device)
                                  : "none (CPU sessions only)");
  }
  // Declared before the registry: the sessions' journals outlive neither.
  std::unique_ptr<kinetri::server::SessionStore> store;
  kinetri::server::SessionRegistry registry(limits);
  kinetri::server::Metrics metrics;
  const std::string metrics_addr = absl::GetFlag(FLAGS_metrics_listen);
  if (!metrics_addr.empty()) {
    const int port = metrics.Expose(metrics_addr);
    if (port < 0) {
      std::fprintf(stderr, "kinetri-server: cannot serve metrics on %s\n",
                   metrics_addr.c_str());
      return 1;
    }
    // The address with the port it got (port 0 asks for a free one).
    const std::string host = metrics_addr.substr(0, metrics_addr.rfind(':'));
    std::printf("kinetri-server: metrics on http://%s:%d/metrics (port %d)\n",
                host.c_str(), port, port);
  }

  // Security: TLS (optionally mutual), bearer tokens with tenants, and
  // protected mode (docs/SECURITY.md).
  const std::string listen = absl::GetFlag(FLAGS_listen);
  const std::string tls_cert = absl::GetFlag(FLAGS_tls_cert);
  const std::string tls_key = absl::GetFlag(FLAGS_tls_key);
  const std::string tls_ca = absl::GetFlag(FLAGS_tls_client_ca);
  if (tls_cert.empty() != tls_key.empty() ||
      (!tls_ca.empty() && tls_cert.empty())) {
    std::fprintf(stderr,
                 "kinetri-server: --tls_cert and --tls_key go together; "
                 "--tls_client_ca needs them\n");
    return 2;
  }
  for (const std::string& f : {tls_cert, tls_key, tls_ca}) {
    if (f.empty()) continue;
    std::FILE* probe = std::fopen(f.c_str(), "r");
    if (probe == nullptr) {
      std::fprintf(stderr, "kinetri-server: cannot read %s\n", f.c_str());
      return 2;
    }
    std::fclose(probe);
  }
  const bool tls = !tls_cert.empty();
  std::unique_ptr<kinetri::server::TokenAuth> auth;
  if (!absl::GetFlag(FLAGS_auth_tokens_file).empty()) {
    auto loaded =
        kinetri::server::TokenAuth::Load(absl::GetFlag(FLAGS_auth_tokens_file));
    if (!loaded.ok()) {
      std::fprintf(stderr, "kinetri-server: %s\n",
                   std::string(loaded.status().message()).c_str());
      return 2;
    }
    auth = *std::move(loaded);
    std::printf("kinetri-server: %zu bearer tokens (--auth_tokens_file)\n",
                auth->size());
  }
  if (!kinetri::server::IsLoopbackAddress(listen) && !(tls && auth) &&
      !absl::GetFlag(FLAGS_insecure)) {
    std::fprintf(stderr,
                 "kinetri-server: protected mode: refusing to listen on %s "
                 "(not loopback) without TLS (--tls_cert, --tls_key) and "
                 "tokens (--auth_tokens_file); pass --insecure to do it "
                 "anyway\n",
                 listen.c_str());
    return 2;
  }

  kinetri::server::IdleWatchdog watchdog(std::chrono::seconds(
      std::max(0, absl::GetFlag(FLAGS_stream_idle_timeout_seconds))));
  const int64_t memory_mb = absl::GetFlag(FLAGS_max_memory_mb);
  kinetri::server::MemoryBudget budget(
      memory_mb < 0    ? 0
      : memory_mb == 0 ? kinetri::server::MemoryBudget::DefaultLimit()
                       : static_cast<uint64_t>(memory_mb) << 20);
  const int query_threads = absl::GetFlag(FLAGS_query_threads);
  const int query_nice = absl::GetFlag(FLAGS_query_nice);
  if (query_threads < 0 || query_threads > 1024 || query_nice < 0 ||
      query_nice > 19) {
    std::fprintf(stderr,
                 "kinetri-server: --query_threads must be in [0, 1024] and "
                 "--query_nice in [0, 19]\n");
    return 2;
  }
  kinetri::server::QueryPool query_pool(
      query_threads > 0
          ? query_threads
          : static_cast<int>(std::max(1u, std::thread::hardware_concurrency())),
      query_nice, absl::GetFlag(FLAGS_query_sched_idle));
  kinetri::server::KinetriServiceImpl service(&registry, &metrics, &watchdog,
                                              &budget, auth.get());
  service.SetQueryPool(&query_pool);
  if (budget.limit() > 0) {
    std::printf("kinetri-server: memory budget %llu MiB (--max_memory_mb)\n",
                static_cast<unsigned long long>(budget.limit() >> 20));
  }
  if (!absl::GetFlag(FLAGS_data_dir).empty()) {
    auto fsync = kinetri::server::ParseFsyncPolicy(absl::GetFlag(FLAGS_fsync));
    if (!fsync.ok()) {
      std::fprintf(stderr, "kinetri-server: %s\n",
                   std::string(fsync.status().message()).c_str());
      return 2;
    }
    auto opened = kinetri::server::SessionStore::Open(
        absl::GetFlag(FLAGS_data_dir), *fsync,
        absl::GetFlag(FLAGS_snapshot_interval_steps));
    if (!opened.ok()) {
      std::fprintf(stderr, "kinetri-server: %s\n",
                   std::string(opened.status().message()).c_str());
      return 2;
    }
    store = *std::move(opened);
    std::printf("kinetri-server: restoring sessions from %s\n",
                absl::GetFlag(FLAGS_data_dir).c_str());
    std::fflush(stdout);
    const auto r = service.EnableDurability(store.get());
    std::printf(
        "kinetri-server: restored %zu sessions (%llu journaled steps "
        "replayed, %zu unavailable, %llu journal bytes cut) in %.3f s; "
        "fsync %s\n",
        r.sessions, static_cast<unsigned long long>(r.steps_replayed),
        r.unavailable, static_cast<unsigned long long>(r.journal_bytes_cut),
        r.seconds, absl::GetFlag(FLAGS_fsync).c_str());
  }
  grpc::EnableDefaultHealthCheckService(true);
  grpc::reflection::InitProtoReflectionServerBuilderPlugin();
  grpc::ServerBuilder builder;
  int port = 0;
  std::shared_ptr<grpc::ServerCredentials> credentials =
      grpc::InsecureServerCredentials();
  if (tls) {
    // The provider re-reads the files when they change: certificates are
    // rotated without a restart and without dropping sessions.
    auto provider =
        std::make_shared<grpc::experimental::FileWatcherCertificateProvider>(
            tls_key, tls_cert, tls_ca,
            std::max(1, absl::GetFlag(FLAGS_tls_reload_seconds)));
    grpc::experimental::TlsServerCredentialsOptions options(provider);
    options.watch_identity_key_cert_pairs();
    if (!tls_ca.empty()) {
      options.watch_root_certs();
      options.set_cert_request_type(
          GRPC_SSL_REQUEST_AND_REQUIRE_CLIENT_CERTIFICATE_AND_VERIFY);
    } else {
      options.set_cert_request_type(GRPC_SSL_DONT_REQUEST_CLIENT_CERTIFICATE);
    }
    credentials = grpc::experimental::TlsServerCredentials(options);
  }
  std::printf("kinetri-server: %s%s, %s\n", tls ? "TLS" : "plaintext (no TLS)",
              tls && !tls_ca.empty() ? " with client certificates" : "",
              auth ? "bearer tokens required" : "no authentication");
  builder.AddListeningPort(listen, credentials, &port);
  const int max_bytes = absl::GetFlag(FLAGS_max_message_mb) * 1024 * 1024;
  // gRPC sets SO_REUSEPORT by default: a second server on the same port
  // would start and split the clients between two session sets.
  builder.AddChannelArgument(GRPC_ARG_ALLOW_REUSEPORT,
                             absl::GetFlag(FLAGS_reuse_port) ? 1 : 0);
  // Vanished clients: keepalive pings find dead connections, whose calls
  // are then cancelled (and the core's loops stop).
  const int keepalive_ms = absl::GetFlag(FLAGS_keepalive_seconds) * 1000;
  if (keepalive_ms > 0) {
    builder.AddChannelArgument(GRPC_ARG_KEEPALIVE_TIME_MS, keepalive_ms);
    builder.AddChannelArgument(GRPC_ARG_KEEPALIVE_TIMEOUT_MS, 20000);
    builder.AddChannelArgument(GRPC_ARG_KEEPALIVE_PERMIT_WITHOUT_CALLS, 1);
  }
  // Clients may ping at most every 10 s without data (more is abuse).
  builder.AddChannelArgument(
      GRPC_ARG_HTTP2_MIN_RECV_PING_INTERVAL_WITHOUT_DATA_MS, 10000);
  builder.AddChannelArgument(GRPC_ARG_MAX_CONCURRENT_STREAMS,
                             absl::GetFlag(FLAGS_max_streams_per_connection));
  grpc::ResourceQuota quota("kinetri-server");
  quota.SetMaxThreads(std::max(4, absl::GetFlag(FLAGS_max_calls)));
  builder.SetResourceQuota(quota);
  // gRPC's synchronous server polls its queue for up to 10 s (the default
  // CQ_TIMEOUT_MSEC); at shutdown it waits for every polling thread to
  // return, so a thread that went back to poll just after the shutdown began
  // held the exit for those 10 s (1 SIGTERM in 8 exited after 11 s with a
  // 1 s grace). Polls of 200 ms bound that wait.
  builder.SetSyncServerOption(
      grpc::ServerBuilder::SyncServerOption::CQ_TIMEOUT_MSEC, 200);
  builder.SetMaxReceiveMessageSize(max_bytes);
  builder.SetMaxSendMessageSize(max_bytes);
  builder.RegisterService(&service);
  // grpc_server_* metrics for every call of every service.
  {
    std::vector<
        std::unique_ptr<grpc::experimental::ServerInterceptorFactoryInterface>>
        interceptors;
    interceptors.push_back(
        std::make_unique<kinetri::server::RpcMetricsInterceptorFactory>(
            &metrics));
    builder.experimental().SetInterceptorCreators(std::move(interceptors));
  }
  kinetri::server::ReflectionV1Service reflection_v1(
      {"kinetri.v1.KinetriService", "grpc.health.v1.Health",
       "grpc.reflection.v1.ServerReflection",
       "grpc.reflection.v1alpha.ServerReflection"});
  builder.RegisterService(&reflection_v1);
  std::unique_ptr<grpc::Server> server = builder.BuildAndStart();
  if (!server || port == 0) {
    std::fprintf(stderr,
                 "kinetri-server: cannot listen on %s (in use by another "
                 "process? --reuse_port shares it)\n",
                 absl::GetFlag(FLAGS_listen).c_str());
    return 1;
  }
  // Probes that cannot speak TLS get their own plaintext port with the
  // health service alone (no Kinetri calls, no tokens travel on it).
  std::unique_ptr<grpc::Server> health_server;
  if (!absl::GetFlag(FLAGS_health_listen).empty()) {
    grpc::ServerBuilder health_builder;
    int health_port = 0;
    health_builder.AddListeningPort(absl::GetFlag(FLAGS_health_listen),
                                    grpc::InsecureServerCredentials(),
                                    &health_port);
    health_builder.SetSyncServerOption(
        grpc::ServerBuilder::SyncServerOption::CQ_TIMEOUT_MSEC, 200);
    health_server = health_builder.BuildAndStart();
    if (!health_server || health_port == 0 ||
        health_server->GetHealthCheckService() == nullptr) {
      std::fprintf(stderr, "kinetri-server: cannot serve health on %s\n",
                   absl::GetFlag(FLAGS_health_listen).c_str());
      return 1;
    }
    health_server->GetHealthCheckService()->SetServingStatus(
        kinetri::server::kServiceName, true);
    health_server->GetHealthCheckService()->SetServingStatus(true);
    std::printf("kinetri-server: health on port %d (%s, plaintext)\n",
                health_port, absl::GetFlag(FLAGS_health_listen).c_str());
  }
  // Probes may ask for the whole server ("") or the service by name;
  // SetServingStatus(bool) later flips both.
  server->GetHealthCheckService()->SetServingStatus(
      kinetri::server::kServiceName, true);
  server->GetHealthCheckService()->SetServingStatus(true);
  std::printf("kinetri-server: listening on port %d (%s)\n", port,
              absl::GetFlag(FLAGS_listen).c_str());
  std::fflush(stdout);

  int ticks = 0;
  while (!g_stop) {
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
    // Tokens: re-read on SIGHUP and when the file changes (checked every
    // second); a broken file keeps the previous tokens.
    const bool second = ++ticks % 20 == 0;
    if (second) service.ExpireIdleSessions();
    const bool hangup = g_reload.exchange(false);
    if (auth && (hangup || second)) {
      const absl::Status st = hangup ? auth->Reload() : auth->ReloadIfChanged();
      if (!st.ok()) {
        std::fprintf(stderr, "kinetri-server: tokens not reloaded: %s\n",
                     std::string(st.message()).c_str());
      }
    }
  }

  std::printf("kinetri-server: draining\n");
  std::fflush(stdout);
  server->GetHealthCheckService()->SetServingStatus(false);
  if (health_server) {
    health_server->GetHealthCheckService()->SetServingStatus(false);
  }
  std::this_thread::sleep_for(
      std::chrono::duration<double>(absl::GetFlag(FLAGS_drain_delay_seconds)));
  {
    // Once the grace has passed, calls still running stop their work too
    // (gRPC cancels them, but a handler computing learns it only at its
    // next read or write).
    const auto grace_end =
        std::chrono::steady_clock::now() +
        std::chrono::seconds(absl::GetFlag(FLAGS_shutdown_grace_seconds));
    std::atomic<bool> shut{false};
    std::thread stopper([&] {
      while (!shut && std::chrono::steady_clock::now() < grace_end) {
        std::this_thread::sleep_for(std::chrono::milliseconds(20));
      }
      if (!shut) service.StopAllWork();
    });
    server->Shutdown(
        std::chrono::system_clock::now() +
        std::chrono::seconds(absl::GetFlag(FLAGS_shutdown_grace_seconds)));
    shut = true;
    stopper.join();
  }
  server->Wait();
  if (store) {
    // Calls are over: snapshot every session whose journal has steps, so
    // the next start restores without replaying them.
    const absl::Time start = absl::Now();
    const size_t written = service.CheckpointAll();
    std::printf("kinetri-server: wrote %zu snapshot(s) in %.3f s\n", written,
                absl::ToDoubleSeconds(absl::Now() - start));
    std::fflush(stdout);
  }
  if (health_server) {
    health_server->Shutdown(std::chrono::system_clock::now());
    health_server->Wait();
  }
  std::printf("kinetri-server: stopped\n");
  std::fflush(nullptr);
  // Every call is over and every session is on disk (journals are written
  // with write(2), snapshots fsynced above). The destructors would now
  // tear gRPC down, which joins its executor thread; after a large answer
  // was cut off by the shutdown that thread can sit in a poll of up to
  // 10 s (seen: 11.4 s exits), with nothing left to do.
  std::_Exit(0);
}
