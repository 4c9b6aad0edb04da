// Starts the real kinetri-server binary on loopback ephemeral ports.
#include "tests/e2e/server_process.h"

#include <arpa/inet.h>
#include <grpcpp/generic/generic_stub.h>
#include <grpcpp/grpcpp.h>
#include <netinet/in.h>
#include <signal.h>
#include <sys/resource.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <condition_variable>
#include <cstdio>
#include <cstring>
#include <mutex>
#include <random>
#include <string>

namespace kinetri::testing {

ServerProcess::ServerProcess(const std::string& binary,
                             const std::vector<std::string>& flags,
                             uint64_t max_file_bytes) {
  int out[2];
  if (pipe(out) != 0) return;
  pid_ = fork();
  if (pid_ == 0) {
    if (max_file_bytes > 0) {
      const rlimit limit{max_file_bytes, max_file_bytes};
      setrlimit(RLIMIT_FSIZE, &limit);
      signal(SIGXFSZ, SIG_IGN);  // writes fail with EFBIG instead
    }
    dup2(out[1], STDOUT_FILENO);
    close(out[0]);
    std::vector<std::string> args = {binary, "--listen=127.0.0.1:0",
                                     "--metrics_listen=127.0.0.1:0"};
    args.insert(args.end(), flags.begin(), flags.end());
    std::vector<char*> argv;
    for (auto& a : args) argv.push_back(a.data());
    argv.push_back(nullptr);
    execv(binary.c_str(), argv.data());
    _exit(127);
  }
  close(out[1]);
  FILE* f = fdopen(out[0], "r");
  char line[512];
  while (f && fgets(line, sizeof line, f)) {
    int p = 0;
    if (std::sscanf(line, "kinetri-server: metrics on %*s (port %d)", &p) ==
        1) {
      metrics_port_ = p;
    } else if (std::sscanf(line, "kinetri-server: health on port %d", &p) ==
               1) {
      health_port_ = p;
    } else if (std::sscanf(line, "kinetri-server: listening on port %d", &p) ==
               1) {
      grpc_port_ = p;
      break;
    }
  }
  // Keep draining the pipe so that the server never blocks on stdout.
  if (f) {
    if (fork() == 0) {
      while (fgets(line, sizeof line, f)) {
      }
      _exit(0);
    }
    fclose(f);
  }
}

int ServerProcess::Stop() {
  if (pid_ <= 0) return -1;
  kill(pid_, SIGTERM);
  int status = 0;
  waitpid(pid_, &status, 0);
  pid_ = -1;
  return status;
}

void ServerProcess::Kill() {
  if (pid_ <= 0) return;
  kill(pid_, SIGKILL);
  waitpid(pid_, nullptr, 0);
  pid_ = -1;
}

void ServerProcess::Signal(int sig) {
  if (pid_ > 0) kill(pid_, sig);
}

ServerProcess::~ServerProcess() { Stop(); }

double ServerProcess::CpuSeconds() const {
  if (pid_ <= 0) return -1.0;
  const std::string path = "/proc/" + std::to_string(pid_) + "/stat";
  FILE* f = std::fopen(path.c_str(), "r");
  if (!f) return -1.0;
  char buf[4096];
  const size_t k = std::fread(buf, 1, sizeof buf - 1, f);
  std::fclose(f);
  buf[k] = 0;
  // Fields after the command name (which may hold spaces): state is field 3,
  // utime and stime are fields 14 and 15.
  const char* p = std::strrchr(buf, ')');
  if (!p) return -1.0;
  unsigned long long utime = 0, stime = 0;
  if (std::sscanf(p + 2,
                  "%*c %*d %*d %*d %*d %*d %*u %*u %*u %*u %*u %llu %llu",
                  &utime, &stime) != 2) {
    return -1.0;
  }
  return double(utime + stime) / double(sysconf(_SC_CLK_TCK));
}

std::vector<double> UniformXY(size_t n, uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> u(0, 1);
  std::vector<double> xy(2 * n);
  for (double& v : xy) v = u(rng);
  return xy;
}

std::string HttpGet(int port, const std::string& path) {
  const int fd = socket(AF_INET, SOCK_STREAM, 0);
  if (fd < 0) return "";
  sockaddr_in addr{};
  addr.sin_family = AF_INET;
  addr.sin_port = htons(static_cast<uint16_t>(port));
  addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  std::string body;
  if (connect(fd, reinterpret_cast<sockaddr*>(&addr), sizeof addr) == 0) {
    const std::string req = "GET " + path +
                            " HTTP/1.0\r\nHost: 127.0.0.1\r\nConnection: "
                            "close\r\n\r\n";
    if (write(fd, req.data(), req.size()) == ssize_t(req.size())) {
      char buf[65536];
      ssize_t k;
      while ((k = read(fd, buf, sizeof buf)) > 0) body.append(buf, k);
    }
  }
  close(fd);
  const size_t sep = body.find("\r\n\r\n");
  return sep == std::string::npos ? "" : body.substr(sep + 4);
}

// grpc.health.v1.Health/Check for the whole server, via the generic stub
// (the health proto is not installed): returns 1 SERVING, 2 NOT_SERVING,
// -1 if the call failed.
int HealthStatus(const std::string& target, const std::string& service) {
  auto channel =
      grpc::CreateChannel(target, grpc::InsecureChannelCredentials());
  grpc::GenericStub stub(channel);
  grpc::ClientContext ctx;
  ctx.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(5));
  // HealthCheckRequest { string service = 1; } (names under 128 bytes).
  std::string bytes_out;
  if (!service.empty()) {
    bytes_out =
        std::string("\x0a", 1) + static_cast<char>(service.size()) + service;
  }
  grpc::Slice slice(bytes_out);
  grpc::ByteBuffer request(&slice, 1), response;
  std::mutex mu;
  std::condition_variable cv;
  bool done = false;
  grpc::Status status;
  stub.UnaryCall(&ctx, "/grpc.health.v1.Health/Check", grpc::StubOptions(),
                 &request, &response, [&](grpc::Status s) {
                   std::lock_guard<std::mutex> lock(mu);
                   status = s;
                   done = true;
                   cv.notify_one();
                 });
  std::unique_lock<std::mutex> lock(mu);
  cv.wait(lock, [&] { return done; });
  if (!status.ok()) return -1;
  std::vector<grpc::Slice> slices;
  if (!response.Dump(&slices).ok()) return -1;
  std::string bytes;
  for (const auto& sl : slices) {
    bytes.append(reinterpret_cast<const char*>(sl.begin()), sl.size());
  }
  // HealthCheckResponse { status (field 1, enum) }: tag 0x08, then value.
  if (bytes.size() == 2 && bytes[0] == 0x08) return bytes[1];
  return -1;
}

}  // namespace kinetri::testing
