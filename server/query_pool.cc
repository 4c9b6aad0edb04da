#include "server/query_pool.h"

#include <algorithm>
#include <cerrno>

#include "absl/time/time.h"

#ifdef __linux__
#include <pthread.h>
#include <sched.h>
#include <sys/resource.h>
#include <sys/syscall.h>
#include <unistd.h>
#endif

namespace kinetri::server {

namespace {

// Raises the calling thread's nice value by `delta` (Linux: nice is per
// thread); returns the value it has afterwards, or -1.
int RaiseOwnNice(int delta) {
#ifdef __linux__
  const id_t tid = static_cast<id_t>(syscall(SYS_gettid));
  errno = 0;
  const int now = getpriority(PRIO_PROCESS, tid);
  if (errno != 0) return -1;
  if (delta > 0) {
    setpriority(PRIO_PROCESS, tid, std::min(19, now + delta));
  }
  errno = 0;
  const int after = getpriority(PRIO_PROCESS, tid);
  return errno != 0 ? -1 : after;
#else
  (void)delta;
  return -1;
#endif
}

// Puts the calling thread under SCHED_IDLE (a waking thread of the normal
// policy preempts it at once); true when it is.
bool EnterIdlePolicy() {
#ifdef __linux__
  sched_param param{};
  param.sched_priority = 0;
  return pthread_setschedparam(pthread_self(), SCHED_IDLE, &param) == 0;
#else
  return false;
#endif
}

}  // namespace

QueryPool::QueryPool(int threads, int nice, bool idle) {
  threads = std::clamp(threads, 1, 1024);
  nice = std::clamp(nice, 0, 19);
  threads_.reserve(threads);
  for (int i = 0; i < threads; ++i) {
    threads_.emplace_back([this, nice, idle] { Loop(nice, idle); });
  }
}

QueryPool::~QueryPool() {
  {
    absl::MutexLock lock(&mu_);
    stopping_ = true;
  }
  for (std::thread& t : threads_) t.join();
}

int QueryPool::applied_nice() const {
  absl::MutexLock lock(&mu_);
  return applied_nice_;
}

bool QueryPool::applied_idle() const {
  absl::MutexLock lock(&mu_);
  return applied_idle_;
}

int QueryPool::queued() const {
  absl::MutexLock lock(&mu_);
  return static_cast<int>(queue_.size());
}

void QueryPool::Loop(int nice, bool idle) {
  const int applied = RaiseOwnNice(nice);
  const bool idle_policy = idle && EnterIdlePolicy();
  absl::MutexLock lock(&mu_);
  applied_nice_ = applied;
  applied_idle_ = idle_policy;
  while (true) {
    mu_.Await(absl::Condition(
        +[](QueryPool* p) ABSL_EXCLUSIVE_LOCKS_REQUIRED(p->mu_) {
          return p->stopping_ || !p->queue_.empty();
        },
        this));
    if (queue_.empty()) return;  // stopping, nothing left
    Job* job = queue_.front();
    queue_.pop_front();
    job->started = true;
    mu_.Unlock();
    job->fn();
    mu_.Lock();
    job->done = true;
  }
}

absl::Status QueryPool::Run(const core::CancelToken& cancel, const char* what,
                            absl::FunctionRef<void()> fn) {
  absl::Status st = cancel.Check(what);
  if (!st.ok()) return st;
  Job job{fn};
  absl::MutexLock lock(&mu_);
  queue_.push_back(&job);
  // Waiting in line: the token decides (every 5 ms) whether to keep waiting.
  while (!job.started) {
    mu_.AwaitWithTimeout(absl::Condition(&job.started), absl::Milliseconds(5));
    if (job.started) break;
    st = cancel.Check(what);
    if (!st.ok()) {
      queue_.erase(std::find(queue_.begin(), queue_.end(), &job));
      return st;
    }
  }
  // Running: fn polls the token itself; the job lives on this stack, so
  // wait for it to finish whatever happens.
  mu_.Await(absl::Condition(&job.done));
  return absl::OkStatus();
}

}  // namespace kinetri::server
