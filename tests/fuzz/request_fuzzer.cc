// libFuzzer target over every RPC's request decoding and the streams'
// message sequences, against the service running in this process on a
// loopback port (built by scripts/fuzz.sh with clang,
// -fsanitize=fuzzer,address,undefined).
//
// An input is one call: its first byte picks the method, the rest is up to
// eight raw messages, each a 2-byte little-endian length and its bytes (a
// short last one takes what is left). Four sessions, sessions/f0 .. f3,
// exist from the start for the calls to aim at. A call that does not end
// within its deadline, ends with UNKNOWN, or leaves a session that is not a
// valid Delaunay triangulation (checked every 256 inputs) aborts: libFuzzer
// then saves the input as a crash to replay (`request_fuzzer CRASH_FILE`).
//
// KINETRI_FUZZ_SEEDS_OUT=DIR writes a seed corpus of valid calls to DIR and
// exits (scripts/fuzz.sh does this before fuzzing).
#include <grpcpp/generic/generic_stub.h>
#include <grpcpp/grpcpp.h>

#include <chrono>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "google/protobuf/stubs/logging.h"
#include "kinetri/v1/kinetri.pb.h"
#include "server/idle_watchdog.h"
#include "server/memory_budget.h"
#include "server/metrics.h"
#include "server/service.h"
#include "server/session_registry.h"
#include "tests/e2e/raw_call.h"

namespace kinetri::server {
namespace {

const char* const kMethods[] = {
    "/kinetri.v1.KinetriService/CreateSession",
    "/kinetri.v1.KinetriService/StreamSteps",
    "/kinetri.v1.KinetriService/Query",
    "/kinetri.v1.KinetriService/StreamQuery",
    "/kinetri.v1.KinetriService/GetSession",
    "/kinetri.v1.KinetriService/ListSessions",
    "/kinetri.v1.KinetriService/ExportTriangulation",
    "/kinetri.v1.KinetriService/DeleteSession",
};
constexpr size_t kNumMethods = sizeof(kMethods) / sizeof(kMethods[0]);

// The service and an in-process channel to it, for the whole run.
struct World {
  ServerLimits limits;
  std::unique_ptr<SessionRegistry> registry;
  Metrics metrics;
  IdleWatchdog watchdog{std::chrono::seconds(5)};
  MemoryBudget budget{256ull << 20};
  std::unique_ptr<KinetriServiceImpl> service;
  std::unique_ptr<grpc::Server> server;
  std::unique_ptr<grpc::GenericStub> stub;
  uint64_t inputs = 0;
};

World* world = nullptr;

std::string Encode(uint8_t method, const std::vector<std::string>& msgs) {
  std::string out(1, static_cast<char>(method));
  for (const std::string& m : msgs) {
    out.push_back(static_cast<char>(m.size() & 0xff));
    out.push_back(static_cast<char>(m.size() >> 8));
    out += m;
  }
  return out;
}

std::vector<std::string> Decode(const uint8_t* data, size_t size) {
  std::vector<std::string> msgs;
  size_t at = 1;
  while (at < size && msgs.size() < 8) {
    size_t len = data[at];
    if (at + 1 < size) len |= size_t{data[at + 1]} << 8;
    at += 2;
    len = at < size ? std::min(len, size - at) : 0;
    msgs.emplace_back(reinterpret_cast<const char*>(data) + std::min(at, size),
                      len);
    at += len;
  }
  return msgs;
}

v1::CreateSessionRequest Points(int n, uint64_t seed) {
  v1::CreateSessionRequest p;
  uint64_t x = seed * 0x9E3779B97F4A7C15ull + 1;
  for (int i = 0; i < 2 * n; ++i) {
    x ^= x << 13;
    x ^= x >> 7;
    x ^= x << 17;
    p.mutable_points()->add_xy(double(x >> 11) / double(1ull << 53));
  }
  return p;
}

// Valid calls of every method, as fuzzer inputs.
std::vector<std::string> Seeds() {
  std::vector<std::string> seeds;
  {
    v1::CreateSessionRequest h;
    h.mutable_header()->set_session_id("s0");
    h.mutable_header()->set_point_count(30);
    seeds.push_back(
        Encode(0, {h.SerializeAsString(), Points(30, 7).SerializeAsString()}));
    h.mutable_header()->mutable_options()->set_point_id_policy(
        v1::POINT_ID_POLICY_CLIENT);
    v1::CreateSessionRequest p = Points(10, 8);
    for (int i = 0; i < 10; ++i) p.mutable_points()->add_ids(100 + i);
    h.mutable_header()->set_point_count(10);
    seeds.push_back(Encode(0, {h.SerializeAsString(), p.SerializeAsString()}));
  }
  for (int sparse = 0; sparse < 2; ++sparse) {
    v1::StepRequest r;
    r.set_session("sessions/f0");
    r.set_step(1);
    const int n = sparse ? 3 : 20;
    for (int i = 0; i < 2 * n; ++i) r.add_xy(0.001 * (i % 7));
    if (sparse) {
      for (int i = 0; i < n; ++i) r.add_ids(i * 5);
    }
    r.set_end_of_step(true);
    seeds.push_back(Encode(1, {r.SerializeAsString()}));
  }
  for (int kind = 1; kind <= 3; ++kind) {
    v1::QueryRequest q;
    q.set_session("sessions/f1");
    q.set_kind(static_cast<v1::QueryKind>(kind));
    q.set_k(3);
    q.set_radius(0.2);
    q.set_include_distances(kind == 2);
    if (kind == 3) {
      for (int i = 0; i < 4; ++i) q.mutable_positions()->add_xy(0.25 * i);
    } else {
      q.mutable_all_points();
    }
    seeds.push_back(Encode(2, {q.SerializeAsString()}));
    seeds.push_back(Encode(3, {q.SerializeAsString()}));
  }
  v1::GetSessionRequest g;
  g.set_name("sessions/f2");
  seeds.push_back(Encode(4, {g.SerializeAsString()}));
  v1::ListSessionsRequest l;
  l.set_page_size(2);
  seeds.push_back(Encode(5, {l.SerializeAsString()}));
  v1::ExportTriangulationRequest e;
  e.set_session("sessions/f2");
  e.set_triangles_per_chunk(5);
  seeds.push_back(Encode(6, {e.SerializeAsString()}));
  v1::DeleteSessionRequest d;
  d.set_name("sessions/f3");
  seeds.push_back(Encode(7, {d.SerializeAsString()}));
  return seeds;
}

// Sessions f0 .. f3 (re-created when a call deleted one).
void EnsureSessions() {
  for (int s = 0; s < 4; ++s) {
    v1::CreateSessionRequest h;
    const int n = 20 + s * 20;
    h.mutable_header()->set_session_id("f" + std::to_string(s));
    h.mutable_header()->set_point_count(n);
    (void)testing::SendRaw(
        *world->stub, kMethods[0],
        {h.SerializeAsString(), Points(n, s).SerializeAsString()}, 5);
  }
}

[[noreturn]] void Fail(const std::string& what) {
  std::fprintf(stderr, "request_fuzzer: %s\n", what.c_str());
  std::abort();
}

}  // namespace
}  // namespace kinetri::server

