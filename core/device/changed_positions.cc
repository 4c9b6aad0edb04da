#include "core/device/changed_positions.h"

#include <atomic>
#include <cstring>

#include "core/parallel.h"

namespace kinetri::core::device {

namespace {

constexpr size_t kBlock = size_t{1} << 14;

inline bool Differs(const Vec2& a, const Vec2& b) {
  static_assert(sizeof(Vec2) == 2 * sizeof(uint64_t));
  uint64_t x[2], y[2];
  std::memcpy(x, &a, sizeof x);
  std::memcpy(y, &b, sizeof y);
  return ((x[0] ^ y[0]) | (x[1] ^ y[1])) != 0;
}

}  // namespace

bool ChangedPositions(absl::Span<const Vec2> now, absl::Span<const Vec2> mirror,
                      size_t most, std::vector<uint32_t>* index,
                      std::vector<Vec2>* value) {
  const size_t n = now.size();
  const size_t blocks = (n + kBlock - 1) / kBlock;
  // Count per block; blocks stop counting once the total is over `most`.
  std::vector<uint32_t> count(blocks + 1, 0);
  std::atomic<size_t> total{0};
  ParallelFor(
      0, blocks,
      [&](size_t b) {
        if (total.load(std::memory_order_relaxed) > most) return;
        const size_t end = std::min(n, (b + 1) * kBlock);
        uint32_t c = 0;
        for (size_t i = b * kBlock; i < end; ++i)
          c += Differs(now[i], mirror[i]);
        count[b] = c;
        total.fetch_add(c, std::memory_order_relaxed);
      },
      1);
  if (total.load() > most) return false;
  // Offsets, then each block with changes writes its own.
  uint32_t at = 0;
  for (size_t b = 0; b < blocks; ++b) {
    const uint32_t c = count[b];
    count[b] = at;
    at += c;
  }
  count[blocks] = at;
  index->resize(at);
  value->resize(at);
  ParallelFor(
      0, blocks,
      [&](size_t b) {
        uint32_t out = count[b];
        if (out == count[b + 1]) return;
        const size_t end = std::min(n, (b + 1) * kBlock);
        for (size_t i = b * kBlock; i < end; ++i) {
          if (Differs(now[i], mirror[i])) {
            (*index)[out] = static_cast<uint32_t>(i);
            (*value)[out] = now[i];
            ++out;
          }
        }
      },
      1);
  return true;
}

bool ChangedPositionsAt(absl::Span<const Vec2> now,
                        absl::Span<const Vec2> mirror,
                        absl::Span<const uint32_t> written, size_t most,
                        std::vector<uint32_t>* index,
                        std::vector<Vec2>* value) {
  index->clear();
  value->clear();
  for (const uint32_t i : written) {
    if (!Differs(now[i], mirror[i])) continue;
    if (index->size() == most) return false;
    index->push_back(i);
    value->push_back(now[i]);
  }
  return true;
}

}  // namespace kinetri::core::device
