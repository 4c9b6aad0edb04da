#include "core/nearest_by_triangles.h"

#include <algorithm>
#include <limits>
#include <vector>

#include "core/parallel.h"
#include "core/predicates.h"
#include "core/query_walks.h"

namespace kinetri::core {
namespace {

// Triangle slots per part of the pass. A part owns the vertices whose
// vertex_edge lies in its slots and updates them directly; offers to other
// vertices (those whose fan crosses into another part, a few per cent) are
// kept and applied after every part is done.
constexpr uint32_t kPartSlots = 16384;

struct Offer {
  double d2;
  uint32_t to, from;
};

// No neighbour yet: farther than any pair of points in the exact domain
// (core/predicates.h), and no near-tie with one.
constexpr double kNone = std::numeric_limits<double>::max();

inline void Take(const Vec2* pos, uint32_t a, uint32_t b, double d2,
                 NearestNeighbor* out) {
  NearestNeighbor& r = out[a];
  // Decided by the rounded squared distances unless they are within their
  // error of each other (as CompareCloserCached). The choice is made
  // without a branch, since whether a neighbour is the closest so far is a
  // coin toss; only near-ties (rare) branch to the exact order.
  const double tol = internal::kDistErrBound * (d2 + r.d2);
  const bool closer = d2 < r.d2 - tol;
  if (closer || d2 > r.d2 + tol) {
    r.d2 = closer ? d2 : r.d2;
    r.id = closer ? b : r.id;
  } else if (CompareCloser(pos[a], pos[b], pos[r.id]) < 0) {
    r = {d2, b};
  }
}

}  // namespace

void NearestNeighborsByTriangles(const MeshView& m, const Vec2* pos,
                                 const uint32_t* vertex_edge,
                                 uint32_t num_vertices, NearestNeighbor* out) {
  const uint32_t nt = m.num_half_edges / 3;
  const size_t parts = (size_t{nt} + kPartSlots - 1) / kPartSlots;
  ParallelFor(0, num_vertices, [&](size_t v) {
    out[v] = NearestNeighbor{kNone, kNoVertex};
  });
  std::vector<std::vector<Offer>> deferred(parts);
  ParallelFor(
      0, parts,
      [&](size_t part) {
        const uint32_t lo = static_cast<uint32_t>(part * kPartSlots);
        const uint32_t hi = std::min(nt, lo + kPartSlots);
        const uint32_t first_edge = 3 * lo, end_edge = 3 * hi;
        std::vector<Offer>& later = deferred[part];
        // Half-edge a->b offers b to a.
        auto offer = [&](uint32_t a, uint32_t b, const Vec2& pa,
                         const Vec2& pb) {
          const double d2 = SquaredDistance(pa, pb);
          const uint32_t e = vertex_edge[a];
          if (e >= first_edge && e < end_edge) {
            Take(pos, a, b, d2, out);
          } else {
            later.push_back({d2, a, b});
          }
        };
        for (uint32_t t = lo; t < hi; ++t) {
          const uint32_t v[3] = {m.origin[3 * t], m.origin[3 * t + 1],
                                 m.origin[3 * t + 2]};
          if (v[0] == kNoVertex) continue;  // free slot
          if (v[0] >= kInfiniteVertex || v[1] >= kInfiniteVertex ||
              v[2] >= kInfiniteVertex) {
            // Ghost: its one finite half-edge (a hull edge).
            for (int k = 0; k < 3; ++k) {
              const uint32_t a = v[k], b = v[(k + 1) % 3];
              if (a < kInfiniteVertex && b < kInfiniteVertex) {
                offer(a, b, pos[a], pos[b]);
              }
            }
            continue;
          }
          const Vec2 p[3] = {pos[v[0]], pos[v[1]], pos[v[2]]};
          offer(v[0], v[1], p[0], p[1]);
          offer(v[1], v[2], p[1], p[2]);
          offer(v[2], v[0], p[2], p[0]);
        }
      },
      1);
  for (const std::vector<Offer>& later : deferred) {
    for (const Offer& o : later) Take(pos, o.to, o.from, o.d2, out);
  }
}

}  // namespace kinetri::core
