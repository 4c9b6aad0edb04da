#include "core/site_adjacency.h"

#include <algorithm>
#include <cstdint>
#include <vector>

#include "core/parallel.h"

namespace kinetri::core {

void BuildSiteAdjacency(const TriangulationView& v, SiteAdjacency* out) {
  const uint32_t n = v.num_points;
  out->offsets.assign(size_t{n} + 1, 0);
  // One walk of each fan: blocks of sites write their rows to buffers of
  // their own (and each site's degree to offsets), then, once the blocks'
  // starts are known, the degrees become offsets and the buffers are copied
  // into place. (Walking every fan twice, to count and then to fill, cost
  // about as much again: the walks are chains of dependent loads.)
  constexpr uint32_t kBlock = 4096;
  const size_t blocks = (size_t{n} + kBlock - 1) / kBlock;
  std::vector<std::vector<uint32_t>> rows(blocks);
  std::vector<uint64_t> block_start(blocks + 1, 0);
  ParallelFor(
      0, blocks,
      [&](size_t b) {
        std::vector<uint32_t>& row = rows[b];
        row.reserve(size_t{kBlock} * 6 + 64);
        const uint32_t hi = static_cast<uint32_t>(
            std::min<size_t>(n, (b + 1) * size_t{kBlock}));
        for (uint32_t s = static_cast<uint32_t>(b * kBlock); s < hi; ++s) {
          if (v.rep[s] != s) continue;
          const size_t before = row.size();
          v.ForEachNeighbor(s, [&](uint32_t w) { row.push_back(w); });
          out->offsets[s + 1] = static_cast<uint32_t>(row.size() - before);
        }
        block_start[b + 1] = row.size();
      },
      1);
  for (size_t b = 0; b < blocks; ++b) block_start[b + 1] += block_start[b];
  out->neighbours.resize(block_start[blocks]);
  ParallelFor(
      0, blocks,
      [&](size_t b) {
        const uint32_t hi = static_cast<uint32_t>(
            std::min<size_t>(n, (b + 1) * size_t{kBlock}));
        uint32_t at = static_cast<uint32_t>(block_start[b]);
        for (uint32_t s = static_cast<uint32_t>(b * kBlock); s < hi; ++s) {
          at += out->offsets[s + 1];
          out->offsets[s + 1] = at;
        }
        std::copy(rows[b].begin(), rows[b].end(),
                  out->neighbours.begin() + block_start[b]);
      },
      1);
  out->member_offsets.clear();
  out->members.clear();
  bool any_duplicates = false;
  for (uint32_t i = 0; i < n && !any_duplicates; ++i) {
    any_duplicates = v.dup_next[i] != kNoVertex;
  }
  if (!any_duplicates) return;
  out->member_offsets.assign(size_t{n} + 1, 0);
  ParallelFor(0, n, [&](size_t i) {
    if (v.rep[i] != i) return;
    uint32_t count = 0;
    for (uint32_t p = static_cast<uint32_t>(i); p != kNoVertex;
         p = v.dup_next[p]) {
      ++count;
    }
    out->member_offsets[i + 1] = count;
  });
  for (uint32_t i = 0; i < n; ++i) {
    out->member_offsets[i + 1] += out->member_offsets[i];
  }
  out->members.resize(out->member_offsets[n]);
  ParallelFor(0, n, [&](size_t i) {
    uint32_t k = out->member_offsets[i];
    const uint32_t begin = k;
    if (k == out->member_offsets[i + 1]) return;
    for (uint32_t p = static_cast<uint32_t>(i); p != kNoVertex;
         p = v.dup_next[p]) {
      out->members[k++] = v.ext_of_int[p];
    }
    std::sort(out->members.begin() + begin, out->members.begin() + k);
  });
}

}  // namespace kinetri::core
