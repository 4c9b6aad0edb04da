// Hilbert keys and order (core/spatial_order.h).
#include "core/spatial_order.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cstdint>
#include <numeric>
#include <random>
#include <utility>
#include <vector>

namespace kinetri::core {
namespace {

constexpr int kOrder = 21;
constexpr uint32_t kSide = 1u << kOrder;

// The textbook xy -> d conversion (branches per level), on the same
// quantisation as HilbertKey: the reference the branch-free one must equal.
uint64_t ReferenceKey(uint32_t x, uint32_t y) {
  uint64_t d = 0;
  for (uint32_t s = kSide / 2; s > 0; s /= 2) {
    const uint32_t rx = (x & s) ? 1 : 0;
    const uint32_t ry = (y & s) ? 1 : 0;
    d += static_cast<uint64_t>(s) * s * ((3 * rx) ^ ry);
    if (ry == 0) {
      if (rx == 1) {
        x = kSide - 1 - x;
        y = kSide - 1 - y;
      }
      std::swap(x, y);
    }
  }
  return d;
}

// Points on the grid cells of the curve: lo = 0, hi = kSide - 1, so that
// quantisation is the identity on integer coordinates.
uint64_t KeyOfCell(uint32_t x, uint32_t y) {
  return HilbertKey(Vec2{double(x), double(y)}, Vec2{0, 0},
                    Vec2{double(kSide - 1), double(kSide - 1)});
}

TEST(SpatialOrder, KeyEqualsTheTextbookCurve) {
  std::mt19937_64 rng(7);
  std::uniform_int_distribution<uint32_t> cell(0, kSide - 1);
  for (int i = 0; i < 200000; ++i) {
    const uint32_t x = cell(rng), y = cell(rng);
    ASSERT_EQ(KeyOfCell(x, y), ReferenceKey(x, y)) << x << " " << y;
  }
  for (uint32_t x : {0u, 1u, kSide / 2 - 1, kSide / 2, kSide - 2, kSide - 1}) {
    for (uint32_t y :
         {0u, 1u, kSide / 2 - 1, kSide / 2, kSide - 2, kSide - 1}) {
      EXPECT_EQ(KeyOfCell(x, y), ReferenceKey(x, y)) << x << " " << y;
    }
  }
}

TEST(SpatialOrder, CurveVisitsEveryCellOnceInUnitSteps) {
  // On a 64 x 64 corner of the curve's first quadrants: consecutive keys
  // are neighbouring cells (the curve is continuous), every key once.
  constexpr uint32_t kSmall = 64;
  std::vector<std::pair<uint64_t, std::pair<uint32_t, uint32_t>>> cells;
  for (uint32_t x = 0; x < kSmall; ++x) {
    for (uint32_t y = 0; y < kSmall; ++y) {
      cells.push_back({KeyOfCell(x, y), {x, y}});
    }
  }
  std::sort(cells.begin(), cells.end());
  for (size_t i = 0; i < cells.size(); ++i) {
    EXPECT_EQ(cells[i].first, i);  // the corner is a prefix of the curve
    if (i == 0) continue;
    const auto [x0, y0] = cells[i - 1].second;
    const auto [x1, y1] = cells[i].second;
    EXPECT_EQ((x0 > x1 ? x0 - x1 : x1 - x0) + (y0 > y1 ? y0 - y1 : y1 - y0), 1u)
        << i;
  }
}

// HilbertOrder sorts by a parallel radix sort in blocks of 64K points:
// sizes on both sides of a block, equal keys, points bunched so that some
// digits are equal everywhere (passes skipped), and all points equal.
void ExpectSortedByKeyThenIndex(const std::vector<Vec2>& pts) {
  const std::vector<uint32_t> order = HilbertOrder(pts);
  ASSERT_EQ(order.size(), pts.size());
  std::vector<uint32_t> seen = order;
  std::sort(seen.begin(), seen.end());
  std::vector<uint32_t> all(pts.size());
  std::iota(all.begin(), all.end(), 0u);
  EXPECT_EQ(seen, all);
  Vec2 lo = pts[0], hi = pts[0];
  for (const Vec2& p : pts) {
    lo = {std::min(lo.x, p.x), std::min(lo.y, p.y)};
    hi = {std::max(hi.x, p.x), std::max(hi.y, p.y)};
  }
  for (size_t i = 1; i < order.size(); ++i) {
    const uint64_t a = HilbertKey(pts[order[i - 1]], lo, hi);
    const uint64_t b = HilbertKey(pts[order[i]], lo, hi);
    ASSERT_TRUE(a < b || (a == b && order[i - 1] < order[i])) << i;
  }
}

TEST(SpatialOrder, OrderIsThePermutationSortedByKeyThenIndex) {
  std::mt19937_64 rng(8);
  std::uniform_real_distribution<double> u(-3.0, 5.0);
  for (size_t n : {size_t{5000}, size_t{200000}}) {
    std::vector<Vec2> pts(n);
    for (Vec2& p : pts) p = {u(rng), u(rng)};
    for (int i = 0; i < 100; ++i) pts.push_back(pts[i]);  // equal keys
    ExpectSortedByKeyThenIndex(pts);
  }
  // Bunched in one corner cell of the curve but two (the bounding box).
  std::uniform_real_distribution<double> tiny(0.0, 1e-5);
  std::vector<Vec2> bunched(70000);
  for (Vec2& p : bunched) p = {tiny(rng), tiny(rng)};
  bunched.push_back({1.0, 1.0});
  bunched.push_back({0.0, 1.0});
  ExpectSortedByKeyThenIndex(bunched);
  // All equal: every key equal, the order is the index order.
  const std::vector<Vec2> same(70000, Vec2{0.5, 0.25});
  const std::vector<uint32_t> order = HilbertOrder(same);
  for (uint32_t i = 0; i < order.size(); ++i) ASSERT_EQ(order[i], i);
}

}  // namespace
}  // namespace kinetri::core
