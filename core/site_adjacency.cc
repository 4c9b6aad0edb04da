#include "core/site_adjacency.h"

#include <algorithm>

#include "core/parallel.h"

namespace kinetri::core {

void BuildSiteAdjacency(const TriangulationView& v, SiteAdjacency* out) {
  const uint32_t n = v.num_points;
  out->offsets.assign(size_t{n} + 1, 0);
  ParallelFor(0, n, [&](size_t i) {
    const uint32_t s = static_cast<uint32_t>(i);
    if (v.rep[s] != s) return;
    uint32_t degree = 0;
    v.ForEachNeighbor(s, [&](uint32_t) { ++degree; });
    out->offsets[i + 1] = degree;
  });
  for (uint32_t i = 0; i < n; ++i) out->offsets[i + 1] += out->offsets[i];
  out->neighbours.resize(out->offsets[n]);
  ParallelFor(0, n, [&](size_t i) {
    uint32_t k = out->offsets[i];
    if (k == out->offsets[i + 1]) return;
    v.ForEachNeighbor(static_cast<uint32_t>(i),
                      [&](uint32_t w) { out->neighbours[k++] = w; });
  });
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
