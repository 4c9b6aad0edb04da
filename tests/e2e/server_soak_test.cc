// Soak: several clients mix creations, steps, queries, deletions, abandoned
// calls and dropped connections against one server for a bounded time
// (KINETRI_SOAK_SECONDS, default 45). Each client keeps a replica of its
// sessions (positions and step number, updated only by acknowledged steps);
// at the end every surviving session is exported and checked exactly: the
// same positions and step number as the replica, and the exported
// triangulation equal to CGAL's Delaunay triangulation of the replica.
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include <atomic>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <map>
#include <memory>
#include <mutex>
#include <random>
#include <string>
#include <thread>
#include <vector>

#include "client/cpp/kinetri_client.h"
#include "tests/core/test_util.h"
#include "tests/e2e/server_process.h"

namespace kinetri {
namespace {

using Clock = std::chrono::steady_clock;

struct Replica {
  std::vector<double> xy;
  uint64_t step = 0;
};

struct Tally {
  std::atomic<int> creates{0}, steps{0}, queries{0}, deletes{0},
      abandoned_steps{0}, abandoned_queries{0}, dropped_connections{0},
      errors{0};
};

double SoakSeconds() {
  const char* s = std::getenv("KINETRI_SOAK_SECONDS");
  return s ? std::atof(s) : 45.0;
}

// One client's loop; its sessions are named soak-<worker>-<k>.
void Worker(const std::string& target, int worker, Clock::time_point end,
            Tally* tally, std::map<std::string, Replica>* out,
            std::string* failure) {
  std::mt19937_64 rng(1000 + worker);
  std::uniform_real_distribution<double> u(0, 1);
  auto client = std::make_unique<Client>(target, 1024);
  std::map<std::string, Replica> mine;
  int next = 0;
  auto fail = [&](const std::string& what, const absl::Status& s) {
    if (failure->empty()) *failure = what + ": " + s.ToString();
    ++tally->errors;
  };
  while (Clock::now() < end && failure->empty()) {
    const int action = static_cast<int>(rng() % 100);
    // Create (at most 10 sessions per client: 5 clients stay under the
    // server's --max_sessions=64).
    if (mine.empty() || (action < 8 && mine.size() < 10)) {
      const size_t n = 200 + rng() % 3000;
      Replica r;
      r.xy.resize(2 * n);
      for (double& v : r.xy) v = u(rng);
      const std::string id =
          "soak-" + std::to_string(worker) + "-" + std::to_string(next++);
      auto s = client->CreateSession(r.xy, v1::SessionOptions(), id);
      if (!s.ok()) {
        fail("create " + id, s.status());
        continue;
      }
      mine["sessions/" + id] = std::move(r);
      ++tally->creates;
      continue;
    }
    auto it = mine.begin();
    std::advance(it, rng() % mine.size());
    const std::string& name = it->first;
    Replica& rep = it->second;
    const size_t n = rep.xy.size() / 2;
    if (action < 45) {  // a few acknowledged steps
      auto st = client->OpenSteps(name);
      if (!st.ok()) {
        fail("open " + name, st.status());
        continue;
      }
      const int k = 1 + static_cast<int>(rng() % 3);
      const double sigma = (rng() % 2 ? 0.1 : 1.0) / std::sqrt(double(n));
      std::normal_distribution<double> g(0, sigma);
      for (int i = 0; i < k; ++i) {
        std::vector<double> d(2 * n);
        for (double& v : d) v = g(rng);
        auto ack = (*st)->MoveBy(d);
        if (!ack.ok()) {
          fail("step " + name, ack.status());
          break;
        }
        for (size_t j = 0; j < d.size(); ++j) rep.xy[j] += d[j];
        rep.step = ack->step();
        ++tally->steps;
      }
      (void)(*st)->Finish();
    } else if (action < 70) {  // a query checked against the replica
      v1::QueryRequest q;
      q.set_session(name);
      q.set_kind(v1::QUERY_KIND_NEAREST);
      q.set_exclude_self(true);
      const uint32_t probe = static_cast<uint32_t>(rng() % n);
      q.mutable_point_ids()->add_ids(probe);
      auto res = client->Query(q);
      if (!res.ok()) {
        fail("query " + name, res.status());
        continue;
      }
      if (res->step != rep.step || res->ids.size() != 1) {
        *failure = "query of " + name + " saw step " +
                   std::to_string(res->step) + ", replica at " +
                   std::to_string(rep.step);
        continue;
      }
      double best = 1e300;
      for (size_t j = 0; j < n; ++j) {
        if (j == probe) continue;
        const double dx = rep.xy[2 * j] - rep.xy[2 * probe];
        const double dy = rep.xy[2 * j + 1] - rep.xy[2 * probe + 1];
        best = std::min(best, dx * dx + dy * dy);
      }
      const uint32_t got = res->ids[0];
      const double gx = rep.xy[2 * got] - rep.xy[2 * probe];
      const double gy = rep.xy[2 * got + 1] - rep.xy[2 * probe + 1];
      if (gx * gx + gy * gy != best) {
        *failure = "wrong nearest neighbour in " + name;
      }
      ++tally->queries;
    } else if (action < 78) {  // a step abandoned before end_of_step
      grpc::ClientContext ctx;
      auto stream = client->stub()->StreamSteps(&ctx);
      v1::StepRequest req;
      req.set_session(name);
      req.set_step(rep.step + 1);
      for (size_t j = 0; j < n; ++j) req.add_xy(0.5 / std::sqrt(double(n)));
      stream->Write(req);  // half the step, then the client goes away
      ctx.TryCancel();
      (void)stream->Finish();
      ++tally->abandoned_steps;
    } else if (action < 86) {  // a big query abandoned after one chunk
      grpc::ClientContext ctx;
      v1::QueryRequest q;
      q.set_session(name);
      q.set_kind(v1::QUERY_KIND_RADIUS);
      q.set_radius(0.2);
      q.mutable_all_points();
      q.set_rows_per_chunk(16);
      auto reader = client->stub()->Query(&ctx, q);
      v1::QueryResponse chunk;
      reader->Read(&chunk);
      ctx.TryCancel();
      (void)reader->Finish();
      ++tally->abandoned_queries;
    } else if (action < 92) {  // drop the connection, open a new one
      client = std::make_unique<Client>(target, 1024);
      ++tally->dropped_connections;
    } else {  // delete
      const absl::Status s = client->DeleteSession(name);
      if (!s.ok()) {
        fail("delete " + name, s);
        continue;
      }
      mine.erase(it);
      ++tally->deletes;
    }
  }
  *out = std::move(mine);
}

TEST(Soak, MixedLoadLosesNothing) {
  testing::ServerProcess server(
      KINETRI_SERVER_BINARY,
      {"--threads=2", "--max_sessions=64", "--stream_idle_timeout_seconds=30"});
  ASSERT_TRUE(server.ok());
  const int kWorkers = 5;
  const double seconds = SoakSeconds();
  const auto end = Clock::now() + std::chrono::duration_cast<Clock::duration>(
                                      std::chrono::duration<double>(seconds));
  Tally tally;
  std::vector<std::map<std::string, Replica>> replicas(kWorkers);
  std::vector<std::string> failures(kWorkers);
  std::vector<std::thread> threads;
  for (int w = 0; w < kWorkers; ++w) {
    threads.emplace_back(Worker, server.target(), w, end, &tally, &replicas[w],
                         &failures[w]);
  }
  for (auto& t : threads) t.join();
  for (int w = 0; w < kWorkers; ++w) {
    EXPECT_TRUE(failures[w].empty()) << "worker " << w << ": " << failures[w];
  }
  // Every surviving session: exactly the replica, and Delaunay.
  Client client(server.target());
  size_t checked = 0;
  for (const auto& mine : replicas) {
    for (const auto& [name, rep] : mine) {
      auto mesh = client.Export(name);
      ASSERT_TRUE(mesh.ok()) << name << ": " << mesh.status();
      EXPECT_EQ(mesh->step, rep.step) << name;
      ASSERT_EQ(mesh->xy, rep.xy) << name;
      std::vector<core::Vec2> pts(rep.xy.size() / 2);
      for (size_t i = 0; i < pts.size(); ++i) {
        pts[i] = {rep.xy[2 * i], rep.xy[2 * i + 1]};
      }
      EXPECT_EQ(testing::EdgesOfTriangles(pts, mesh->triangles),
                testing::CgalDelaunayEdges(pts))
          << name;
      ++checked;
    }
  }
  auto list = client.ListSessions();
  ASSERT_TRUE(list.ok());
  EXPECT_EQ(list->size(), checked);  // nothing stale left behind
  std::printf(
      "soak %.0f s, %d clients: %d creates, %d steps, %d checked queries, %d "
      "deletes, %d abandoned steps, %d abandoned queries, %d dropped "
      "connections; %zu sessions exported and checked exactly\n",
      seconds, kWorkers, tally.creates.load(), tally.steps.load(),
      tally.queries.load(), tally.deletes.load(), tally.abandoned_steps.load(),
      tally.abandoned_queries.load(), tally.dropped_connections.load(),
      checked);
  EXPECT_EQ(tally.errors.load(), 0);
  EXPECT_GT(tally.steps.load(), 0);
}

}  // namespace
}  // namespace kinetri
