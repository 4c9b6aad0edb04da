// Seeded random-mutation fuzzing of every RPC's request decoding and of the
// step and creation streams' message sequences, against the service running
// in-process (a crash fails the test run). Messages start valid (random
// fields, some hostile: NaN, huge counts, odd lengths, wrong steps), are
// serialized, then mutated (bit flips, truncation, insertion, duplication)
// and sent raw. Every call must end with a status within its deadline, and
// afterwards every session must still be a valid Delaunay triangulation.
// KINETRI_FUZZ_SECONDS (default 20) bounds the run; KINETRI_FUZZ_SEED picks
// the seed (a failure prints the seed and the iteration to replay).
#include <grpcpp/generic/generic_stub.h>
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <limits>
#include <random>
#include <string>
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

using Clock = std::chrono::steady_clock;

class Fuzzer {
 public:
  explicit Fuzzer(uint64_t seed) : rng_(seed) {}

  double Coordinate() {
    switch (rng_() % 12) {
      case 0:
        return std::nan("");
      case 1:
        return std::numeric_limits<double>::infinity();
      case 2:
        return 1e300;
      case 3:
        return 1e-310;
      case 4:
        return 0.5;
      default:
        return std::uniform_real_distribution<double>(-1, 2)(rng_);
    }
  }
  uint64_t Count(uint64_t typical) {
    switch (rng_() % 10) {
      case 0:
        return 0;
      case 1:
        return std::numeric_limits<uint64_t>::max() - rng_() % 3;
      case 2:
        return 1ull << (rng_() % 40);
      default:
        return rng_() % (typical + 1);
    }
  }
  std::string SessionName() {
    switch (rng_() % 6) {
      case 0:
        return "";
      case 1:
        return "sessions/" + std::string(rng_() % 300, 'a' + rng_() % 26);
      case 2:
        return "bogus";
      default:
        return "sessions/f" + std::to_string(rng_() % 4);
    }
  }
  // Serialized bytes, mutated now and then.
  std::string Mutate(std::string bytes) {
    const int edits = rng_() % 3 == 0 ? 0 : 1 + static_cast<int>(rng_() % 4);
    for (int i = 0; i < edits; ++i) {
      const size_t at = bytes.empty() ? 0 : rng_() % bytes.size();
      switch (rng_() % 5) {
        case 0:
          if (!bytes.empty()) bytes[at] ^= static_cast<char>(1 << (rng_() % 8));
          break;
        case 1:
          bytes.resize(at);
          break;
        case 2:
          bytes.insert(at, 1, static_cast<char>(rng_()));
          break;
        case 3:
          bytes += bytes.substr(at);
          break;
        default:
          if (!bytes.empty()) bytes[at] = static_cast<char>(rng_());
          break;
      }
    }
    return bytes;
  }

