// Hilbert-curve ordering of points, used to number vertices for locality.
#include "core/spatial_order.h"

#include <tbb/parallel_sort.h>

#include <algorithm>
#include <utility>

#include "core/parallel.h"

namespace kinetri::core {
namespace {
constexpr int kOrder = 21;
constexpr uint32_t kSide = 1u << kOrder;

uint32_t Quantize(double v, double lo, double hi) {
  if (!(hi > lo)) return 0;
  const double t = (v - lo) / (hi - lo) * static_cast<double>(kSide - 1);
  if (!(t > 0.0)) return 0;
  if (t >= static_cast<double>(kSide - 1)) return kSide - 1;
  return static_cast<uint32_t>(t);
}
}  // namespace

uint64_t HilbertKey(const Vec2& p, const Vec2& lo, const Vec2& hi) {
  uint32_t x = Quantize(p.x, lo.x, hi.x);
  uint32_t y = Quantize(p.y, lo.y, hi.y);
  // Level by level from the top bit: the quadrant's two bits, then the
  // rotation of what is left (ry == 0: complement if rx == 1, then swap),
  // with masks instead of branches (the quadrants are unpredictable).
  uint64_t d = 0;
  for (int k = kOrder - 1; k >= 0; --k) {
    const uint32_t rx = (x >> k) & 1u;
    const uint32_t ry = (y >> k) & 1u;
    d = (d << 2) | ((3u * rx) ^ ry);
    const uint32_t flip = (0u - (rx & (ry ^ 1u))) & (kSide - 1);
    x ^= flip;
    y ^= flip;
    const uint32_t swap = (x ^ y) & (0u - (ry ^ 1u));
    x ^= swap;
    y ^= swap;
  }
  return d;
}

std::vector<uint32_t> HilbertOrder(absl::Span<const Vec2> points,
                                   std::vector<uint64_t>* keys) {
  const size_t n = points.size();
  std::vector<uint32_t> order(n);
  if (keys != nullptr) keys->clear();
  if (n == 0) return order;
  Vec2 lo = points[0], hi = points[0];
  for (const Vec2& p : points) {
    lo.x = std::min(lo.x, p.x);
    lo.y = std::min(lo.y, p.y);
    hi.x = std::max(hi.x, p.x);
    hi.y = std::max(hi.y, p.y);
  }
  std::vector<std::pair<uint64_t, uint32_t>> keyed(n);
  ParallelFor(0, n, [&](size_t i) {
    keyed[i] = {HilbertKey(points[i], lo, hi), static_cast<uint32_t>(i)};
  });
  tbb::parallel_sort(keyed.begin(), keyed.end());
  for (size_t i = 0; i < n; ++i) order[i] = keyed[i].second;
  if (keys != nullptr) {
    keys->resize(n);
    for (size_t i = 0; i < n; ++i) (*keys)[i] = keyed[i].first;
  }
  return order;
}

}  // namespace kinetri::core
