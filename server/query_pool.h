// Runs the computation of queries on threads of their own, at a lower CPU
// priority than steps.
//
// Queries read an immutable snapshot, so a step never waits for one on a
// lock. What is left is the CPU: eight clients looping all-points queries
// keep eight gRPC threads computing on two cores, and a 1-point step's
// threads then wait for the scheduler behind them (p50 6.7 ms against
// 0.4 ms idle in CI). Here a query's handler thread hands each block of
// rows (and each chunk of the answer to encode) to the pool and sleeps
// until it is done: at most `threads` blocks compute at once, on threads
// that run under SCHED_IDLE (`idle`) or with a nice value raised by
// `nice`, so a step's threads take a core from them as soon as they wake.
// (Nice alone let a query thread finish its time slice first: step p99
// under load 2.3-3.0 ms against 1.4-1.8 ms with SCHED_IDLE.) Queries still
// get the whole machine while no step runs.
#ifndef KINETRI_SERVER_QUERY_POOL_H_
#define KINETRI_SERVER_QUERY_POOL_H_

#include <cstdint>
#include <deque>
#include <thread>
#include <vector>

#include "absl/functional/function_ref.h"
#include "absl/status/status.h"
#include "absl/synchronization/mutex.h"
#include "core/cancel.h"

namespace kinetri::server {

class QueryPool {
 public:
  // threads in [1, 1024]; nice in [0, 19]: how much the pool's threads'
  // nice value is raised (0: same priority as steps); idle: they also run
  // under the SCHED_IDLE policy (Linux; no privilege needed). Where a
  // change fails (no such call), the threads keep the process's priority.
  QueryPool(int threads, int nice, bool idle = false);
  // Waits for the blocks in progress; none may be queued.
  ~QueryPool();
  QueryPool(const QueryPool&) = delete;
  QueryPool& operator=(const QueryPool&) = delete;

  // Runs fn on a pool thread and returns once it has returned. While it
  // waits for a free thread, `cancel` is polled every few milliseconds:
  // once it fires, fn is not run and its status (CANCELLED or
  // DEADLINE_EXCEEDED naming `what`) is returned. Once fn runs, it polls
  // the token itself.
  absl::Status Run(const core::CancelToken& cancel, const char* what,
                   absl::FunctionRef<void()> fn);

  int threads() const { return static_cast<int>(threads_.size()); }
  // The nice value the pool's threads got (-1 before they started or
  // where it could not be read).
  int applied_nice() const;
  // Whether the pool's threads run under SCHED_IDLE.
  bool applied_idle() const;
  // Blocks waiting for a thread now.
  int queued() const;

 private:
  struct Job {
    absl::FunctionRef<void()> fn;
    bool started = false;
    bool done = false;
  };
  void Loop(int nice, bool idle);

  mutable absl::Mutex mu_;
  std::deque<Job*> queue_ ABSL_GUARDED_BY(mu_);
  bool stopping_ ABSL_GUARDED_BY(mu_) = false;
  int applied_nice_ ABSL_GUARDED_BY(mu_) = -1;
  bool applied_idle_ ABSL_GUARDED_BY(mu_) = false;
  std::vector<std::thread> threads_;
};

}  // namespace kinetri::server

#endif  // KINETRI_SERVER_QUERY_POOL_H_
