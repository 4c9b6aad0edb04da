// Bearer-token authentication and tenants (see auth.h).
#include "server/auth.h"

#include <openssl/crypto.h>
#include <openssl/evp.h>
#include <sys/random.h>
#include <sys/stat.h>

#include <cerrno>
#include <cstring>
#include <fstream>
#include <sstream>

#include "absl/strings/ascii.h"
#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "absl/strings/strip.h"

namespace kinetri::server {
namespace {

std::array<unsigned char, 32> Sha256(const std::string& s) {
  std::array<unsigned char, 32> out{};
  unsigned int len = 0;
  EVP_Digest(s.data(), s.size(), out.data(), &len, EVP_sha256(), nullptr);
  return out;
}

bool ValidTenantName(const std::string& name) {
  if (name.empty() || name.size() > 63) return false;
  for (char c : name) {
    if (!(absl::ascii_islower(c) || absl::ascii_isdigit(c) || c == '-' ||
          c == '_')) {
      return false;
    }
  }
  return true;
}

}  // namespace

absl::StatusOr<std::vector<TokenAuth::Entry>> TokenAuth::Parse(
    const std::string& path) {
  std::ifstream in(path);
  if (!in) {
    return absl::FailedPreconditionError(absl::StrCat(
        "--auth_tokens_file: cannot read ", path, ": ", std::strerror(errno)));
  }
  std::vector<Entry> entries;
  std::string line;
  for (int number = 1; std::getline(in, line); ++number) {
    const size_t hash = line.find('#');
    if (hash != std::string::npos) line.resize(hash);
    std::vector<std::string> words =
        absl::StrSplit(line, absl::ByAnyChar(" \t\r"), absl::SkipEmpty());
    if (words.empty()) continue;
    auto bad = [&](const std::string& why) {
      return absl::InvalidArgumentError(absl::StrCat(
          "--auth_tokens_file ", path, " line ", number, ": ", why,
          " (expected: TOKEN TENANT [sessions=N] [points=N] [memory_mb=N])"));
    };
    if (words.size() < 2) return bad("a token needs a tenant");
    if (words[0].size() < 16) {
      return bad("tokens must have at least 16 characters");
    }
    Entry e;
    e.hash = Sha256(words[0]);
    e.tenant.name = words[1];
    if (!ValidTenantName(e.tenant.name)) {
      return bad("tenant names are [a-z0-9_-]{1,63}");
    }
    for (size_t i = 2; i < words.size(); ++i) {
      absl::string_view w = words[i];
      if (absl::ConsumePrefix(&w, "sessions=")) {
        if (!absl::SimpleAtoi(w, &e.tenant.max_sessions)) {
          return bad(absl::StrCat("bad number in ", words[i]));
        }
      } else if (absl::ConsumePrefix(&w, "points=")) {
        if (!absl::SimpleAtoi(w, &e.tenant.max_points)) {
          return bad(absl::StrCat("bad number in ", words[i]));
        }
      } else if (absl::ConsumePrefix(&w, "memory_mb=")) {
        if (!absl::SimpleAtoi(w, &e.tenant.max_memory_mb) ||
            e.tenant.max_memory_mb > (uint64_t{1} << 40)) {
          return bad(absl::StrCat("bad number in ", words[i]));
        }
      } else {
        return bad(absl::StrCat("unknown field ", words[i]));
      }
    }
    for (const Entry& other : entries) {
      if (CRYPTO_memcmp(other.hash.data(), e.hash.data(), e.hash.size()) == 0) {
        return bad("the same token appears twice");
      }
    }
    entries.push_back(std::move(e));
  }
  if (entries.empty()) {
    return absl::InvalidArgumentError(absl::StrCat(
        "--auth_tokens_file ", path, ": no tokens (nobody could connect)"));
  }
  return entries;
}

absl::StatusOr<std::unique_ptr<TokenAuth>> TokenAuth::Load(
    const std::string& path) {
  auto auth = std::make_unique<TokenAuth>();
  auth->path_ = path;
  absl::Status s = auth->Reload();
  if (!s.ok()) return s;
  return auth;
}

size_t TokenAuth::size() const {
  absl::MutexLock lock(&mu_);
  return entries_ ? entries_->size() : 0;
}

absl::Status TokenAuth::Reload() {
  struct stat st {};
  const bool have_stat = ::stat(path_.c_str(), &st) == 0;
  auto parsed = Parse(path_);
  if (!parsed.ok()) return parsed.status();
  auto table = std::make_shared<const std::vector<Entry>>(*std::move(parsed));
  absl::MutexLock lock(&mu_);
  entries_ = std::move(table);
  if (have_stat) {
    mtime_ = st.st_mtim;
    file_size_ = st.st_size;
  }
  return absl::OkStatus();
}

absl::Status TokenAuth::ReloadIfChanged() {
  if (!enabled()) return absl::OkStatus();
  struct stat st {};
  if (::stat(path_.c_str(), &st) != 0) {
    return absl::FailedPreconditionError(absl::StrCat(
        "--auth_tokens_file: cannot stat ", path_, ": ", std::strerror(errno),
        " (the previous tokens stay in force)"));
  }
  {
    absl::MutexLock lock(&mu_);
    if (st.st_mtim.tv_sec == mtime_.tv_sec &&
        st.st_mtim.tv_nsec == mtime_.tv_nsec && st.st_size == file_size_) {
      return absl::OkStatus();
    }
  }
  absl::Status reloaded = Reload();
  if (!reloaded.ok()) {
    // Reported once per change of the file, not at every check.
    absl::MutexLock lock(&mu_);
    mtime_ = st.st_mtim;
    file_size_ = st.st_size;
  }
  return reloaded;
}

absl::StatusOr<Tenant> TokenAuth::AuthenticateToken(
    const std::string& token) const {
  if (!enabled()) return Tenant{};
  std::shared_ptr<const std::vector<Entry>> entries;
  {
    absl::MutexLock lock(&mu_);
    entries = entries_;
  }
  const auto hash = Sha256(token);
  // Every entry is compared (constant time each), whichever matches.
  const Entry* match = nullptr;
  for (const Entry& e : *entries) {
    if (CRYPTO_memcmp(e.hash.data(), hash.data(), hash.size()) == 0) {
      match = &e;
    }
  }
  if (match == nullptr || token.empty()) {
    return absl::UnauthenticatedError(
        "missing or invalid bearer token (metadata 'authorization: Bearer "
        "TOKEN')");
  }
  return match->tenant;
}

absl::StatusOr<Tenant> TokenAuth::Authenticate(
    const grpc::ServerContext& ctx) const {
  if (!enabled()) return Tenant{};
  const auto& md = ctx.client_metadata();
  auto it = md.find("authorization");
  std::string token;
  if (it != md.end()) {
    absl::string_view value(it->second.data(), it->second.size());
    if (absl::ConsumePrefix(&value, "Bearer ") ||
        absl::ConsumePrefix(&value, "bearer ")) {
      token = std::string(absl::StripAsciiWhitespace(value));
    }
  }
  return AuthenticateToken(token);
}

bool IsLoopbackAddress(const std::string& host_port) {
  std::string host = host_port;
  if (!host.empty() && host[0] == '[') {  // [v6]:port
    const size_t close = host.find(']');
    host = close == std::string::npos ? host : host.substr(1, close - 1);
  } else {
    const size_t colon = host.rfind(':');
    if (colon != std::string::npos) host.resize(colon);
  }
  if (absl::StartsWith(host, "unix:")) return true;  // a local socket
  return host == "localhost" || host == "::1" || absl::StartsWith(host, "127.");
}

std::string RandomHex128() {
  unsigned char bytes[16];
  size_t got = 0;
  while (got < sizeof(bytes)) {
    const ssize_t r = getrandom(bytes + got, sizeof(bytes) - got, 0);
    if (r > 0) got += static_cast<size_t>(r);
  }
  static constexpr char kHex[] = "0123456789abcdef";
  std::string out;
  for (unsigned char b : bytes) {
    out.push_back(kHex[b >> 4]);
    out.push_back(kHex[b & 15]);
  }
  return out;
}

}  // namespace kinetri::server
