// Many servers behind one address: three kinetri-server replicas (TLS,
// tokens, durable sessions) behind HAProxy running deploy/proxy/haproxy.cfg
// itself, with only the addresses and certificate paths changed for
// loopback. Sessions are created, stepped and queried through the proxy;
// each lives on exactly one replica; a replica killed with SIGKILL makes
// only its own sessions unavailable, and after a restart with its data
// directory they come back where they were.
#include <arpa/inet.h>
#include <gtest/gtest.h>
#include <netinet/in.h>
#include <signal.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <map>
#include <memory>
#include <random>
#include <regex>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "client/cpp/kinetri_client.h"
#include "tests/core/test_util.h"
#include "tests/e2e/server_process.h"

namespace kinetri {
namespace {

namespace fs = std::filesystem;

constexpr int kReplicas = 3;
constexpr int kSessions = 30;
constexpr int kPoints = 300;
constexpr char kToken[] = "replica-test-token-0123456789";

std::string Haproxy() {
  for (const char* p : {"/usr/sbin/haproxy", "/usr/local/sbin/haproxy"}) {
    if (access(p, X_OK) == 0) return p;
  }
  return "";
}

// A loopback port nobody listens on now.
int FreePort() {
  const int fd = socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in a{};
  a.sin_family = AF_INET;
  a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  socklen_t len = sizeof a;
  int port = 0;
  if (bind(fd, reinterpret_cast<sockaddr*>(&a), sizeof a) == 0 &&
      getsockname(fd, reinterpret_cast<sockaddr*>(&a), &len) == 0) {
    port = ntohs(a.sin_port);
  }
  close(fd);
  return port;
}

bool Accepts(int port) {
  const int fd = socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in a{};
  a.sin_family = AF_INET;
  a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  a.sin_port = htons(static_cast<uint16_t>(port));
  const bool ok = connect(fd, reinterpret_cast<sockaddr*>(&a), sizeof a) == 0;
  close(fd);
  return ok;
}

std::vector<core::Vec2> AsPoints(const std::vector<double>& xy) {
  std::vector<core::Vec2> p(xy.size() / 2);
  for (size_t i = 0; i < p.size(); ++i) p[i] = {xy[2 * i], xy[2 * i + 1]};
  return p;
}

// What the client knows of a session: its step and positions.
struct Model {
  std::string name;
  uint64_t step = 0;
  std::vector<double> xy;
  int owner = -1;
};

class ReplicasTest : public ::testing::Test {
 protected:
  void SetUp() override {
    haproxy_ = Haproxy();
    if (haproxy_.empty()) {
      GTEST_SKIP() << "haproxy is not installed (scripts/setup.sh installs "
                      "it)";
    }
    char tmpl[] = "/tmp/kinetri-replicas-XXXXXX";
    ASSERT_NE(mkdtemp(tmpl), nullptr);
    dir_ = tmpl;
    const std::string certs = dir_ + "/tls";
    ASSERT_EQ(std::system(("bash " KINETRI_SOURCE_DIR
                           "/tests/e2e/make_test_certs.sh " +
                           certs)
                              .c_str()),
              0);
    // The file names of deploy/proxy/haproxy.cfg (a Kubernetes TLS secret
    // plus the CA).
    fs::copy_file(certs + "/server.pem", certs + "/tls.crt");
    fs::copy_file(certs + "/server.key", certs + "/tls.key");
    fs::copy_file(certs + "/ca.pem", certs + "/ca.crt");
    std::ofstream(dir_ + "/tokens") << kToken << " sim\n";
    for (int i = 0; i < kReplicas; ++i) {
      ports_[i] = FreePort();
      fs::create_directories(DataDir(i));
      StartReplica(i);
    }
    StartProxy();
    ClientSecurity security;
    security.token = kToken;
    security.ca_file = dir_ + "/tls/ca.pem";
    proxy_ = std::make_unique<Client>(
        "127.0.0.1:" + std::to_string(proxy_port_), 4096, security);
    for (int i = 0; i < kReplicas; ++i) {
      direct_[i] = std::make_unique<Client>(
          "127.0.0.1:" + std::to_string(ports_[i]), 4096, security);
    }
  }

  void TearDown() override {
    proxy_.reset();
    for (auto& d : direct_) d.reset();
    if (proxy_pid_ > 0) {
      kill(proxy_pid_, SIGTERM);
      waitpid(proxy_pid_, nullptr, 0);
    }
    for (auto& r : replicas_) r.reset();
    if (!dir_.empty()) fs::remove_all(dir_);
  }

  std::string DataDir(int i) const {
    return dir_ + "/data" + std::to_string(i);
  }

