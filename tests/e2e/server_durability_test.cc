// Durable sessions (--data_dir) of the real kinetri-server: SIGKILL at
// random moments during creation, steps and compaction, then a restart
// checked against a client-side replay; fsync modes; corrupt and truncated
// files; a full disk.
#include <gtest/gtest.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <map>
#include <random>
#include <string>
#include <thread>
#include <vector>

#include "client/cpp/kinetri_client.h"
#include "tests/core/test_util.h"
#include "tests/e2e/server_process.h"

namespace kinetri {
namespace {

namespace fs = std::filesystem;
using Clock = std::chrono::steady_clock;

std::string TempDir() {
  char tmpl[] = "/tmp/kinetri-durable-XXXXXX";
  const char* d = mkdtemp(tmpl);
  return d ? d : "";
}

std::vector<core::Vec2> AsPoints(const std::vector<double>& xy) {
  std::vector<core::Vec2> p(xy.size() / 2);
  for (size_t i = 0; i < p.size(); ++i) p[i] = {xy[2 * i], xy[2 * i + 1]};
  return p;
}

// The session on the server equals the model: same step, same positions,
// and its triangles are CGAL's Delaunay triangulation of them.
void ExpectSession(Client& c, const std::string& name, uint64_t step,
                   const std::vector<double>& xy, const std::string& where) {
  auto s = c.GetSession(name);
  ASSERT_TRUE(s.ok()) << where << ": " << name << ": " << s.status();
  ASSERT_EQ(s->step(), step) << where << ": " << name;
  auto mesh = c.Export(name);
  ASSERT_TRUE(mesh.ok()) << where << ": " << mesh.status();
  ASSERT_EQ(mesh->xy, xy) << where << ": " << name << " positions";
  const auto pts = AsPoints(xy);
  ASSERT_EQ(testing::EdgesOfTriangles(pts, mesh->triangles),
            testing::CgalDelaunayEdges(pts))
      << where << ": " << name << " is not Delaunay";
}

class DurabilityTest : public ::testing::Test {
 protected:
  void SetUp() override { dir_ = TempDir(); }
  void TearDown() override {
    server_.reset();
    fs::remove_all(dir_);
  }
  void Start(const std::string& fsync, int snapshot_interval = 0,
             uint64_t max_file_bytes = 0) {
    server_ = std::make_unique<testing::ServerProcess>(
        KINETRI_SERVER_BINARY,
        std::vector<std::string>{
            "--data_dir=" + dir_, "--fsync=" + fsync, "--threads=2",
            "--snapshot_interval_steps=" + std::to_string(snapshot_interval)},
        max_file_bytes);
    ASSERT_TRUE(server_->ok());
    client_ = std::make_unique<Client>(server_->target(), 4000);
  }
  std::string dir_;
  std::unique_ptr<testing::ServerProcess> server_;
  std::unique_ptr<Client> client_;
};

struct Model {
  std::vector<double> xy;  // at `step`, acknowledged
  uint64_t step = 0;
  // A step sent but not acknowledged when the server died: it may or may
  // not be on disk.
  bool pending = false;
  std::vector<double> pending_xy;
};

// 24 SIGKILLs at random moments while sessions are created, stepped and
// compacted (a snapshot every 3 steps), fsync always: after each restart
// every acknowledged session and step is there, exactly.
TEST_F(DurabilityTest, KilledAtRandomMomentsLosesNoAcknowledgedStep) {
  std::map<std::string, Model> model;
  // Creations in flight when the server died: they may exist or not.
  std::map<std::string, std::vector<double>> maybe_created;
  std::mt19937_64 rng(20261123);
  int kills = 0, acked_steps = 0, acked_creations = 0;
  for (int round = 0; round < 24; ++round) {
    Start("always", 3);
    const std::string where = "after kill " + std::to_string(round);
    for (auto& [name, m] : model) {
      auto s = client_->GetSession(name);
      ASSERT_TRUE(s.ok()) << where << ": " << name << " lost";
      if (m.pending && s->step() == m.step + 1) {
        m.xy = m.pending_xy;
        m.step += 1;
      }
      m.pending = false;
      ExpectSession(*client_, name, m.step, m.xy, where);
    }
    for (auto& [name, xy] : maybe_created) {
      auto s = client_->GetSession(name);
      if (!s.ok()) {
        ASSERT_EQ(s.status().code(), absl::StatusCode::kNotFound) << where;
        continue;
      }
      ExpectSession(*client_, name, 0, xy, where);
      model[name] = Model{xy, 0, false, {}};
    }
    maybe_created.clear();
    if (HasFatalFailure()) return;

    // Work until the killer strikes (20..250 ms).
    std::atomic<bool> dead{false};
    const int delay_ms = 20 + static_cast<int>(rng() % 230);
    std::thread killer([&] {
      std::this_thread::sleep_for(std::chrono::milliseconds(delay_ms));
      server_->Kill();
      dead = true;
    });
    std::uniform_int_distribution<int> size(500, 2500);
    std::normal_distribution<double> g(0.0, 0.002);
    while (!dead) {
      if (model.size() < 12 && (model.size() < 6 || rng() % 8 == 0)) {
        const std::string name = "sessions/c" + std::to_string(round) + "-" +
                                 std::to_string(rng() % 100000);
        if (model.count(name) || maybe_created.count(name)) continue;
        const std::vector<double> xy = testing::UniformXY(size(rng), rng());
        maybe_created[name] = xy;
        auto s =
            client_->CreateSession(xy, v1::SessionOptions(), name.substr(9));
        if (!s.ok()) break;
        maybe_created.erase(name);
        model[name] = Model{xy, 0, false, {}};
        ++acked_creations;
        continue;
      }
      auto it = model.begin();
      std::advance(it, rng() % model.size());
      Model& m = it->second;
      auto stream = client_->OpenSteps(it->first);
      if (!stream.ok()) break;
      bool failed = false;
      for (int k = 0; k < 4 && !dead; ++k) {
        std::vector<double> d(m.xy.size());
        for (double& v : d) v = g(rng);
        m.pending_xy = m.xy;
        for (size_t i = 0; i < d.size(); ++i) m.pending_xy[i] += d[i];
        m.pending = true;
        auto ack = (*stream)->MoveBy(d);
        if (!ack.ok()) {
          failed = true;
          break;
        }
        ASSERT_EQ(ack->step(), m.step + 1);
        m.xy = m.pending_xy;
        m.step += 1;
        m.pending = false;
        ++acked_steps;
      }
      if (failed) break;
      (*stream)->Finish().IgnoreError();
    }
    killer.join();
    ++kills;
  }
  std::printf("%d kills, %d acknowledged creations, %d acknowledged steps\n",
              kills, acked_creations, acked_steps);
  EXPECT_GE(kills, 20);
  EXPECT_GT(acked_steps, 50);
}

// everysec: a kill loses at most about the last second of acknowledged
// steps; what comes back is an exact earlier step.
TEST_F(DurabilityTest, EverySecondLosesAtMostAboutOneSecond) {
  Start("everysec");
  const std::vector<double> start = testing::UniformXY(800, 5);
  ASSERT_TRUE(
      client_->CreateSession(start, v1::SessionOptions(), "everysec").ok());
  auto stream = client_->OpenSteps("sessions/everysec");
  ASSERT_TRUE(stream.ok());
  std::vector<std::vector<double>> history = {start};
  std::vector<Clock::time_point> acked_at = {Clock::now()};
  std::mt19937_64 rng(6);
  std::normal_distribution<double> g(0.0, 0.002);
  const auto until = Clock::now() + std::chrono::milliseconds(2500);
  while (Clock::now() < until) {
    std::vector<double> d(start.size());
    for (double& v : d) v = g(rng);
    auto ack = (*stream)->MoveBy(d);
    ASSERT_TRUE(ack.ok());
    std::vector<double> next = history.back();
    for (size_t i = 0; i < d.size(); ++i) next[i] += d[i];
    history.push_back(std::move(next));
    acked_at.push_back(Clock::now());
  }
  const auto killed_at = Clock::now();
  server_->Kill();
  uint64_t must_have = 0;  // the last step acknowledged 1.5 s before the kill
  for (size_t s = 0; s < acked_at.size(); ++s) {
    if (acked_at[s] + std::chrono::milliseconds(1500) <= killed_at) {
      must_have = s;
    }
  }
  Start("everysec");
  auto s = client_->GetSession("sessions/everysec");
  ASSERT_TRUE(s.ok());
  std::printf("acknowledged %zu steps, restored step %llu (at least %llu)\n",
              history.size() - 1, static_cast<unsigned long long>(s->step()),
              static_cast<unsigned long long>(must_have));
  EXPECT_GE(s->step(), must_have);
  ASSERT_LT(s->step(), history.size());
  ExpectSession(*client_, "sessions/everysec", s->step(), history[s->step()],
                "everysec");
}

// Points that joined and left survive restarts: replayed from the journal
// (with their client ids), and from snapshots (compaction every 2 steps),
// including a client-id session that has no point left.
TEST_F(DurabilityTest, JoinsAndLeavesAreRestored) {
  for (const int interval : {0, 2}) {
    SCOPED_TRACE(interval ? "snapshots" : "journal");
    Start("always", interval);
    std::vector<double> seq = testing::UniformXY(500, 8);
    ASSERT_TRUE(client_->CreateSession(seq, v1::SessionOptions(), "seq").ok());
    std::vector<double> cxy = testing::UniformXY(4, 9);
    std::vector<uint64_t> cid = {10, 11, 12, 13};
    ASSERT_TRUE(
        client_->CreateSessionWithIds(cxy, cid, v1::SessionOptions(), "cid")
            .ok());
    auto a = client_->OpenSteps("sessions/seq");
    auto b = client_->OpenSteps("sessions/cid");
    ASSERT_TRUE(a.ok() && b.ok());
    std::mt19937_64 rng(10);
    std::uniform_real_distribution<double> u(0, 1);
    for (int step = 1; step <= 5; ++step) {
      PointChanges ch;
      std::vector<uint8_t> gone(seq.size() / 2, 0);
      for (int k = 0; k < 20; ++k) {
        const uint32_t id = rng() % (seq.size() / 2);
        if (!gone[id]) ch.remove_ids.push_back(id);
        gone[id] = 1;
      }
      for (int k = 0; k < 30; ++k) ch.add_xy.push_back(u(rng));
      std::vector<double> next;
      for (size_t i = 0; i < gone.size(); ++i) {
        if (gone[i]) continue;
        next.push_back(seq[2 * i]);
        next.push_back(seq[2 * i + 1]);
      }
      next.insert(next.end(), ch.add_xy.begin(), ch.add_xy.end());
      ASSERT_TRUE((*a)->Change(ch).ok());
      seq = next;
    }
    // The client-id session: all four leave, two join, then one more.
    PointChanges ch;
    ch.remove_client_ids = {10, 11, 12, 13};
    ASSERT_TRUE((*b)->Change(ch).ok());
    ch = {};
    ch.add_xy = {0.5, 0.5, 0.25, 0.75};
    ch.add_client_ids = {13, 99};
    ASSERT_TRUE((*b)->Change(ch).ok());
    ch = {};
    ch.add_xy = {0.75, 0.25};
    ch.add_client_ids = {5};
    ASSERT_TRUE((*b)->Change(ch).ok());
    server_->Kill();
    Start("always", interval);
    ExpectSession(*client_, "sessions/seq", 5, seq, "restored");
    auto mesh = client_->Export("sessions/cid");
    ASSERT_TRUE(mesh.ok()) << mesh.status();
    EXPECT_EQ(mesh->xy,
              (std::vector<double>{0.5, 0.5, 0.25, 0.75, 0.75, 0.25}));
    EXPECT_EQ(mesh->point_ids, (std::vector<uint64_t>{13, 99, 5}));
    EXPECT_EQ(client_->GetSession("sessions/cid")->options().point_id_policy(),
              v1::POINT_ID_POLICY_CLIENT);
    // Empty, it is still a client-id session after a restart.
    b = client_->OpenSteps("sessions/cid");
    ch = {};
    ch.remove_client_ids = {13, 99, 5};
    ASSERT_TRUE((*b)->Change(ch).ok());
    ASSERT_TRUE((*b)->Finish().ok());
    client_.reset();                    // no open connection to drain
    ASSERT_TRUE(server_->Stop() == 0);  // drain: snapshot of the empty set
    Start("always", interval);
    auto s = client_->GetSession("sessions/cid");
    ASSERT_TRUE(s.ok()) << s.status();
    EXPECT_EQ(s->point_count(), 0u);
    EXPECT_EQ(s->options().point_id_policy(), v1::POINT_ID_POLICY_CLIENT);
    b = client_->OpenSteps("sessions/cid");
    ch = {};
    ch.add_xy = {0.5, 0.5};
    ch.add_client_ids = {77};
    auto ack = (*b)->Change(ch);
    ASSERT_TRUE(ack.ok()) << ack.status();
    EXPECT_EQ(client_->Export("sessions/cid")->point_ids,
              std::vector<uint64_t>{77});
    ASSERT_TRUE((*b)->Finish().ok());
    client_.reset();
    server_.reset();
    fs::remove_all(dir_);
    dir_ = TempDir();
  }
}

// A truncated journal is cut at its last whole record; a corrupt snapshot
// makes only that session unavailable (DATA_LOSS) until it is deleted.
TEST_F(DurabilityTest, CorruptAndTruncatedFiles) {
  Start("always", 1000);
  std::map<std::string, std::vector<double>> xy;
  for (const std::string id : {"keep", "cut", "bad"}) {
    xy[id] = testing::UniformXY(600, id.size());
    ASSERT_TRUE(client_->CreateSession(xy[id], v1::SessionOptions(), id).ok());
  }
  std::vector<double> cut_before_last;
  {
    auto stream = client_->OpenSteps("sessions/cut");
    ASSERT_TRUE(stream.ok());
    for (int s = 0; s < 3; ++s) {
      if (s == 2) cut_before_last = xy["cut"];
      std::vector<double> d(1200, 0.001 * (s + 1));
      ASSERT_TRUE((*stream)->MoveBy(d).ok());
      for (size_t i = 0; i < d.size(); ++i) xy["cut"][i] += d[i];
    }
  }
  // A crash (a clean stop would snapshot the journal away).
  server_->Kill();
  const std::string sessions = dir_ + "/sessions/";
  fs::resize_file(sessions + "@cut/journal",
                  fs::file_size(sessions + "@cut/journal") - 5);
  {
    std::fstream f(sessions + "@bad/snapshot",
                   std::ios::in | std::ios::out | std::ios::binary);
    f.seekp(200);
    f.put('\x5a');
  }
  Start("always", 1000);
  ExpectSession(*client_, "sessions/keep", 0, xy["keep"], "keep");
  ExpectSession(*client_, "sessions/cut", 2, cut_before_last, "cut");
  auto bad = client_->GetSession("sessions/bad");
  EXPECT_EQ(bad.status().code(), absl::StatusCode::kDataLoss) << bad.status();
  EXPECT_NE(bad.status().message().find("corrupt"), std::string::npos);
  EXPECT_EQ(client_->NearestOfAll("sessions/bad").status().code(),
            absl::StatusCode::kDataLoss);
  const std::string metrics =
      testing::HttpGet(server_->metrics_port(), "/metrics");
  EXPECT_NE(metrics.find("kinetri_restore{what=\"unavailable\"} 1"),
            std::string::npos)
      << metrics;
  EXPECT_EQ(metrics.find("kinetri_restore{what=\"journal_bytes_cut\"} 0"),
            std::string::npos);
  // Deleting drops the broken files; the name can be used again.
  EXPECT_TRUE(client_->DeleteSession("sessions/bad").ok());
  EXPECT_EQ(client_->GetSession("sessions/bad").status().code(),
            absl::StatusCode::kNotFound);
  EXPECT_TRUE(
      client_->CreateSession(xy["keep"], v1::SessionOptions(), "bad").ok());
}

// A full disk (here: a file-size limit) refuses the step with a clear
// status and the session stays at its previous step; queries go on.
TEST_F(DurabilityTest, FullDiskRefusesTheStepAndKeepsTheSession) {
  Start("always", 100000, /*max_file_bytes=*/300000);
  std::vector<double> xy = testing::UniformXY(1000, 7);
  ASSERT_TRUE(client_->CreateSession(xy, v1::SessionOptions(), "full").ok());
  auto stream = client_->OpenSteps("sessions/full");
  ASSERT_TRUE(stream.ok());
  uint64_t acked = 0;
  absl::Status refused;
  for (int s = 0; s < 100; ++s) {
    std::vector<double> d(2000, 1e-4);
    auto ack = (*stream)->MoveBy(d);
    if (!ack.ok()) {
      refused = ack.status();
      break;
    }
    for (size_t i = 0; i < d.size(); ++i) xy[i] += d[i];
    ++acked;
  }
  ASSERT_FALSE(refused.ok()) << "the journal never filled the disk";
  EXPECT_EQ(refused.code(), absl::StatusCode::kResourceExhausted) << refused;
  EXPECT_NE(refused.message().find("not applied"), std::string::npos);
  EXPECT_GT(acked, 3u);
  ExpectSession(*client_, "sessions/full", acked, xy, "disk full");
  EXPECT_TRUE(client_->NearestOfAll("sessions/full").ok());
  // Once restarted (the same files), the session is exactly there.
  server_->Kill();
  Start("always", 100000);
  ExpectSession(*client_, "sessions/full", acked, xy, "after restart");
}

// Idle expiry: a session no call touches for its TTL is deleted (files
// too); touching it keeps it; GetSession shows when it expires; sessions
// without a TTL stay; the count is a metric.
TEST_F(DurabilityTest, IdleSessionsExpire) {
  Start("always");
  v1::SessionOptions ttl;
  ttl.set_idle_ttl_seconds(2);
  ASSERT_TRUE(
      client_->CreateSession(testing::UniformXY(200, 8), ttl, "short").ok());
  ASSERT_TRUE(client_
                  ->CreateSession(testing::UniformXY(200, 9),
                                  v1::SessionOptions(), "forever")
                  .ok());
  auto s = client_->GetSession("sessions/short");
  ASSERT_TRUE(s.ok());
  EXPECT_EQ(s->options().idle_ttl_seconds(), 2u);
  ASSERT_TRUE(s->has_expire_time());
  const int64_t now_s = absl::ToUnixSeconds(absl::Now());
  EXPECT_NEAR(static_cast<double>(s->expire_time().seconds()),
              static_cast<double>(now_s + 2), 1.5);
  EXPECT_FALSE(client_->GetSession("sessions/forever")->has_expire_time());
  // Touched every 0.5 s for 4 s: still there.
  for (int i = 0; i < 8; ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(500));
    ASSERT_TRUE(client_->NearestOfAll("sessions/short").ok()) << i;
  }
  // Left alone: gone within TTL + the once-a-second sweep.
  std::this_thread::sleep_for(std::chrono::milliseconds(3500));
  EXPECT_EQ(client_->GetSession("sessions/short").status().code(),
            absl::StatusCode::kNotFound);
  EXPECT_TRUE(client_->GetSession("sessions/forever").ok());
  EXPECT_FALSE(fs::exists(dir_ + "/sessions/@short"));
  EXPECT_TRUE(fs::exists(dir_ + "/sessions/@forever"));
  EXPECT_NE(testing::HttpGet(server_->metrics_port(), "/metrics")
                .find("kinetri_sessions_expired_total 1"),
            std::string::npos);
}

}  // namespace
}  // namespace kinetri
