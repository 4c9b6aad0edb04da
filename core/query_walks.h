// Per-query graph steps (greedy walk, reverse-search parent), host+device.
#ifndef KINETRI_CORE_QUERY_WALKS_H_
#define KINETRI_CORE_QUERY_WALKS_H_

#include <cmath>
#include <cstdint>

#include "core/hd.h"
#include "core/predicates.h"
#include "core/triangulation_view.h"

namespace kinetri::core {

// The neighbour of `site` that comes first in the CompareCloser order from q
// (or `site` itself when it precedes all of them, i.e. when include_self).
// CompareCloser(q, a, b) given the squared distances da, db computed in
// double: decided by them unless they are within rounding of each other.
KINETRI_HD inline int CompareCloserCached(const Vec2& q, const Vec2& a,
                                          double da, const Vec2& b, double db) {
  const double tol = internal::kDistErrBound * (da + db);
  if (da < db - tol) return -1;
  if (da > db + tol) return 1;
  return CompareCloser(q, a, b);
}

KINETRI_HD inline double SquaredDistance(const Vec2& q, const Vec2& p) {
  const double dx = q.x - p.x, dy = q.y - p.y;
  return dx * dx + dy * dy;
}

KINETRI_HD inline uint32_t FirstNeighbor(const TriangulationView& v,
                                         const Vec2& q, uint32_t site,
                                         bool include_self) {
  // Squared distances in double decide when they differ by more than their
  // rounding error; only near-ties go to the exact CompareCloser.
  auto d2 = [&](uint32_t x) { return SquaredDistance(q, v.pos[x]); };
  uint32_t best = include_self ? site : kNoVertex;
  double best_d2 = include_self ? d2(site) : 0.0;
  v.ForEachNeighbor(site, [&](uint32_t w) {
    const double dw = d2(w);
    if (best == kNoVertex) {
      best = w;
      best_d2 = dw;
      return;
    }
    if (CompareCloserCached(q, v.pos[w], dw, v.pos[best], best_d2) < 0) {
      best = w;
      best_d2 = dw;
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

// The nearest other point of internal point `in` (all-points NN, one
// element): coincident points first (distance 0, smallest external id), else
// the first Delaunay neighbour site and its smallest external id. Returns
// false when the point has no other point.
KINETRI_HD inline bool NearestOtherPoint(const TriangulationView& v,
                                         uint32_t in, uint32_t* nn_ext,
                                         double* distance) {
  if (v.num_sites == v.num_points) {
    // Every point is a site of its own: the nearest site is the answer.
    const uint32_t w = FirstNeighbor(v, v.pos[in], in, false);
    if (w == kNoVertex) return false;
    const double dx = v.pos[in].x - v.pos[w].x;
    const double dy = v.pos[in].y - v.pos[w].y;
    *nn_ext = v.ext_of_int[w];
    *distance = sqrt(dx * dx + dy * dy);
    return true;
  }
  const uint32_t ext = v.ext_of_int[in];
  const uint32_t site = v.rep[in];
  uint32_t best = kNoVertex;
  for (uint32_t p = site; p != kNoVertex; p = v.dup_next[p]) {
    const uint32_t e = v.ext_of_int[p];
    if (e != ext && e < best) best = e;
  }
  if (best != kNoVertex) {
    *nn_ext = best;
    *distance = 0.0;
    return true;
  }
  const uint32_t w = FirstNeighbor(v, v.pos[site], site, false);
  if (w == kNoVertex) return false;
  for (uint32_t p = w; p != kNoVertex; p = v.dup_next[p]) {
    const uint32_t e = v.ext_of_int[p];
    if (e < best) best = e;
  }
  const double dx = v.pos[site].x - v.pos[w].x;
  const double dy = v.pos[site].y - v.pos[w].y;
  *nn_ext = best;
  *distance = sqrt(dx * dx + dy * dy);
  return true;
}

}  // namespace kinetri::core

#endif  // KINETRI_CORE_QUERY_WALKS_H_