  void StartReplica(int i) {
    replicas_[i] = std::make_unique<testing::ServerProcess>(
        KINETRI_SERVER_BINARY,
        std::vector<std::string>{
            "--listen=127.0.0.1:" + std::to_string(ports_[i]),
            "--tls_cert=" + dir_ + "/tls/tls.crt",
            "--tls_key=" + dir_ + "/tls/tls.key",
            "--auth_tokens_file=" + dir_ + "/tokens",
            "--data_dir=" + DataDir(i), "--fsync=always", "--threads=1"});
    ASSERT_TRUE(replicas_[i]->ok()) << "replica " << i << " did not start";
  }

  // deploy/proxy/haproxy.cfg with loopback addresses and the test's
  // certificates; nothing else changes.
  void StartProxy() {
    std::ifstream in(KINETRI_SOURCE_DIR "/deploy/proxy/haproxy.cfg");
    ASSERT_TRUE(in) << "deploy/proxy/haproxy.cfg";
    std::stringstream text;
    text << in.rdbuf();
    std::string cfg = text.str();
    proxy_port_ = FreePort();
    cfg =
        std::regex_replace(cfg, std::regex("/etc/kinetri/tls"), dir_ + "/tls");
    cfg = std::regex_replace(cfg, std::regex("bind :50051"),
                             "bind 127.0.0.1:" + std::to_string(proxy_port_));
    for (int i = 0; i < kReplicas; ++i) {
      const std::regex server("kinetri-" + std::to_string(i) +
                              "\\.\\$\\{KINETRI_REPLICA_DOMAIN\\}:50051");
      ASSERT_TRUE(std::regex_search(cfg, server)) << "replica " << i;
      cfg = std::regex_replace(cfg, server,
                               "127.0.0.1:" + std::to_string(ports_[i]));
    }
    const std::string path = dir_ + "/haproxy.cfg";
    std::ofstream(path) << cfg;
    proxy_pid_ = fork();
    if (proxy_pid_ == 0) {
      const std::string log = dir_ + "/haproxy.log";
      freopen(log.c_str(), "w", stdout);
      freopen(log.c_str(), "a", stderr);
      execl(haproxy_.c_str(), "haproxy", "-db", "-f", path.c_str(),
            static_cast<char*>(nullptr));
      _exit(127);
    }
    for (int i = 0; i < 200 && !Accepts(proxy_port_); ++i) {
      std::this_thread::sleep_for(std::chrono::milliseconds(25));
    }
    ASSERT_TRUE(Accepts(proxy_port_))
        << "haproxy did not start; see " << dir_ << "/haproxy.log";
  }

  // The replicas that have `name` (directly, not through the proxy).
  std::vector<int> Owners(const std::string& name) {
    std::vector<int> owners;
    for (int i = 0; i < kReplicas; ++i) {
      if (!replicas_[i]) continue;
      auto s = direct_[i]->GetSession(name);
      if (s.ok()) {
        owners.push_back(i);
      } else {
        EXPECT_EQ(s.status().code(), absl::StatusCode::kNotFound)
            << name << " on replica " << i << ": " << s.status();
      }
    }
    return owners;
  }

  // One step of small random moves through the proxy, mirrored in `m`.
  void Step(Model& m, std::mt19937_64& rng) {
    std::normal_distribution<double> d(0.0, 0.002);
    std::vector<double> dxy(m.xy.size());
    for (double& v : dxy) v = d(rng);
    auto steps = proxy_->OpenSteps(m.name);
    ASSERT_TRUE(steps.ok()) << m.name << ": " << steps.status();
    auto r = (*steps)->MoveBy(dxy);
    ASSERT_TRUE(r.ok()) << m.name << ": " << r.status();
    ASSERT_TRUE((*steps)->Finish().ok());
    for (size_t i = 0; i < dxy.size(); ++i) m.xy[i] += dxy[i];
    ++m.step;
    ASSERT_EQ(r->step(), m.step);
  }

  // The session, read through the proxy, is the model: same step, same
  // positions, CGAL's Delaunay triangulation, nearest neighbours answered.
  void Expect(const Model& m, const std::string& where) {
    auto s = proxy_->GetSession(m.name);
    ASSERT_TRUE(s.ok()) << where << ": " << m.name << ": " << s.status();
    ASSERT_EQ(s->step(), m.step) << where << ": " << m.name;
    auto mesh = proxy_->Export(m.name);
    ASSERT_TRUE(mesh.ok()) << where << ": " << mesh.status();
    ASSERT_EQ(mesh->xy, m.xy) << where << ": " << m.name << " positions";
    const auto pts = AsPoints(m.xy);
    ASSERT_EQ(testing::EdgesOfTriangles(pts, mesh->triangles),
              testing::CgalDelaunayEdges(pts))
        << where << ": " << m.name << " is not Delaunay";
    auto nn = proxy_->NearestOfAll(m.name);
    ASSERT_TRUE(nn.ok()) << where << ": " << nn.status();
    ASSERT_EQ(nn->rows(), pts.size());
    ASSERT_EQ(nn->step, m.step);
  }

