// The query pool: blocks run on its threads, at most `threads` at once, at a
// raised nice value; a call cancelled while it waits in line is not run.
#include "server/query_pool.h"

#include <gtest/gtest.h>

#include <atomic>
#include <chrono>
#include <thread>
#include <vector>

#ifdef __linux__
#include <sched.h>
#include <sys/resource.h>
#include <sys/syscall.h>
#include <unistd.h>
#endif

namespace kinetri::server {
namespace {

using Clock = std::chrono::steady_clock;

int OwnNice() {
#ifdef __linux__
  return getpriority(PRIO_PROCESS, static_cast<id_t>(syscall(SYS_gettid)));
#else
  return 0;
#endif
}

TEST(QueryPool, RunsOnItsOwnLowerPriorityThreads) {
  QueryPool pool(2, 7);
  const std::thread::id caller = std::this_thread::get_id();
  const int caller_nice = OwnNice();
  std::thread::id ran_on;
  int nice_seen = -100;
  const absl::Status st = pool.Run(core::CancelToken::Never(), "q", [&] {
    ran_on = std::this_thread::get_id();
    nice_seen = OwnNice();
  });
  ASSERT_TRUE(st.ok()) << st;
  EXPECT_NE(ran_on, caller);
#ifdef __linux__
  EXPECT_EQ(nice_seen, std::min(19, caller_nice + 7));
  EXPECT_EQ(pool.applied_nice(), nice_seen);
#endif
  EXPECT_EQ(OwnNice(), caller_nice);  // the caller's priority is untouched
}

// With `idle`, the pool's threads run under SCHED_IDLE (a waking step
// preempts them at once); the caller's policy is untouched.
TEST(QueryPool, IdlePolicyForItsThreadsOnly) {
  QueryPool pool(1, 0, /*idle=*/true);
  int policy_seen = -1;
  const absl::Status st = pool.Run(core::CancelToken::Never(), "q", [&] {
#ifdef __linux__
    policy_seen = sched_getscheduler(0);
#endif
  });
  ASSERT_TRUE(st.ok()) << st;
#ifdef __linux__
  EXPECT_EQ(policy_seen, SCHED_IDLE);
  EXPECT_TRUE(pool.applied_idle());
  EXPECT_EQ(sched_getscheduler(0), SCHED_OTHER);
#endif
  QueryPool plain(1, 0);
  EXPECT_TRUE(plain
                  .Run(core::CancelToken::Never(), "q",
                       [&] {
#ifdef __linux__
                         policy_seen = sched_getscheduler(0);
#endif
                       })
                  .ok());
#ifdef __linux__
  EXPECT_EQ(policy_seen, SCHED_OTHER);
  EXPECT_FALSE(plain.applied_idle());
#endif
}

TEST(QueryPool, AtMostThreadsBlocksAtOnceAndEveryBlockRuns) {
  QueryPool pool(3, 0);
  std::atomic<int> running{0}, most{0}, done{0};
  std::vector<std::thread> callers;
  for (int c = 0; c < 12; ++c) {
    callers.emplace_back([&] {
      for (int j = 0; j < 5; ++j) {
        ASSERT_TRUE(pool.Run(core::CancelToken::Never(), "q",
                             [&] {
                               const int now = ++running;
                               int m = most.load();
                               while (now > m &&
                                      !most.compare_exchange_weak(m, now)) {
                               }
                               std::this_thread::sleep_for(
                                   std::chrono::milliseconds(2));
                               --running;
                               ++done;
                             })
                        .ok());
      }
    });
  }
  for (auto& t : callers) t.join();
  EXPECT_EQ(done.load(), 60);
  EXPECT_LE(most.load(), 3);
  EXPECT_GE(most.load(), 2);  // 12 callers keep more than one thread busy
  EXPECT_EQ(pool.queued(), 0);
}

TEST(QueryPool, CancelledWhileWaitingInLineIsNotRun) {
  QueryPool pool(1, 0);
  std::atomic<bool> release{false}, started{false};
  std::thread busy([&] {
    ASSERT_TRUE(pool.Run(core::CancelToken::Never(), "q",
                         [&] {
                           started = true;
                           while (!release) {
                             std::this_thread::sleep_for(
                                 std::chrono::milliseconds(1));
                           }
                         })
                    .ok());
  });
  while (!started) std::this_thread::sleep_for(std::chrono::milliseconds(1));
  // A deadline 30 ms away, behind a block that does not end: the call
  // gives up after its deadline, without running.
  std::atomic<bool> cancelled{false};
  const core::CancelToken deadline(
      nullptr, Clock::now() + std::chrono::milliseconds(30));
  const core::CancelToken by_client([&] { return cancelled.load(); });
  bool ran = false;
  const auto t0 = Clock::now();
  absl::Status st = pool.Run(deadline, "query", [&] { ran = true; });
  const double ms =
      std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
  EXPECT_EQ(st.code(), absl::StatusCode::kDeadlineExceeded) << st;
  EXPECT_FALSE(ran);
  EXPECT_LT(ms, 30 + 200);  // polled every 5 ms; slack for a loaded machine
  std::thread canceller([&] {
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
    cancelled = true;
  });
  st = pool.Run(by_client, "query", [&] { ran = true; });
  canceller.join();
  EXPECT_EQ(st.code(), absl::StatusCode::kCancelled) << st;
  EXPECT_FALSE(ran);
  EXPECT_EQ(pool.queued(), 0);
  release = true;
  busy.join();
  // The pool still serves.
  EXPECT_TRUE(
      pool.Run(core::CancelToken::Never(), "q", [&] { ran = true; }).ok());
  EXPECT_TRUE(ran);
}

TEST(QueryPool, AlreadyCancelledIsNotRun) {
  QueryPool pool(1, 0);
  const core::CancelToken fired([] { return true; }, Clock::time_point::max(),
                                Clock::duration::zero());
  bool ran = false;
  EXPECT_EQ(pool.Run(fired, "query", [&] { ran = true; }).code(),
            absl::StatusCode::kCancelled);
  EXPECT_FALSE(ran);
}

}  // namespace
}  // namespace kinetri::server