extern "C" int LLVMFuzzerInitialize(int*, char***) {
  using namespace kinetri::server;
  // Mutated strings make protobuf log invalid UTF-8 by the thousand.
  google::protobuf::SetLogHandler(
      [](google::protobuf::LogLevel, const char*, int, const std::string&) {});
  if (const char* out = std::getenv("KINETRI_FUZZ_SEEDS_OUT")) {
    const std::vector<std::string> seeds = Seeds();
    for (size_t i = 0; i < seeds.size(); ++i) {
      std::ofstream(std::string(out) + "/seed-" + std::to_string(i),
                    std::ios::binary)
          << seeds[i];
    }
    std::printf("wrote %zu seeds to %s\n", seeds.size(), out);
    std::exit(0);
  }
  world = new World;
  world->limits.max_sessions = 8;
  world->limits.max_points_per_session = 5000;
  world->limits.max_query_results = 100000;
  world->limits.default_threads = 2;
  world->registry = std::make_unique<SessionRegistry>(world->limits);
  world->service = std::make_unique<KinetriServiceImpl>(
      world->registry.get(), &world->metrics, &world->watchdog, &world->budget);
  // Over loopback TCP, as clients call it (gRPC's in-process transport
  // never ends a unary call that was sent a second message; TCP does).
  grpc::ServerBuilder builder;
  int port = 0;
  builder.AddListeningPort("127.0.0.1:0", grpc::InsecureServerCredentials(),
                           &port);
  builder.RegisterService(world->service.get());
  world->server = builder.BuildAndStart();
  if (!world->server || port == 0) Fail("the server did not start");
  world->stub = std::make_unique<grpc::GenericStub>(grpc::CreateChannel(
      "127.0.0.1:" + std::to_string(port), grpc::InsecureChannelCredentials()));
  EnsureSessions();
  return 0;
}

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace kinetri::server;
  if (size == 0) return 0;
  const char* method = kMethods[data[0] % kNumMethods];
  const std::vector<std::string> msgs = Decode(data, size);
  const grpc::Status st =
      kinetri::testing::SendRaw(*world->stub, method, msgs, 10);
  if (st.error_code() == grpc::StatusCode::DEADLINE_EXCEEDED) {
    Fail(std::string(method) + " did not end within 10 s");
  }
  if (st.error_code() == grpc::StatusCode::UNKNOWN) {
    Fail(std::string(method) + " ended with UNKNOWN: " + st.error_message());
  }
  if (++world->inputs % 256 == 0) {
    for (const auto& s : world->registry->List("", 100)) {
      const Session::Snapshot snap = s->Read();
      if (!snap.tri->Validate().ok()) {
        Fail(s->name() + " is not a valid Delaunay triangulation");
      }
    }
    EnsureSessions();
  }
  return 0;
}
