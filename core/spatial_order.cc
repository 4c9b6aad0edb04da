// Hilbert-curve ordering of points, used to number vertices for locality.
#include "core/spatial_order.h"

#include <algorithm>
#include <array>
#include <utility>

#include "core/parallel.h"

namespace kinetri::core {
namespace {
constexpr int kOrder = 21;
constexpr uint32_t kSide = 1u << kOrder;
constexpr int kKeyBits = 2 * kOrder;

struct Keyed {
  uint64_t key;
  uint32_t index;
};

// Stable least-significant-digit radix sort by key (kKeyBits bits), 11 bits
// a pass: per-block histograms, then each block scatters its items in
// parallel. Stable, so equal keys keep their order (the index order the
// input has). A pass whose digit is the same for every item is skipped.
void RadixSortByKey(std::vector<Keyed>* items) {
  constexpr int kDigitBits = 11;
  constexpr size_t kBuckets = size_t{1} << kDigitBits;
  constexpr size_t kBlockItems = size_t{1} << 16;
  const size_t n = items->size();
  const size_t blocks = (n + kBlockItems - 1) / kBlockItems;
  std::vector<Keyed> other(n);
  std::vector<std::array<uint32_t, kBuckets>> hist(blocks);
  Keyed* src = items->data();
  Keyed* dst = other.data();
  for (int shift = 0; shift < kKeyBits; shift += kDigitBits) {
    auto digit = [shift](uint64_t key) {
      return static_cast<size_t>((key >> shift) & (kBuckets - 1));
    };
    ParallelFor(
        0, blocks,
        [&](size_t b) {
          hist[b].fill(0);
          const size_t end = std::min(n, (b + 1) * kBlockItems);
          for (size_t i = b * kBlockItems; i < end; ++i) {
            ++hist[b][digit(src[i].key)];
          }
        },
        1);
    // Offsets bucket-major, block-minor (stable); skip a pass that would
    // leave every item where it is.
    size_t sum = 0;
    bool one_bucket = false;
    for (size_t d = 0; d < kBuckets; ++d) {
      size_t in_bucket = 0;
      for (size_t b = 0; b < blocks; ++b) {
        const uint32_t c = hist[b][d];
        hist[b][d] = static_cast<uint32_t>(sum);
        sum += c;
        in_bucket += c;
      }
      if (in_bucket == n) one_bucket = true;
    }
    if (one_bucket) continue;
    ParallelFor(
        0, blocks,
        [&](size_t b) {
          std::array<uint32_t, kBuckets>& at = hist[b];
          const size_t end = std::min(n, (b + 1) * kBlockItems);
          for (size_t i = b * kBlockItems; i < end; ++i) {
            dst[at[digit(src[i].key)]++] = src[i];
          }
        },
        1);
    std::swap(src, dst);
  }
  if (src != items->data()) items->swap(other);
}

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
  std::vector<Keyed> keyed(n);
  ParallelFor(0, n, [&](size_t i) {
    keyed[i] = {HilbertKey(points[i], lo, hi), static_cast<uint32_t>(i)};
  });
  RadixSortByKey(&keyed);
  if (keys != nullptr) keys->resize(n);
  ParallelFor(0, n, [&](size_t i) {
    order[i] = keyed[i].index;
    if (keys != nullptr) (*keys)[i] = keyed[i].key;
  });
  return order;
}

}  // namespace kinetri::core
