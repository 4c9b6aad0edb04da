#include "server/memory_budget.h"

#include <unistd.h>

#include <algorithm>
#include <cstdio>
#include <fstream>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/strip.h"
#include "core/device/device_executor.h"

namespace kinetri::server {

namespace {

// Host memory per point a session's device executor adds to the host
// session (0 on the CPU).
uint64_t DeviceHostBytesPerPoint(std::string_view backend) {
  if (backend == "cpu") return 0;
  return core::device::kDeviceHostBytesPerPoint +
         (backend == "emulated" ? core::device::kDeviceBytesPerPoint : 0);
}

}  // namespace

uint64_t MemoryBudget::SessionBytesPerPoint(std::string_view backend) {
  return kSessionBytesPerPoint + DeviceHostBytesPerPoint(backend);
}

uint64_t MemoryBudget::CopyBytesPerPoint(std::string_view backend) {
  return kCopyBytesPerPoint + DeviceHostBytesPerPoint(backend);
}

uint64_t MemoryBudget::DeviceFixedBytes(std::string_view backend) {
  if (backend == "cpu") return 0;
  return backend == "emulated" ? core::device::kEmulatedHostFixedBytes
                               : core::device::kCudaHostFixedBytes;
}

MemoryBudget::Reservation& MemoryBudget::Reservation::operator=(
    Reservation&& o) noexcept {
  if (this != &o) {
    Release();
    budget_ = o.budget_;
    bytes_ = o.bytes_;
    o.budget_ = nullptr;
    o.bytes_ = 0;
  }
  return *this;
}

void MemoryBudget::Reservation::Release() {
  if (budget_ != nullptr && bytes_ > 0) {
    absl::MutexLock lock(&budget_->mu_);
    budget_->used_ -= bytes_;
  }
  budget_ = nullptr;
  bytes_ = 0;
}

absl::StatusOr<MemoryBudget::Reservation> MemoryBudget::Reserve(
    uint64_t bytes, const std::string& what) {
  Reservation r;
  if (absl::Status s = GrowTo(&r, bytes, what); !s.ok()) return s;
  return r;
}

absl::Status MemoryBudget::GrowTo(Reservation* r, uint64_t bytes,
                                  const std::string& what) {
  if (bytes <= r->bytes_) return absl::OkStatus();
  const uint64_t more = bytes - r->bytes_;
  absl::MutexLock lock(&mu_);
  if (limit_ > 0 && (more > limit_ || used_ > limit_ - more)) {
    return absl::ResourceExhaustedError(absl::StrCat(
        what, ": needs about ", (more + (1 << 20) - 1) >> 20,
        " MiB more, but only ", (limit_ - std::min(used_, limit_)) >> 20,
        " of the server's ", limit_ >> 20,
        " MiB memory budget (--max_memory_mb) are free"));
  }
  used_ += more;
  r->budget_ = this;
  r->bytes_ = bytes;
  return absl::OkStatus();
}

uint64_t MemoryBudget::used() const {
  absl::MutexLock lock(&mu_);
  return used_;
}

uint64_t MemoryBudget::DefaultLimit() {
  uint64_t limit = 0;
  const long pages = sysconf(_SC_PHYS_PAGES);
  const long page = sysconf(_SC_PAGE_SIZE);
  if (pages > 0 && page > 0) limit = uint64_t(pages) * uint64_t(page);
  for (const char* path : {"/sys/fs/cgroup/memory.max",
                           "/sys/fs/cgroup/memory/memory.limit_in_bytes"}) {
    std::ifstream in(path);
    std::string text;
    uint64_t v = 0;
    if (in >> text && absl::SimpleAtoi(text, &v) && v > 0 &&
        (limit == 0 || v < limit)) {
      limit = v;
    }
  }
  return limit / 10 * 8;
}

}  // namespace kinetri::server
