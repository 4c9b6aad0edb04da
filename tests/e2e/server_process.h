// Starts the real kinetri-server binary on loopback ephemeral ports.
#ifndef KINETRI_TESTS_E2E_SERVER_PROCESS_H_
#define KINETRI_TESTS_E2E_SERVER_PROCESS_H_

#include <sys/types.h>

#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

namespace kinetri::testing {

class ServerProcess {
 public:
  // Runs `binary` with --listen=127.0.0.1:0 --metrics_listen=127.0.0.1:0 and
  // the extra flags; waits until it prints its ports.
  // max_file_bytes > 0: the server may write no file larger than that
  // (RLIMIT_FSIZE; writes beyond fail with EFBIG, as on a full disk).
  explicit ServerProcess(const std::string& binary,
                         const std::vector<std::string>& flags = {},
                         uint64_t max_file_bytes = 0);
  ~ServerProcess();  // SIGTERM, then wait

  bool ok() const { return grpc_port_ > 0; }
  std::string target() const {
    return "127.0.0.1:" + std::to_string(grpc_port_);
  }
  int metrics_port() const { return metrics_port_; }
  // The plaintext health-only port (--health_listen), 0 if none.
  int health_port() const { return health_port_; }
  pid_t pid() const { return pid_; }
  // CPU seconds (user + system) the server has used so far.
  double CpuSeconds() const;
  // Sends SIGTERM and returns the exit status.
  int Stop();
  // Sends a signal without waiting.
  void Signal(int sig);
  // SIGKILL, then wait (a crash: nothing is flushed or drained).
  void Kill();

 private:
  pid_t pid_ = -1;
  int grpc_port_ = 0;
  int metrics_port_ = 0;
  int health_port_ = 0;
};

// n uniform random points in the unit square, packed x, y.
std::vector<double> UniformXY(size_t n, uint64_t seed);

// grpc.health.v1.Health/Check of `service` ("": the whole server) on a
// plaintext target: 1 SERVING, 2 NOT_SERVING, -1 if the call failed.
int HealthStatus(const std::string& target, const std::string& service = "");

// GET http://127.0.0.1:port/path; returns the body ("" on failure).
std::string HttpGet(int port, const std::string& path);

}  // namespace kinetri::testing

#endif  // KINETRI_TESTS_E2E_SERVER_PROCESS_H_
