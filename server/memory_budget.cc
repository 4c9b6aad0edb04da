#include "server/memory_budget.h"

#include <unistd.h>

#include <algorithm>
#include <cstdio>
#include <fstream>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/strip.h"

namespace kinetri::server {

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
  absl::MutexLock lock(&mu_);
  if (limit_ > 0 && (bytes > limit_ || used_ > limit_ - bytes)) {
    return absl::ResourceExhaustedError(absl::StrCat(
        what, ": needs about ", bytes >> 20, " MiB, but only ",
        (limit_ - std::min(used_, limit_)) >> 20, " of the server's ",
        limit_ >> 20, " MiB memory budget (--max_memory_mb) are free"));
  }
  used_ += bytes;
  return Reservation(this, bytes);
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
