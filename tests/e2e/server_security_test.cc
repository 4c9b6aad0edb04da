// Security of the real kinetri-server: TLS (and mutual TLS) with
// certificates made at test time by openssl, bearer tokens, tenants,
// token-file reload, unguessable ids and protected mode (docs/SECURITY.md).
#include <grpcpp/generic/generic_stub.h>
#include <gtest/gtest.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cstdlib>
#include <fstream>
#include <regex>
#include <string>
#include <thread>
#include <vector>

#include "client/cpp/kinetri_client.h"
#include "tests/e2e/server_process.h"

namespace kinetri {
namespace {

constexpr char kTokenA[] = "alpha-token-0123456789abcdef";
constexpr char kTokenB[] = "beta-token-0123456789abcdef";
constexpr char kTokenC[] = "gamma-token-0123456789abcdef";
constexpr char kTokenD[] = "delta-token-0123456789abcdef";

std::string TempDir() {
  char tmpl[] = "/tmp/kinetri-security-XXXXXX";
  const char* d = mkdtemp(tmpl);
  return d ? d : "";
}

void WriteFile(const std::string& path, const std::string& text) {
  std::ofstream(path) << text;
}

class SecurityTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    dir_ = new std::string(TempDir());
    ASSERT_FALSE(dir_->empty());
    const std::string cmd = std::string("bash ") + KINETRI_SOURCE_DIR +
                            "/tests/e2e/make_test_certs.sh " + *dir_;
    ASSERT_EQ(std::system(cmd.c_str()), 0) << cmd;
  }
  static void TearDownTestSuite() {
    std::system(("rm -rf " + *dir_).c_str());
    delete dir_;
  }
  static std::string File(const std::string& name) {
    return *dir_ + "/" + name;
  }
  // A TLS server with tokens for tenants alpha and beta (beta: at most one
  // session); mutual TLS when `mutual`.
  void StartServer(bool mutual, const std::string& device = "none") {
    WriteFile(File("tokens"), std::string("# test tokens\n") + kTokenA +
                                  " alpha\n" + kTokenB + " beta sessions=1\n" +
                                  kTokenD + " delta memory_mb=1\n");
    std::vector<std::string> flags = {
        "--tls_cert=" + File("server.pem"), "--tls_key=" + File("server.key"),
        "--auth_tokens_file=" + File("tokens"), "--tls_reload_seconds=1",
        "--device=" + device};
    if (mutual) flags.push_back("--tls_client_ca=" + File("ca.pem"));
    server_ =
        std::make_unique<testing::ServerProcess>(KINETRI_SERVER_BINARY, flags);
    ASSERT_TRUE(server_->ok());
  }
  ClientSecurity Secure(const std::string& token, bool client_cert = false) {
    ClientSecurity s;
    s.token = token;
    s.ca_file = File("ca.pem");
    if (client_cert) {
      s.cert_file = File("client.pem");
      s.key_file = File("client.key");
    }
    return s;
  }
  std::unique_ptr<Client> Connect(const ClientSecurity& s) {
    return std::make_unique<Client>(server_->target(), 1000, s);
  }

  static std::string* dir_;
  std::unique_ptr<testing::ServerProcess> server_;
};
std::string* SecurityTest::dir_ = nullptr;

TEST_F(SecurityTest, TlsRefusesPlaintextAndTheWrongCa) {
  StartServer(/*mutual=*/false);
  auto plain = Connect(ClientSecurity{.token = kTokenA});
  EXPECT_EQ(plain->ListSessions().status().code(),
            absl::StatusCode::kUnavailable);
  ClientSecurity wrong = Secure(kTokenA);
  wrong.ca_file = File("other_ca.pem");
  EXPECT_EQ(Connect(wrong)->ListSessions().status().code(),
            absl::StatusCode::kUnavailable);
  EXPECT_TRUE(Connect(Secure(kTokenA))->ListSessions().ok());
}