  std::string haproxy_;
  std::string dir_;
  int ports_[kReplicas] = {};
  int proxy_port_ = 0;
  pid_t proxy_pid_ = -1;
  std::unique_ptr<testing::ServerProcess> replicas_[kReplicas];
  std::unique_ptr<Client> proxy_;
  std::unique_ptr<Client> direct_[kReplicas];
};

TEST_F(ReplicasTest, SessionsLiveOnTheirOwnerAndSurviveItsRestart) {
  std::mt19937_64 rng(7);
  std::vector<Model> sessions(kSessions);
  v1::SessionOptions options;
  for (int i = 0; i < kSessions; ++i) {
    Model& m = sessions[i];
    m.xy = testing::UniformXY(kPoints, 100 + i);
    // Every third session is named by the client library, the rest by the
    // caller: both are routed by the same key from their creation on.
    const std::string id = i % 3 == 0 ? "" : "sim-" + std::to_string(i);
    auto s = proxy_->CreateSession(m.xy, options, id);
    ASSERT_TRUE(s.ok()) << i << ": " << s.status();
    m.name = s->name();
    if (!id.empty()) {
      ASSERT_EQ(m.name, "sessions/" + id);
    }
    for (int k = 0; k < 2; ++k) Step(m, rng);
  }

  // Each session is on exactly one replica, and the sessions are spread.
  std::map<int, int> per_replica;
  for (Model& m : sessions) {
    const std::vector<int> owners = Owners(m.name);
    ASSERT_EQ(owners.size(), 1u) << m.name;
    m.owner = owners[0];
    ++per_replica[m.owner];
    Expect(m, "before the kill");
  }
  ASSERT_GE(per_replica.size(), 2u) << "the proxy did not spread sessions";
  for (const auto& [replica, count] : per_replica) {
    std::printf("replica %d owns %d sessions\n", replica, count);
  }

  // SIGKILL the replica with the most sessions.
  int victim = per_replica.begin()->first;
  for (const auto& [replica, count] : per_replica) {
    if (count > per_replica[victim]) victim = replica;
  }
  replicas_[victim]->Kill();
  replicas_[victim].reset();
  int others = 0;
  int unavailable = 0;
  for (Model& m : sessions) {
    // (The proxy tries a dead owner twice, a second apart: three are
    // enough.)
    if (m.owner == victim && ++unavailable <= 3) {
      // Unavailable, never re-created elsewhere.
      auto s = proxy_->GetSession(m.name);
      ASSERT_FALSE(s.ok()) << m.name;
      EXPECT_EQ(s.status().code(), absl::StatusCode::kUnavailable)
          << s.status();
      auto steps = proxy_->OpenSteps(m.name);
      EXPECT_FALSE(steps.ok());
    } else if (m.owner != victim) {
      // The others never notice.
      Step(m, rng);
      Expect(m, "while a replica is down");
      ++others;
    }
  }
  EXPECT_GT(others, 0);
  for (Model& m : sessions) {
    EXPECT_EQ(Owners(m.name).size(), m.owner == victim ? 0u : 1u) << m.name;
  }

  // Restarted with its data directory (same address), its sessions are
  // back at their last acknowledged step (fsync=always).
  StartReplica(victim);
  for (Model& m : sessions) {
    const std::vector<int> owners = Owners(m.name);
    ASSERT_EQ(owners, std::vector<int>{m.owner}) << m.name;
    Expect(m, "after the restart");
    Step(m, rng);
    Expect(m, "stepped after the restart");
  }
  // Deleting through the proxy reaches the owner.
  ASSERT_TRUE(proxy_->DeleteSession(sessions[0].name).ok());
  EXPECT_TRUE(Owners(sessions[0].name).empty());
}

// SIGTERM drains, then writes a snapshot of every session with journaled
// steps: the journals are empty and a restart replays nothing.
TEST_F(ReplicasTest, ShutdownWritesSnapshots) {
  std::mt19937_64 rng(11);
  Model m;
  m.xy = testing::UniformXY(kPoints, 5);
  auto s = proxy_->CreateSession(m.xy, {}, "drained");
  ASSERT_TRUE(s.ok()) << s.status();
  m.name = s->name();
  for (int k = 0; k < 3; ++k) Step(m, rng);
  const std::vector<int> owners = Owners(m.name);
  ASSERT_EQ(owners.size(), 1u);
  const int owner = owners[0];
  const fs::path journal =
      fs::path(DataDir(owner)) / "sessions" / "sim@drained" / "journal";
  ASSERT_TRUE(fs::exists(journal));
  EXPECT_GT(fs::file_size(journal), 0u);
  // Idle client connections hold a server's shutdown for seconds.
  for (auto& d : direct_) d.reset();
  EXPECT_EQ(replicas_[owner]->Stop(), 0);
  replicas_[owner].reset();
  EXPECT_EQ(fs::file_size(journal), 0u) << "no snapshot at shutdown";
  StartReplica(owner);
  Expect(m, "after a drained restart");
}

}  // namespace
}  // namespace kinetri
