// CPU executors: data-parallel loops on oneTBB's work-stealing scheduler.
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

#include <algorithm>
#include <atomic>
#include <cstddef>
#include <cstdint>
#include <vector>

namespace kinetri::core {

// *slot = min(*slot, value), atomically (relaxed): deterministic claims and
// vertex-edge repair whatever the thread order.
inline void AtomicMin(uint32_t* slot, uint32_t value) {
  std::atomic_ref<uint32_t> ref(*slot);
  uint32_t cur = ref.load(std::memory_order_relaxed);
  while (value < cur &&
         !ref.compare_exchange_weak(cur, value, std::memory_order_relaxed)) {
  }
}

// *slot = value, atomically (relaxed): for a slot several threads may reset
// to the same value at once (claims released after a round).
inline void AtomicStore(uint32_t* slot, uint32_t value) {
  std::atomic_ref<uint32_t>(*slot).store(value, std::memory_order_relaxed);
}

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

// Indices i in [0, n) with pred(i), ascending. Fixed-size blocks make the
// result independent of the thread count.
template <typename Pred>
std::vector<uint32_t> FilterIndices(size_t n, Pred&& pred) {
  constexpr size_t kBlock = 4096;
  const size_t blocks = (n + kBlock - 1) / kBlock;
  std::vector<uint32_t> count(blocks + 1, 0);
  ParallelFor(
      0, blocks,
      [&](size_t b) {
        uint32_t c = 0;
        const size_t end = std::min(n, (b + 1) * kBlock);
        for (size_t i = b * kBlock; i < end; ++i) c += pred(i) ? 1 : 0;
        count[b + 1] = c;
      },
      1);
  for (size_t b = 0; b < blocks; ++b) count[b + 1] += count[b];
  std::vector<uint32_t> out(count[blocks]);
  ParallelFor(
      0, blocks,
      [&](size_t b) {
        uint32_t k = count[b];
        const size_t end = std::min(n, (b + 1) * kBlock);
        for (size_t i = b * kBlock; i < end; ++i) {
          if (pred(i)) out[k++] = static_cast<uint32_t>(i);
        }
      },
      1);
  return out;
}

}  // namespace kinetri::core

#endif  // KINETRI_CORE_PARALLEL_H_
