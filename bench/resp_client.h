// A minimal Redis client (RESP2 over a loopback TCP socket) for the service
// benchmark: pipelined commands, replies parsed one by one. Only what the
// benchmark needs; not a general-purpose client.
#ifndef KINETRI_BENCH_RESP_CLIENT_H_
#define KINETRI_BENCH_RESP_CLIENT_H_

#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"

namespace kinetri::bench {

struct RespValue {
  enum class Type { kSimple, kError, kInteger, kBulk, kNil, kArray };
  Type type = Type::kNil;
  std::string str;  // simple, error, bulk
  int64_t integer = 0;
  std::vector<RespValue> elements;  // array
};

class RespClient {
 public:
  RespClient() = default;
  RespClient(const RespClient&) = delete;
  RespClient& operator=(const RespClient&) = delete;
  ~RespClient();

  absl::Status Connect(const std::string& host, int port);
  // Queues one command (sent by Flush).
  void Append(const std::vector<absl::string_view>& args);
  absl::Status Flush();
  // Reads the next reply.
  absl::StatusOr<RespValue> Read();
  // Append + Flush + Read.
  absl::StatusOr<RespValue> Call(const std::vector<absl::string_view>& args);

 private:
  absl::Status Fill();  // reads more bytes into in_
  absl::StatusOr<absl::string_view> Line();
  absl::StatusOr<RespValue> Parse();

  int fd_ = -1;
  std::string out_;
  std::string in_;
  size_t in_pos_ = 0;
};

}  // namespace kinetri::bench

#endif  // KINETRI_BENCH_RESP_CLIENT_H_