  // One call: a method and its raw messages.
  std::pair<std::string, std::vector<std::string>> Call() {
    std::vector<std::string> msgs;
    switch (rng_() % 7) {
      case 0: {  // CreateSession: header + chunks
        v1::CreateSessionRequest h;
        const uint64_t n = Count(64);
        h.mutable_header()->set_point_count(n);
        h.mutable_header()->set_session_id(
            rng_() % 2 ? "f" + std::to_string(rng_() % 4) : "");
        h.mutable_header()->mutable_options()->set_threads(
            static_cast<uint32_t>(Count(4)));
        if (rng_() % 3 == 0) {
          h.mutable_header()->mutable_options()->set_point_id_policy(
              v1::POINT_ID_POLICY_CLIENT);
        }
        msgs.push_back(Mutate(h.SerializeAsString()));
        const int chunks = 1 + static_cast<int>(rng_() % 3);
        for (int c = 0; c < chunks; ++c) {
          v1::CreateSessionRequest p;
          const int k = static_cast<int>(rng_() % 80);
          for (int i = 0; i < k; ++i) p.mutable_points()->add_xy(Coordinate());
          if (rng_() % 3 == 0) {
            for (int i = 0; i < k / 2; ++i) {
              p.mutable_points()->add_ids(rng_() % 100);
            }
          }
          msgs.push_back(Mutate(p.SerializeAsString()));
        }
        return {"/kinetri.v1.KinetriService/CreateSession", msgs};
      }
      case 1: {  // StreamSteps: a few chunks of a few steps
        const std::string name = SessionName();
        const int k = 1 + static_cast<int>(rng_() % 4);
        for (int i = 0; i < k; ++i) {
          v1::StepRequest r;
          r.set_session(rng_() % 4 ? name : SessionName());
          r.set_step(rng_() % 4);
          r.set_mode(static_cast<v1::DisplacementMode>(rng_() % 4));
          const int v = static_cast<int>(rng_() % 130);
          for (int j = 0; j < v; ++j) r.add_xy(0.01 * Coordinate());
          if (rng_() % 3 == 0) {
            for (int j = 0; j < v / 2; ++j) r.add_ids(rng_() % 70);
          }
          r.set_end_of_step(rng_() % 2);
          msgs.push_back(Mutate(r.SerializeAsString()));
        }
        return {"/kinetri.v1.KinetriService/StreamSteps", msgs};
      }
      case 2: {  // Query
        v1::QueryRequest q;
        q.set_session(SessionName());
        q.set_kind(static_cast<v1::QueryKind>(rng_() % 5));
        q.set_k(static_cast<int32_t>(rng_() % 2 ? rng_() % 10 : rng_()));
        q.set_radius(rng_() % 2 ? 0.1 * Coordinate() : Coordinate());
        q.set_exclude_self(rng_() % 2);
        q.set_include_distances(rng_() % 2);
        q.set_max_results_per_row(static_cast<uint32_t>(Count(8)));
        q.set_rows_per_chunk(static_cast<uint32_t>(Count(8)));
        switch (rng_() % 3) {
          case 0:
            q.mutable_all_points();
            break;
          case 1:
            for (int i = 0; i < 5; ++i) {
              q.mutable_point_ids()->add_ids(rng_() % 80);
            }
            break;
          default:
            for (int i = 0; i < 7; ++i) {
              q.mutable_positions()->add_xy(Coordinate());
            }
            break;
        }
        msgs.push_back(Mutate(q.SerializeAsString()));
        return {"/kinetri.v1.KinetriService/Query", msgs};
      }
      case 3: {
        v1::GetSessionRequest g;
        g.set_name(SessionName());
        msgs.push_back(Mutate(g.SerializeAsString()));
        return {"/kinetri.v1.KinetriService/GetSession", msgs};
      }
      case 4: {
        v1::ListSessionsRequest l;
        l.set_page_size(static_cast<int32_t>(rng_() % 2 ? rng_() % 5 : rng_()));
        l.set_page_token(rng_() % 2 ? SessionName() : "");
        msgs.push_back(Mutate(l.SerializeAsString()));
        return {"/kinetri.v1.KinetriService/ListSessions", msgs};
      }
      case 5: {
        v1::ExportTriangulationRequest e;
        e.set_session(SessionName());
        e.set_triangles_per_chunk(static_cast<uint32_t>(Count(10)));
        msgs.push_back(Mutate(e.SerializeAsString()));
        return {"/kinetri.v1.KinetriService/ExportTriangulation", msgs};
      }
      default: {
        v1::DeleteSessionRequest d;
        d.set_name(SessionName());
        msgs.push_back(Mutate(d.SerializeAsString()));
        return {"/kinetri.v1.KinetriService/DeleteSession", msgs};
      }
    }
  }

 private:
  std::mt19937_64 rng_;
};

using testing::SendRaw;

