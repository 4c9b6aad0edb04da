// Per-query graph steps (greedy walk, reverse-search parent), host+device.
#ifndef KINETRI_CORE_QUERY_WALKS_H_
#define KINETRI_CORE_QUERY_WALKS_H_

#include <cstdint>

#include "core/hd.h"
#include "core/predicates.h"
#include "core/triangulation_view.h"

namespace kinetri::core {

// The neighbour of `site` that comes first in the CompareCloser order from q
// (or `site` itself when it precedes all of them, i.e. when include_self).
KINETRI_HD inline uint32_t FirstNeighbor(const TriangulationView& v,
                                         const Vec2& q, uint32_t site,
                                         bool include_self) {
  uint32_t best = include_self ? site : kNoVertex;
  v.ForEachNeighbor(site, [&](uint32_t w) {
    if (best == kNoVertex || CompareCloser(q, v.pos[w], v.pos[best]) < 0) {
      best = w;
    }
  });
  return best;
}

// Greedy walk from `start` to the site that comes first from q.
KINETRI_HD inline uint32_t WalkToNearestSite(const TriangulationView& v,
                                             const Vec2& q, uint32_t start) {
  uint32_t cur = start;
  while (true) {
    const uint32_t next = FirstNeighbor(v, q, cur, /*include_self=*/true);
    if (next == cur) return cur;
    cur = next;
  }
}

}  // namespace kinetri::core

#endif  // KINETRI_CORE_QUERY_WALKS_H_