TEST_F(SecurityTest, MutualTlsNeedsAClientCertificateFromTheCa) {
  StartServer(/*mutual=*/true);
  EXPECT_EQ(Connect(Secure(kTokenA))->ListSessions().status().code(),
            absl::StatusCode::kUnavailable);
  ClientSecurity foreign = Secure(kTokenA, true);
  foreign.cert_file = File("other_client.pem");
  foreign.key_file = File("other_client.key");
  EXPECT_EQ(Connect(foreign)->ListSessions().status().code(),
            absl::StatusCode::kUnavailable);
  EXPECT_TRUE(Connect(Secure(kTokenA, true))->ListSessions().ok());
}

TEST_F(SecurityTest, EveryCallNeedsAValidToken) {
  StartServer(false);
  auto owner = Connect(Secure(kTokenA));
  auto made = owner->CreateSession(testing::UniformXY(300, 1),
                                   v1::SessionOptions(), "mine");
  ASSERT_TRUE(made.ok()) << made.status();
  for (const std::string& token :
       {std::string(), std::string("not-a-token-0123456789"),
        std::string(kTokenA) + "x"}) {
    auto c = Connect(Secure(token));
    const auto unauth = absl::StatusCode::kUnauthenticated;
    EXPECT_EQ(c->ListSessions().status().code(), unauth);
    EXPECT_EQ(c->GetSession("sessions/mine").status().code(), unauth);
    EXPECT_EQ(c->CreateSession(testing::UniformXY(10, 2), v1::SessionOptions())
                  .status()
                  .code(),
              unauth);
    EXPECT_EQ(c->NearestOfAll("sessions/mine").status().code(), unauth);
    EXPECT_EQ(c->Export("sessions/mine").status().code(), unauth);
    EXPECT_EQ(c->DeleteSession("sessions/mine").code(), unauth);
    StepStream steps(c->stub(), "sessions/mine", 1, 1000, token);
    EXPECT_EQ(steps.MoveBy(std::vector<double>(600, 0.0)).status().code(),
              unauth);
  }
  // Nothing above touched the session.
  auto still = owner->GetSession("sessions/mine");
  ASSERT_TRUE(still.ok());
  EXPECT_EQ(still->step(), 0u);
}

TEST_F(SecurityTest, TenantsSeeOnlyTheirOwnSessions) {
  StartServer(false);
  auto alpha = Connect(Secure(kTokenA));
  auto beta = Connect(Secure(kTokenB));
  ASSERT_TRUE(alpha
                  ->CreateSession(testing::UniformXY(400, 3),
                                  v1::SessionOptions(), "shared-name")
                  .ok());
  auto generated =
      alpha->CreateSession(testing::UniformXY(400, 4), v1::SessionOptions());
  ASSERT_TRUE(generated.ok());
  // Generated ids carry 128 random bits.
  EXPECT_TRUE(std::regex_match(generated->name(),
                               std::regex("sessions/s-[0-9a-f]{32}")))
      << generated->name();

  // Beta sees nothing of alpha's, and gets NOT_FOUND, never
  // PERMISSION_DENIED (names do not leak).
  auto listed = beta->ListSessions();
  ASSERT_TRUE(listed.ok());
  EXPECT_TRUE(listed->empty());
  const auto nf = absl::StatusCode::kNotFound;
  for (const std::string& name :
       {std::string("sessions/shared-name"), std::string(generated->name())}) {
    EXPECT_EQ(beta->GetSession(name).status().code(), nf);
    EXPECT_EQ(beta->NearestOfAll(name).status().code(), nf);
    EXPECT_EQ(beta->Export(name).status().code(), nf);
    EXPECT_EQ(beta->DeleteSession(name).code(), nf);
    StepStream steps(beta->stub(), name, 1, 1000, kTokenB);
    EXPECT_EQ(steps.MoveBy(std::vector<double>(800, 0.0)).status().code(), nf);
  }
  // The same id in another tenant is another session.
  auto own = beta->CreateSession(testing::UniformXY(50, 5),
                                 v1::SessionOptions(), "shared-name");
  ASSERT_TRUE(own.ok()) << own.status();
  EXPECT_EQ(beta->GetSession("sessions/shared-name")->point_count(), 50u);
  EXPECT_EQ(alpha->GetSession("sessions/shared-name")->point_count(), 400u);
  auto alpha_list = alpha->ListSessions();
  ASSERT_TRUE(alpha_list.ok());
  EXPECT_EQ(alpha_list->size(), 2u);
  // Delta's memory limit: 1 MiB holds about 2800 points (375 B each).
  auto delta = Connect(Secure(kTokenD));
  EXPECT_TRUE(
      delta->CreateSession(testing::UniformXY(2000, 10), v1::SessionOptions())
          .ok());
  auto over =
      delta->CreateSession(testing::UniformXY(2000, 11), v1::SessionOptions());
  EXPECT_EQ(over.status().code(), absl::StatusCode::kResourceExhausted);
  EXPECT_NE(over.status().message().find("MiB"), std::string::npos);
  // Beta's own limit: one session.
  EXPECT_EQ(beta->CreateSession(testing::UniformXY(50, 6), v1::SessionOptions())
                .status()
                .code(),
            absl::StatusCode::kResourceExhausted);
}

