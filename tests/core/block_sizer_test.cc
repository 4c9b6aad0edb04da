// The device executor's query block sizes (core/device/block_sizer.h), on
// blocks whose time is a fixed cost plus a cost per query.
#include "core/device/block_sizer.h"

#include <gtest/gtest.h>

#include <vector>

namespace kinetri::core::device {
namespace {

struct Blocks {
  std::vector<size_t> sizes;
  double longest = 0.0;  // seconds of the longest block
  size_t blocks = 0;
};

// Runs `queries` queries in blocks, each taking fixed + per_query * n.
Blocks Simulate(size_t queries, size_t max_block, bool fixed_cost_aware,
                double fixed, double per_query) {
  BlockSizer sizer(max_block, fixed_cost_aware);
  Blocks run;
  for (size_t done = 0; done < queries;) {
    const size_t n = std::min(sizer.size(), queries - done);
    const double seconds = fixed + per_query * double(n);
    run.sizes.push_back(n);
    run.longest = std::max(run.longest, seconds);
    ++run.blocks;
    sizer.Done(n, seconds);
    done += n;
  }
  return run;
}

TEST(BlockSizer, CpuBlocksGrowWhileCheapAndStayNearTheTarget) {
  // 1 us per query: blocks double from 2 ...
  Blocks cheap = Simulate(100000, 1 << 14, false, 0.0, 1e-6);
  EXPECT_EQ(cheap.sizes.front(), BlockSizer::kFirstBlock);
  EXPECT_EQ(cheap.sizes[5], 64u);
  // ... until a block takes at least half the target (4096 queries).
  EXPECT_EQ(cheap.sizes[cheap.sizes.size() - 2], 4096u);
  EXPECT_LE(cheap.longest, 2 * BlockSizer::kTargetSeconds);
  // 6 ms per query (rows of thousands of points): blocks stay at a size
  // whose time is within twice the target, so cancellation, polled between
  // blocks, stops the work soon.
  Blocks heavy = Simulate(200, 1 << 14, false, 0.0, 6e-3);
  EXPECT_LE(heavy.longest, 2 * BlockSizer::kTargetSeconds);
}

TEST(BlockSizer, GpuBlocksOutgrowAFixedCostOverTheTarget) {
  // 12 ms per block whatever its size, 10 ns per query: the rule of the CPU
  // would keep 2 queries per block (50,000 blocks for 100K queries).
  Blocks cpu_rule = Simulate(100000, 1 << 20, false, 12e-3, 1e-8);
  EXPECT_EQ(cpu_rule.sizes.back(), BlockSizer::kFirstBlock);
  EXPECT_GT(cpu_rule.blocks, 40000u);
  Blocks gpu = Simulate(100000, 1 << 20, true, 12e-3, 1e-8);
  EXPECT_LT(gpu.blocks, 20u);
  EXPECT_LE(gpu.longest, BlockSizer::kLimitSeconds);
  // A fixed cost over the limit still lets blocks grow (up to twice it).
  Blocks slow = Simulate(100000, 1 << 20, true, 40e-3, 1e-8);
  EXPECT_LT(slow.blocks, 20u);
  EXPECT_LE(slow.longest, 2 * 40e-3 + 1e-3);
}

TEST(BlockSizer, GpuBlocksOfHeavyQueriesStayShort) {
  // 6 ms per query on top of a 0.1 ms block cost: no growth past what
  // keeps a block near the target.
  Blocks heavy = Simulate(200, 1 << 20, true, 1e-4, 6e-3);
  EXPECT_LE(heavy.longest, BlockSizer::kLimitSeconds);
  // Blocks that got slower (the GPU got busy) shrink again.
  BlockSizer sizer(1 << 20, true);
  for (int i = 0; i < 12; ++i) sizer.Done(sizer.size(), 1e-3);
  const size_t grown = sizer.size();
  EXPECT_GT(grown, 1000u);
  sizer.Done(grown, 0.2);
  EXPECT_EQ(sizer.size(), grown / 2);
}

TEST(BlockSizer, AGivenFirstBlockOnAGpu) {
  // The first block a run asks for (KINETRI_DEVICE_QUERY_BLOCK), on either
  // rule; the largest block still caps it.
  EXPECT_EQ(BlockSizer(1 << 20, true, 16384).size(), 16384u);
  EXPECT_EQ(BlockSizer(1 << 20, false, 16384).size(), 16384u);
  EXPECT_EQ(BlockSizer(1000, true, 16384).size(), 1000u);
  EXPECT_EQ(BlockSizer(1 << 20, true, 0).size(), BlockSizer::kFirstBlock);
  // From there the fixed-cost rule goes on: a block all fixed cost grows.
  BlockSizer sizer(1 << 20, true, 16384);
  sizer.Done(16384, 2e-3);
  EXPECT_EQ(sizer.size(), 32768u);
}

TEST(BlockSizer, GpuBlocksStartAtTheFillAndStayThere) {
  // A GPU of 132 multiprocessors (a fill of 132 x 512 queries) where a
  // query takes 4 ms on its thread and a wave of the fill runs at once: a
  // block takes 4 ms per wave, whatever its size below the fill.
  const size_t fill = 132 * 512;
  auto seconds = [&](size_t n) { return 4e-3 * double((n + fill - 1) / fill); };
  BlockSizer sizer(1 << 20, true, 0, fill);
  EXPECT_EQ(sizer.size(), fill);
  std::vector<size_t> sizes;
  for (size_t done = 0; done < 1000000;) {
    const size_t n = std::min(sizer.size(), 1000000 - done);
    sizes.push_back(n);
    sizer.Done(n, seconds(n));
    done += n;
  }
  for (size_t n : sizes) EXPECT_GE(n, std::min(fill, sizes.back()));
  EXPECT_LT(sizes.size(), 10u);
  // Heavy queries (50 ms a wave): a block grows to two waves at most and
  // halves when it gets slower, but not below the fill, where halving
  // would not shorten it.
  BlockSizer heavy(1 << 20, true, 0, fill);
  for (int i = 0; i < 6; ++i) {
    const size_t n = heavy.size();
    heavy.Done(n, 0.05 * double((n + fill - 1) / fill));
    EXPECT_GE(heavy.size(), fill);
    EXPECT_LE(heavy.size(), 2 * fill);
  }
  heavy.Done(heavy.size(), 0.5);
  EXPECT_EQ(heavy.size(), fill);
  heavy.Done(fill, 0.5);
  EXPECT_EQ(heavy.size(), fill);
  // A given first block goes first; the CPU rule knows no fill.
  EXPECT_EQ(BlockSizer(1 << 20, true, 4096, fill).size(), 4096u);
  // A given first block below the fill lowers the floor with it: blocks
  // still halve when slow.
  BlockSizer given(1 << 20, true, 4096, fill);
  given.Done(4096, 1e-3);
  given.Done(given.size(), 0.5);
  EXPECT_EQ(given.size(), 4096u);
  given.Done(4096, 0.5);
  EXPECT_EQ(given.size(), 4096u);
  EXPECT_EQ(BlockSizer(1 << 20, false, 0, fill).size(),
            BlockSizer::kFirstBlock);
  EXPECT_EQ(BlockSizer(1000, true, 0, fill).size(), 1000u);
}

TEST(BlockSizer, ACutBlockSetsTheNext) {
  // Results over a block's memory: the next block is what fitted, below
  // the fill too; from there the rules go on.
  BlockSizer sizer(1 << 20, true, 0, 67584);
  sizer.CutTo(300);
  EXPECT_EQ(sizer.size(), 300u);
  sizer.CutTo(0);
  EXPECT_EQ(sizer.size(), 1u);
  sizer.Done(1, 1e-4);
  EXPECT_EQ(sizer.size(), 2u);
  BlockSizer small(100, false);
  small.CutTo(5000);
  EXPECT_EQ(small.size(), 100u);
}

TEST(BlockSizer, NeverBeyondTheLargestBlock) {
  Blocks run = Simulate(1000000, 5000, true, 1e-3, 0.0);
  for (size_t n : run.sizes) EXPECT_LE(n, 5000u);
  BlockSizer one(1, false);
  EXPECT_EQ(one.size(), 1u);
}

}  // namespace
}  // namespace kinetri::core::device
