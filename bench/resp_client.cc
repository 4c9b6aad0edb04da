#include "bench/resp_client.h"

#include <arpa/inet.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <sys/socket.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"

namespace kinetri::bench {

RespClient::~RespClient() {
  if (fd_ >= 0) close(fd_);
}

absl::Status RespClient::Connect(const std::string& host, int port) {
  fd_ = socket(AF_INET, SOCK_STREAM, 0);
  if (fd_ < 0) return absl::InternalError(strerror(errno));
  sockaddr_in addr{};
  addr.sin_family = AF_INET;
  addr.sin_port = htons(static_cast<uint16_t>(port));
  if (inet_pton(AF_INET, host.c_str(), &addr.sin_addr) != 1) {
    return absl::InvalidArgumentError(absl::StrCat("bad address ", host));
  }
  if (connect(fd_, reinterpret_cast<sockaddr*>(&addr), sizeof addr) != 0) {
    const std::string err = strerror(errno);
    close(fd_);
    fd_ = -1;
    return absl::UnavailableError(
        absl::StrCat("connect ", host, ":", port, ": ", err));
  }
  int one = 1;
  setsockopt(fd_, IPPROTO_TCP, TCP_NODELAY, &one, sizeof one);
  return absl::OkStatus();
}

void RespClient::Append(const std::vector<absl::string_view>& args) {
  absl::StrAppend(&out_, "*", args.size(), "\r\n");
  for (absl::string_view a : args) {
    absl::StrAppend(&out_, "$", a.size(), "\r\n", a, "\r\n");
  }
}

absl::Status RespClient::Flush() {
  size_t sent = 0;
  while (sent < out_.size()) {
    const ssize_t k = send(fd_, out_.data() + sent, out_.size() - sent, 0);
    if (k < 0) {
      if (errno == EINTR) continue;
      return absl::UnavailableError(absl::StrCat("send: ", strerror(errno)));
    }
    sent += static_cast<size_t>(k);
  }
  out_.clear();
  return absl::OkStatus();
}

absl::Status RespClient::Fill() {
  if (in_pos_ > 0 && in_pos_ == in_.size()) {
    in_.clear();
    in_pos_ = 0;
  } else if (in_pos_ > (1 << 20)) {
    in_.erase(0, in_pos_);
    in_pos_ = 0;
  }
  char buf[1 << 16];
  while (true) {
    const ssize_t k = recv(fd_, buf, sizeof buf, 0);
    if (k > 0) {
      in_.append(buf, static_cast<size_t>(k));
      return absl::OkStatus();
    }
    if (k < 0 && errno == EINTR) continue;
    return absl::UnavailableError(
        k == 0 ? "redis closed the connection"
               : absl::StrCat("recv: ", strerror(errno)));
  }
}

absl::StatusOr<absl::string_view> RespClient::Line() {
  while (true) {
    const size_t end = in_.find("\r\n", in_pos_);
    if (end != std::string::npos) {
      absl::string_view line(in_.data() + in_pos_, end - in_pos_);
      in_pos_ = end + 2;
      return line;
    }
    if (absl::Status s = Fill(); !s.ok()) return s;
  }
}

absl::StatusOr<RespValue> RespClient::Parse() {
  auto line = Line();
  if (!line.ok()) return line.status();
  if (line->empty()) return absl::DataLossError("empty RESP line");
  RespValue v;
  const char kind = (*line)[0];
  const absl::string_view rest = line->substr(1);
  int64_t num = 0;
  switch (kind) {
    case '+':
      v.type = RespValue::Type::kSimple;
      v.str = std::string(rest);
      return v;
    case '-':
      v.type = RespValue::Type::kError;
      v.str = std::string(rest);
      return v;
    case ':':
      if (!absl::SimpleAtoi(rest, &num))
        return absl::DataLossError("bad RESP integer");
      v.type = RespValue::Type::kInteger;
      v.integer = num;
      return v;
    case '$': {
      if (!absl::SimpleAtoi(rest, &num))
        return absl::DataLossError("bad RESP length");
      if (num < 0) return v;  // nil
      const size_t need = static_cast<size_t>(num) + 2;
      while (in_.size() - in_pos_ < need) {
        if (absl::Status s = Fill(); !s.ok()) return s;
      }
      v.type = RespValue::Type::kBulk;
      v.str.assign(in_.data() + in_pos_, static_cast<size_t>(num));
      in_pos_ += need;
      return v;
    }
    case '*': {
      if (!absl::SimpleAtoi(rest, &num))
        return absl::DataLossError("bad RESP array length");
      if (num < 0) return v;
      v.type = RespValue::Type::kArray;
      v.elements.reserve(static_cast<size_t>(num));
      for (int64_t i = 0; i < num; ++i) {
        auto e = Parse();
        if (!e.ok()) return e.status();
        v.elements.push_back(*std::move(e));
      }
      return v;
    }
    default:
      return absl::DataLossError(
          absl::StrCat("bad RESP type '", std::string(1, kind), "'"));
  }
}

absl::StatusOr<RespValue> RespClient::Read() { return Parse(); }

absl::StatusOr<RespValue> RespClient::Call(
    const std::vector<absl::string_view>& args) {
  Append(args);
  if (absl::Status s = Flush(); !s.ok()) return s;
  return Read();
}

}  // namespace kinetri::bench