// A tenant's memory limit counts a session on the device executor with
// the executor's host memory (and, emulated, its device memory): 759 bytes
// per point and 64 KiB, not 375 per point.
TEST_F(SecurityTest, TenantMemoryCountsDeviceSessions) {
#if !defined(KINETRI_SERVER_EMULATED_DEVICE)
  GTEST_SKIP() << "built without the CCCL headers: no emulated device";
#endif
  StartServer(false, "emulated");
  auto delta = Connect(Secure(kTokenD));  // memory_mb=1
  auto over =
      delta->CreateSession(testing::UniformXY(2000, 12), v1::SessionOptions());
  EXPECT_EQ(over.status().code(), absl::StatusCode::kResourceExhausted)
      << over.status();
  EXPECT_NE(over.status().message().find("MiB"), std::string::npos);
  auto on_device =
      delta->CreateSession(testing::UniformXY(1000, 13), v1::SessionOptions());
  ASSERT_TRUE(on_device.ok()) << on_device.status();
  EXPECT_EQ(on_device->backend(), "emulated");
  // Beside it (805 KiB), a CPU session of 500 points (183 KiB) fits, and
  // one of 1000 does not.
  v1::SessionOptions cpu;
  cpu.set_backend(v1::BACKEND_CPU);
  EXPECT_EQ(
      delta->CreateSession(testing::UniformXY(1000, 14), cpu).status().code(),
      absl::StatusCode::kResourceExhausted);
  auto beside = delta->CreateSession(testing::UniformXY(500, 15), cpu);
  ASSERT_TRUE(beside.ok()) << beside.status();
  EXPECT_EQ(beside->backend(), "cpu");
}

TEST_F(SecurityTest, TokenFileReloads) {
  StartServer(false);
  auto gamma = Connect(Secure(kTokenC));
  EXPECT_EQ(gamma->ListSessions().status().code(),
            absl::StatusCode::kUnauthenticated);
  // Gamma added, beta revoked; picked up on change (checked every second)
  // and at once on SIGHUP.
  WriteFile(File("tokens"), std::string(kTokenA) + " alpha\n" + kTokenC +
                                " gamma\n# beta revoked\n");
  server_->Signal(SIGHUP);
  bool gamma_in = false;
  for (int i = 0; i < 50 && !gamma_in; ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
    gamma_in = gamma->ListSessions().ok();
  }
  EXPECT_TRUE(gamma_in);
  EXPECT_EQ(Connect(Secure(kTokenB))->ListSessions().status().code(),
            absl::StatusCode::kUnauthenticated);
  // A broken file keeps the tokens in force.
  WriteFile(File("tokens"), "short alpha\n");
  server_->Signal(SIGHUP);
  std::this_thread::sleep_for(std::chrono::milliseconds(1500));
  EXPECT_TRUE(gamma->ListSessions().ok());
}

