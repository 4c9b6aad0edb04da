// CPU executor: data-parallel loops on oneTBB's work-stealing scheduler.
//
// Why TBB rather than a hand-rolled std::thread pool: it is a Debian package
// with a CMake config, balances uneven loops (flip worklists shrink from
// millions to a handful of edges) by work stealing, and task_arena gives a
// per-triangulation thread limit that tests use to compare 1 thread against
// all threads. All algorithms here are written so that their result does not
// depend on how TBB splits a range.
#ifndef KINETRI_CORE_PARALLEL_H_
#define KINETRI_CORE_PARALLEL_H_

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include <cstddef>
#include <cstdint>

namespace kinetri::core {

// Calls fn(i) for i in [begin, end) in parallel.
template <typename Fn>
void ParallelFor(size_t begin, size_t end, Fn&& fn, size_t grain = 2048) {
  if (end <= begin) return;
  if (end - begin <= grain) {
    for (size_t i = begin; i < end; ++i) fn(i);
    return;
  }
  tbb::parallel_for(tbb::blocked_range<size_t>(begin, end, grain),
                    [&](const tbb::blocked_range<size_t>& r) {
                      for (size_t i = r.begin(); i != r.end(); ++i) fn(i);
                    });
}

// Calls fn(lo, hi) on disjoint chunks covering [begin, end).
template <typename Fn>
void ParallelChunks(size_t begin, size_t end, Fn&& fn, size_t grain = 2048) {
  if (end <= begin) return;
  if (end - begin <= grain) {
    fn(begin, end);
    return;
  }
  tbb::parallel_for(tbb::blocked_range<size_t>(begin, end, grain),
                    [&](const tbb::blocked_range<size_t>& r) {
                      fn(r.begin(), r.end());
                    });
}

}  // namespace kinetri::core

#endif  // KINETRI_CORE_PARALLEL_H_
