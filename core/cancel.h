// Cooperative cancellation for long core loops.
//
// A CancelToken wraps a caller's "should I stop?" check (the server's is:
// the client cancelled or the deadline passed). Long loops poll it at a
// fine granularity (a block of queries, a region of triangles) and, once it
// fires, stop and return absl::CancelledError / DeadlineExceededError
// without leaving partial results behind. Polling is cheap after the first
// positive answer (a relaxed atomic), and thread-safe.
#ifndef KINETRI_CORE_CANCEL_H_
#define KINETRI_CORE_CANCEL_H_

#include <atomic>
#include <chrono>
#include <cstdint>
#include <functional>
#include <string>
#include <utility>

#include "absl/status/status.h"

namespace kinetri::core {

class CancelToken {
 public:
  using Clock = std::chrono::steady_clock;

  // Never fires.
  CancelToken() = default;
  // Fires when `cancelled` returns true or `deadline` has passed (either may
  // be omitted: an empty function, or Clock::time_point::max()).
  // `check_interval`: how often at most `cancelled` runs (0: at every poll,
  // possibly from several threads at once: `cancelled` must be
  // thread-safe).
  explicit CancelToken(
      std::function<bool()> cancelled,
      Clock::time_point deadline = Clock::time_point::max(),
      Clock::duration check_interval = std::chrono::milliseconds(1))
      : cancelled_(std::move(cancelled)),
        deadline_(deadline),
        check_interval_(check_interval) {}

  CancelToken(const CancelToken&) = delete;
  CancelToken& operator=(const CancelToken&) = delete;

  // True once the token has fired (sticky). Cheap to poll often: the
  // caller's check (which may cost microseconds, e.g. gRPC's IsCancelled)
  // runs at most once per check interval; the deadline is exact.
  bool Cancelled() const {
    if (fired_.load(std::memory_order_relaxed) != kNo) return true;
    const Clock::time_point now = Clock::now();
    int why = kNo;
    if (deadline_ != Clock::time_point::max() && now >= deadline_) {
      why = kDeadline;
    } else if (cancelled_) {
      if (check_interval_ == Clock::duration::zero()) {
        // At every poll, from every thread (tests count the polls).
        if (cancelled_()) why = kCancelled;
      } else {
        const int64_t t = now.time_since_epoch().count();
        int64_t next = next_check_.load(std::memory_order_relaxed);
        if (t >= next &&
            next_check_.compare_exchange_strong(
                next, t + check_interval_.count(), std::memory_order_relaxed) &&
            cancelled_()) {
          why = kCancelled;
        }
      }
    }
    if (why == kNo) return false;
    int expected = kNo;
    fired_.compare_exchange_strong(expected, why, std::memory_order_relaxed);
    return true;
  }

  // OK while not fired; else CANCELLED or DEADLINE_EXCEEDED naming `what`.
  absl::Status Check(const char* what) const {
    if (!Cancelled()) return absl::OkStatus();
    return fired_.load(std::memory_order_relaxed) == kDeadline
               ? absl::DeadlineExceededError(
                     std::string(what) + ": deadline exceeded, work stopped")
               : absl::CancelledError(std::string(what) +
                                      ": cancelled, work stopped");
  }

  // A token that never fires, for callers without one.
  static const CancelToken& Never() {
    static const CancelToken never;
    return never;
  }

 private:
  enum : int { kNo = 0, kCancelled = 1, kDeadline = 2 };
  std::function<bool()> cancelled_;
  mutable std::atomic<int64_t> next_check_{0};
  Clock::time_point deadline_ = Clock::time_point::max();
  Clock::duration check_interval_ = Clock::duration::zero();
  mutable std::atomic<int> fired_{kNo};
};

}  // namespace kinetri::core

#endif  // KINETRI_CORE_CANCEL_H_