// Certificates rotate without a restart: the server picks up new files
// (checked every --tls_reload_seconds) and keeps its sessions.
TEST_F(SecurityTest, CertificateRotationKeepsSessions) {
  // Its own copies of the pair, replaced below.
  std::system(("cp " + File("server.pem") + " " + File("rot.pem") + " && cp " +
               File("server.key") + " " + File("rot.key"))
                  .c_str());
  WriteFile(File("tokens"), std::string(kTokenA) + " alpha\n");
  server_ = std::make_unique<testing::ServerProcess>(
      KINETRI_SERVER_BINARY,
      std::vector<std::string>{
          "--tls_cert=" + File("rot.pem"), "--tls_key=" + File("rot.key"),
          "--auth_tokens_file=" + File("tokens"), "--tls_reload_seconds=1"});
  ASSERT_TRUE(server_->ok());
  ASSERT_TRUE(Connect(Secure(kTokenA))
                  ->CreateSession(testing::UniformXY(100, 7),
                                  v1::SessionOptions(), "kept")
                  .ok());
  // Key first, then certificate, each by rename (as a secret update does).
  std::system(("cp " + File("other_server.key") + " " + File("rot.key.new") +
               " && cp " + File("other_server.pem") + " " +
               File("rot.pem.new") + " && mv " + File("rot.key.new") + " " +
               File("rot.key") + " && mv " + File("rot.pem.new") + " " +
               File("rot.pem"))
                  .c_str());
  ClientSecurity rotated = Secure(kTokenA);
  rotated.ca_file = File("other_ca.pem");
  bool switched = false;
  for (int i = 0; i < 100 && !switched; ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
    switched = Connect(rotated)->GetSession("sessions/kept").ok();
  }
  EXPECT_TRUE(switched) << "new certificate not served within 10 s";
  // Clients trusting only the old CA are refused now.
  EXPECT_EQ(Connect(Secure(kTokenA))->ListSessions().status().code(),
            absl::StatusCode::kUnavailable);
}

// Probes that cannot speak TLS use the plaintext health-only port; the
// Kinetri service is not served there.
TEST_F(SecurityTest, PlaintextHealthPortForProbes) {
  WriteFile(File("tokens"), std::string(kTokenA) + " alpha\n");
  server_ = std::make_unique<testing::ServerProcess>(
      KINETRI_SERVER_BINARY,
      std::vector<std::string>{"--tls_cert=" + File("server.pem"),
                               "--tls_key=" + File("server.key"),
                               "--auth_tokens_file=" + File("tokens"),
                               "--health_listen=127.0.0.1:0"});
  ASSERT_TRUE(server_->ok());
  ASSERT_GT(server_->health_port(), 0);
  const std::string health =
      "127.0.0.1:" + std::to_string(server_->health_port());
  EXPECT_EQ(testing::HealthStatus(health), 1);
  Client plain(health, 1000, ClientSecurity{.token = kTokenA});
  EXPECT_EQ(plain.ListSessions().status().code(),
            absl::StatusCode::kUnimplemented);
}

// Protected mode: a non-loopback address without TLS and tokens is refused
// (exit status 2) unless --insecure says so.
TEST(SecurityProtectedMode, RefusesPublicPlaintextUnlessInsecure) {
  testing::ServerProcess refused(KINETRI_SERVER_BINARY, {"--listen=0.0.0.0:0"});
  EXPECT_FALSE(refused.ok());
  const int status = refused.Stop();
  EXPECT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 2) << status;
  testing::ServerProcess allowed(KINETRI_SERVER_BINARY,
                                 {"--listen=0.0.0.0:0", "--insecure"});
  EXPECT_TRUE(allowed.ok());
}

}  // namespace
}  // namespace kinetri
