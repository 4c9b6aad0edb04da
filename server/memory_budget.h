// A server-wide memory budget: work a client can cause reserves its memory
// estimate first and is refused with RESOURCE_EXHAUSTED when the budget
// would be exceeded, before anything is allocated.
#ifndef KINETRI_SERVER_MEMORY_BUDGET_H_
#define KINETRI_SERVER_MEMORY_BUDGET_H_

#include <cstdint>
#include <string>
#include <string_view>

#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"

namespace kinetri::server {

class MemoryBudget {
 public:
  // Measured on the reference machine (docs/RELIABILITY.md): a session's
  // peak while it is built (CGAL) and its resident size with step scratch
  // stay under kSessionBytesPerPoint; a snapshot copy made by a step while
  // readers hold the current one under kCopyBytesPerPoint. Both include
  // the region executor's apexes across each edge, which it keeps between
  // steps (24 bytes per point; the copy's executor fills its own).
  static constexpr uint64_t kSessionBytesPerPoint = 375;
  static constexpr uint64_t kCopyBytesPerPoint = 185;
  // The same by where the session runs (its backend name: "cpu",
  // "emulated", "cuda"): on a device, the executor's host memory beside the
  // mesh (its position mirrors and download arrays) is added, and on the
  // emulated device, whose memory is the host's, the device memory too. A
  // copy gets an executor of its own. Plus, once per session or copy on a
  // device, DeviceFixedBytes (its pinned staging).
  static uint64_t SessionBytesPerPoint(std::string_view backend);
  static uint64_t CopyBytesPerPoint(std::string_view backend);
  static uint64_t DeviceFixedBytes(std::string_view backend);
  // A query block: its rows' bookkeeping (the queries, their order, sizes
  // and offsets: ~100 bytes) and each result kept twice (the rows as they
  // are found, then the answer), 4 bytes per id and 8 per distance.
  static constexpr uint64_t kQueryBytesPerRow = 100;
  static uint64_t QueryBytesPerResult(bool distances) {
    return 2 * (4 + (distances ? 8 : 0));
  }

  // limit_bytes == 0: no limit.
  explicit MemoryBudget(uint64_t limit_bytes) : limit_(limit_bytes) {}

  // Releases its bytes when destroyed (move-only).
  class Reservation {
   public:
    Reservation() = default;
    Reservation(Reservation&& o) noexcept
        : budget_(o.budget_), bytes_(o.bytes_) {
      o.budget_ = nullptr;
      o.bytes_ = 0;
    }
    Reservation& operator=(Reservation&& o) noexcept;
    Reservation(const Reservation&) = delete;
    Reservation& operator=(const Reservation&) = delete;
    ~Reservation() { Release(); }
    uint64_t bytes() const { return bytes_; }
    void Release();

   private:
    friend class MemoryBudget;
    Reservation(MemoryBudget* b, uint64_t bytes) : budget_(b), bytes_(bytes) {}
    MemoryBudget* budget_ = nullptr;
    uint64_t bytes_ = 0;
  };

  // RESOURCE_EXHAUSTED (naming `what`, the estimate and what is left) when
  // `bytes` more would pass the limit.
  absl::StatusOr<Reservation> Reserve(uint64_t bytes, const std::string& what);
  // Grows `r` (empty, or a reservation of this budget) to `bytes` in all;
  // RESOURCE_EXHAUSTED (as Reserve) when the growth does not fit, and `r`
  // stays as it was. Smaller than r's bytes: nothing changes.
  absl::Status GrowTo(Reservation* r, uint64_t bytes, const std::string& what);

  uint64_t limit() const { return limit_; }
  uint64_t used() const;

  // The default limit: 80 % of the memory this process may use (the cgroup
  // limit if there is one, else the machine's memory).
  static uint64_t DefaultLimit();

 private:
  const uint64_t limit_;
  mutable absl::Mutex mu_;
  uint64_t used_ ABSL_GUARDED_BY(mu_) = 0;
};

}  // namespace kinetri::server

#endif  // KINETRI_SERVER_MEMORY_BUDGET_H_