TEST(RequestFuzz, EveryCallEndsAndSessionsStayDelaunay) {
  // Parsing mutated strings makes protobuf log invalid UTF-8 by the
  // thousand; keep the test's output readable.
  google::protobuf::SetLogHandler(
      [](google::protobuf::LogLevel, const char*, int, const std::string&) {});
  ServerLimits limits;
  limits.max_sessions = 8;
  limits.max_points_per_session = 5000;
  limits.max_query_results = 100000;
  limits.default_threads = 2;
  SessionRegistry registry(limits);
  Metrics metrics;
  IdleWatchdog watchdog(std::chrono::seconds(5));
  MemoryBudget budget(256ull << 20);
  KinetriServiceImpl service(&registry, &metrics, &watchdog, &budget);
  grpc::ServerBuilder builder;
  int port = 0;
  builder.AddListeningPort("127.0.0.1:0", grpc::InsecureServerCredentials(),
                           &port);
  builder.RegisterService(&service);
  std::unique_ptr<grpc::Server> server = builder.BuildAndStart();
  ASSERT_TRUE(server && port > 0);
  auto channel = grpc::CreateChannel("127.0.0.1:" + std::to_string(port),
                                     grpc::InsecureChannelCredentials());
  grpc::GenericStub stub(channel);

  const char* seed_env = std::getenv("KINETRI_FUZZ_SEED");
  const uint64_t seed = seed_env ? std::strtoull(seed_env, nullptr, 10)
                                 : static_cast<uint64_t>(time(nullptr));
  const char* secs_env = std::getenv("KINETRI_FUZZ_SECONDS");
  const double seconds = secs_env ? std::atof(secs_env) : 20.0;
  std::printf("fuzz seed %llu for %.0f s (KINETRI_FUZZ_SEED to replay)\n",
              static_cast<unsigned long long>(seed), seconds);
  Fuzzer fuzz(seed);
  // A few valid sessions to aim at (sessions/f0 .. f3).
  std::mt19937_64 rng(seed);
  for (int s = 0; s < 4; ++s) {
    v1::CreateSessionRequest h, p;
    const int n = 20 + s * 20;
    h.mutable_header()->set_session_id("f" + std::to_string(s));
    h.mutable_header()->set_point_count(n);
    for (int i = 0; i < 2 * n; ++i) {
      p.mutable_points()->add_xy(std::uniform_real_distribution<double>()(rng));
    }
    ASSERT_TRUE(SendRaw(stub, "/kinetri.v1.KinetriService/CreateSession",
                        {h.SerializeAsString(), p.SerializeAsString()})
                    .ok());
  }
  const auto end = Clock::now() + std::chrono::duration_cast<Clock::duration>(
                                      std::chrono::duration<double>(seconds));
  int calls = 0, ok_calls = 0;
  std::map<int, int> codes;
  while (Clock::now() < end) {
    const auto [method, msgs] = fuzz.Call();
    const grpc::Status st = SendRaw(stub, method, msgs);
    ASSERT_NE(st.error_code(), grpc::StatusCode::DEADLINE_EXCEEDED)
        << "call " << calls << " (seed " << seed << ") to " << method
        << " did not end";
    ASSERT_NE(st.error_code(), grpc::StatusCode::UNKNOWN)
        << "call " << calls << " (seed " << seed << ") to " << method << ": "
        << st.error_message();
    ++codes[st.error_code()];
    ok_calls += st.ok();
    ++calls;
  }
  // Every session the calls left behind is a valid Delaunay triangulation.
  for (const auto& s : registry.List("", 100)) {
    const Session::Snapshot snap = s->Read();
    EXPECT_TRUE(snap.tri->Validate().ok()) << s->name();
  }
  std::printf("%d calls (%d OK); status codes:", calls, ok_calls);
  for (const auto& [code, count] : codes) std::printf(" %d:%d", code, count);
  std::printf("\n");
  EXPECT_GT(calls, 100);
  server->Shutdown(std::chrono::system_clock::now() + std::chrono::seconds(2));
}

}  // namespace
}  // namespace kinetri::server
