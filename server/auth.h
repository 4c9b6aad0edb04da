// Bearer-token authentication and tenants.
//
// --auth_tokens_file holds one token per line: `TOKEN TENANT [sessions=N]
// [points=N] [memory_mb=N]` ('#' starts a comment). The server keeps only
// SHA-256 hashes of the tokens; a caller's token (metadata `authorization:
// Bearer TOKEN`) is hashed and compared in constant time with every entry. The
// file is re-read on SIGHUP and when its modification time changes; a file that
// does not parse keeps the previous table (and is reported).
//
// Tenants: every session belongs to the tenant of the token that created
// it; a tenant sees only its own sessions (others' are NOT_FOUND, so names
// do not leak). With no tokens file, authentication is off and every caller
// is the unnamed tenant "".
#ifndef KINETRI_SERVER_AUTH_H_
#define KINETRI_SERVER_AUTH_H_

#include <grpcpp/grpcpp.h>

#include <array>
#include <cstdint>
#include <ctime>
#include <memory>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"

namespace kinetri::server {

struct Tenant {
  std::string name;            // [a-z0-9_-]{1,63}; "" when auth is off
  uint32_t max_sessions = 0;   // 0: the server's limit
  uint64_t max_points = 0;     // points over all its sessions; 0: no own limit
  uint64_t max_memory_mb = 0;  // memory of all its sessions (admission
                               // estimate per point); 0: no own limit
};

class TokenAuth {
 public:
  // Authentication off.
  TokenAuth() = default;
  // Loads `path`; errors name the line.
  static absl::StatusOr<std::unique_ptr<TokenAuth>> Load(
      const std::string& path);

  bool enabled() const { return !path_.empty(); }
  size_t size() const;

  // The tenant of the call's bearer token; UNAUTHENTICATED without a valid
  // one (when enabled).
  absl::StatusOr<Tenant> Authenticate(const grpc::ServerContext& ctx) const;
  absl::StatusOr<Tenant> AuthenticateToken(const std::string& token) const;

  // Re-reads the file; on error the previous tokens stay in force.
  absl::Status Reload();
  // Reload() if the file's modification time or size changed.
  absl::Status ReloadIfChanged();

 private:
  struct Entry {
    std::array<unsigned char, 32> hash;
    Tenant tenant;
  };
  static absl::StatusOr<std::vector<Entry>> Parse(const std::string& path);

  std::string path_;
  mutable absl::Mutex mu_;
  std::shared_ptr<const std::vector<Entry>> entries_ ABSL_GUARDED_BY(mu_);
  struct timespec mtime_ ABSL_GUARDED_BY(mu_) = {};
  int64_t file_size_ ABSL_GUARDED_BY(mu_) = -1;
};

// "host:port" listens only on loopback (127.0.0.0/8, ::1, localhost).
bool IsLoopbackAddress(const std::string& host_port);

// 128 random bits from the kernel as 32 lowercase hex digits.
std::string RandomHex128();

}  // namespace kinetri::server

#endif  // KINETRI_SERVER_AUTH_H_
