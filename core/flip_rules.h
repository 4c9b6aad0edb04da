// Per-element steps of fixing and legalizing, written once for CPU and GPU.
//
// Each function reads one triangle or edge of the mesh and the vertex
// positions and decides locally; executors (core/kinetic.cc on CPU threads, a
// CUDA kernel on the GPU) call them element by element.
//
// Validity of the closed mesh (see core/mesh.h for ghost triangles):
//   * a finite triangle is valid iff it is strictly counter-clockwise;
//   * a ghost triangle owns the hull turn at the finite vertex a of its spoke
//     half-edge a->inf; it is valid iff the hull turns left at a, or goes
//     straight on through a (collinear hull points are hull vertices).
// All triangles valid and a hull that winds once (HullWindsOnce) imply the
// mesh is an embedding: every point of the hull's interior is covered by
// exactly as many triangles as the hull winds around it, i.e. once.
#ifndef KINETRI_CORE_FLIP_RULES_H_
#define KINETRI_CORE_FLIP_RULES_H_

#include <cstdint>

#include "core/hd.h"
#include "core/mesh.h"
#include "core/predicates.h"
#include "core/vec2.h"

namespace kinetri::core::rules {

// The kinds of flips the fixing step performs (see ProposeFixFlip).
enum FixFlipKind : uint32_t {
  kNoFlip = 0,
  kInteriorFlip = 1,  // both triangles finite
  kHullAbsorb = 2,    // a vertex crossed a hull edge: it joins the hull
  kHullRelease = 3,   // a hull vertex became reflex: it leaves the hull
};

// Given p, a, q collinear: is a strictly between p and q?
KINETRI_HD inline bool StrictlyBetween(const Vec2& p, const Vec2& a,
                                       const Vec2& q) {
  return (LexLess(p, a) && LexLess(a, q)) || (LexLess(q, a) && LexLess(a, p));
}

// Hull turn p -> a -> q (counter-clockwise hull order) is convex or straight.
// (pos: a pointer to the positions, or anything indexed as one, such as
// PosWith below.)
template <typename Pos>
KINETRI_HD inline bool TurnOk(const Pos& pos, uint32_t p, uint32_t a,
                              uint32_t q) {
  if (p == q || p == a || a == q || p == kInfiniteVertex ||
      q == kInfiniteVertex || a == kInfiniteVertex) {
    return false;
  }
  const int o = Orient2d(pos[p], pos[a], pos[q]);
  if (o != 0) return o > 0;
  return StrictlyBetween(pos[p], pos[a], pos[q]);
}

// The half-edge a->inf of ghost triangle t (a finite), or kNoEdge.
KINETRI_HD inline uint32_t SpokeOf(const MeshView& m, uint32_t t) {
  for (uint32_t e = 3 * t; e < 3 * t + 3; ++e) {
    if (m.origin[e] != kInfiniteVertex && m.Dest(e) == kInfiniteVertex) {
      return e;
    }
  }
  return kNoEdge;
}

// Hull neighbours of the spoke's vertex: previous and next in CCW order.
KINETRI_HD inline uint32_t SpokePrev(const MeshView& m, uint32_t spoke) {
  return m.origin[Prev(m.twin[spoke])];
}
KINETRI_HD inline uint32_t SpokeNext(const MeshView& m, uint32_t spoke) {
  return m.origin[Prev(spoke)];
}

template <typename Pos>
KINETRI_HD inline bool TriangleOk(const MeshView& m, const Pos& pos,
                                  uint32_t t) {
  const uint32_t a = m.origin[3 * t], b = m.origin[3 * t + 1],
                 c = m.origin[3 * t + 2];
  if (a == kNoVertex) return true;  // free slot
  if (a == kInfiniteVertex || b == kInfiniteVertex || c == kInfiniteVertex) {
    const uint32_t s = SpokeOf(m, t);
    if (s == kNoEdge) return false;
    return TurnOk(pos, SpokePrev(m, s), m.origin[s], SpokeNext(m, s));
  }
  return Orient2d(pos[a], pos[b], pos[c]) > 0;
}

// The positions with vertex u's replaced by pu (what-if tests of the rules
// above, without writing the shared array).
struct PosWith {
  const Vec2* pos;
  uint32_t u;
  Vec2 pu;
  KINETRI_HD const Vec2& operator[](uint32_t i) const {
    return i == u ? pu : pos[i];
  }
};

// Calls fn(t) for every triangle around the origin of half-edge e0 and, for
// its ghost triangles, their three neighbours (the hull turns at the
// origin's hull neighbours read its position too): every triangle whose
// TriangleOk reads that vertex. Triangles may come more than once.
template <typename Fn>
KINETRI_HD inline void ForEachStarAndHullRing(const MeshView& m, uint32_t e0,
                                              Fn&& fn) {
  if (e0 == kNoEdge) return;
  uint32_t e = e0;
  do {
    const uint32_t t = TriangleOf(e);
    fn(t);
    if (m.IsGhost(t)) {
      for (uint32_t h = 3 * t; h < 3 * t + 3; ++h) fn(TriangleOf(m.twin[h]));
    }
    e = m.twin[Prev(e)];
  } while (e != e0);
}

// A half-edge leaving each vertex whose position TriangleOk(t) reads: t's
// own for a finite triangle; for a ghost triangle those of its hull turn
// (the previous hull vertex, the spoke's, the next). False for a ghost
// triangle without a spoke.
KINETRI_HD inline bool DecidingEdges(const MeshView& m, uint32_t t,
                                     uint32_t edge[3]) {
  if (m.IsGhost(t)) {
    const uint32_t s = SpokeOf(m, t);
    if (s == kNoEdge) return false;
    edge[0] = Prev(m.twin[s]);
    edge[1] = s;
    edge[2] = Prev(s);
  } else {
    for (uint32_t k = 0; k < 3; ++k) edge[k] = 3 * t + k;
  }
  return true;
}

// The hold-back rule: the culprits of an invalid triangle t that no flip
// repairs, among the vertices its TriangleOk reads (its corners; for a
// ghost triangle the three of its hull turn) for which moving(u) holds
// (u moved and may still be held back: pos[u] != from[u] at least): the
// one whose old position alone makes t valid (the farthest moved if several
// do), else every moving one. Writes them, each with a half-edge leaving it
// (for its star), to vertex[] / edge[] and returns how many (0: none).
template <typename Moving>
KINETRI_HD inline int Culprits(const MeshView& m, const Vec2* pos,
                               const Vec2* from, uint32_t t,
                               const Moving& moving, uint32_t vertex[3],
                               uint32_t edge[3]) {
  uint32_t cand[3], out_edge[3];
  if (!DecidingEdges(m, t, out_edge)) return 0;
  for (int k = 0; k < 3; ++k) cand[k] = m.origin[out_edge[k]];
  int best = -1;
  double best_d = -1.0;
  bool any = false;
  for (int k = 0; k < 3; ++k) {
    const uint32_t u = cand[k];
    if (u == kInfiniteVertex || u == kNoVertex || !moving(u)) continue;
    any = true;
    const double dx = pos[u].x - from[u].x, dy = pos[u].y - from[u].y;
    const double d = dx * dx + dy * dy;
    if (d > best_d && TriangleOk(m, PosWith{pos, u, from[u]}, t)) {
      best = k;
      best_d = d;
    }
  }
  if (!any) return 0;
  int n = 0;
  for (int k = 0; k < 3; ++k) {
    const uint32_t u = cand[k];
    if (best >= 0 && k != best) continue;
    if (u == kInfiniteVertex || u == kNoVertex || !moving(u)) continue;
    vertex[n] = u;
    edge[n] = out_edge[k];
    ++n;
  }
  return n;
}

// Every triangle may be read (the unbounded rules).
struct AnyTriangle {
  KINETRI_HD bool operator()(uint32_t) const { return true; }
};

// Reads of the rules below go through may_read(t) (a triangle slot) before
// they touch a triangle other than the one they start from; a refusal sets
// *outside and the answer is then meaningless. Executors that fix in
// regions in parallel pass their region's bounds: the rule then reads
// only what the region owns, and a refused element goes to a serial pass.

// True iff u and w are joined by an edge. `e` is any half-edge leaving u.
template <typename MayRead>
KINETRI_HD inline bool Adjacent(const MeshView& m, uint32_t e, uint32_t w,
                                const MayRead& may_read, bool* outside,
                                uint32_t max_degree = 1u << 16) {
  uint32_t x = e;
  for (uint32_t i = 0; i < max_degree; ++i) {
    if (m.Dest(x) == w) return true;
    x = m.twin[Prev(x)];
    if (x == e) return false;
    if (!may_read(TriangleOf(x))) {
      *outside = true;
      return false;
    }
  }
  return true;
}
KINETRI_HD inline bool Adjacent(const MeshView& m, uint32_t e, uint32_t w,
                                uint32_t max_degree = 1u << 16) {
  bool outside = false;
  return Adjacent(m, e, w, AnyTriangle{}, &outside, max_degree);
}

// True iff the origin of e is a hull vertex (joined to the infinite vertex).
KINETRI_HD inline bool OnHull(const MeshView& m, uint32_t e) {
  return Adjacent(m, e, kInfiniteVertex);
}

struct FixProposal {
  uint32_t edge = kNoEdge;  // half-edge to flip
  uint32_t kind = kNoFlip;  // FixFlipKind
  // Endpoints of the edge the flip creates. Flips that create edges at a
  // shared vertex never run in the same round (vertex claims), so no round
  // can create the same edge twice.
  uint32_t new_u = kNoVertex;
  uint32_t new_w = kNoVertex;
};

// For an invalid triangle t, proposes one flip that makes t valid; kNoFlip if
// no such flip exists (the step is then split or falls back). Termination:
// interior flips and hull absorptions lower the number of invalid finite
// triangles; hull releases keep it (they create one valid triangle) and
// shrink the hull by one vertex. So (invalid finite triangles, hull size)
// decreases lexicographically with every flip.
template <typename MayRead>
KINETRI_HD inline FixProposal ProposeFixFlip(const MeshView& m, const Vec2* pos,
                                             uint32_t t,
                                             const MayRead& may_read,
                                             bool* outside) {
  FixProposal out;
  // May the triangle of half-edge h be read? Else the proposal is refused.
  auto readable = [&](uint32_t h) {
    if (may_read(TriangleOf(h))) return true;
    *outside = true;
    return false;
  };
  if (m.IsGhost(t)) {
    // kHullRelease: spoke a->inf with hull p -> a -> q reflex at a.
    const uint32_t e = SpokeOf(m, t);
    if (e == kNoEdge) return out;
    const uint32_t a = m.origin[e];
    const uint32_t te = m.twin[e];
    if (!readable(te)) return out;
    const uint32_t p = m.origin[Prev(te)], q = SpokeNext(m, e);
    const uint32_t tp = m.twin[Prev(te)];
    if (!readable(tp)) return out;
    const uint32_t pp = m.origin[Prev(tp)];
    const uint32_t tn = m.twin[Next(e)];
    if (!readable(tn)) return out;
    const uint32_t qq = m.origin[Prev(tn)];
    if (p == q || pp == q || pp == a || qq == a) return out;  // hull <= 3
    if (Orient2d(pos[p], pos[q], pos[a]) <= 0) return out;
    // p-q exists already?
    if (Adjacent(m, Prev(te), q, may_read, outside) || *outside) return out;
    out.edge = e;
    out.kind = kHullRelease;
    out.new_u = p;
    out.new_w = q;
    return out;
  }
  for (uint32_t e = 3 * t; e < 3 * t + 3; ++e) {
    const uint32_t f = m.twin[e];
    if (!readable(f)) return out;
    const uint32_t a = m.origin[e], b = m.origin[f];
    const uint32_t c = m.Apex(e), d = m.Apex(f);
    if (d != kInfiniteVertex) {
      if (c != d && Orient2d(pos[d], pos[c], pos[a]) > 0 &&
          Orient2d(pos[c], pos[d], pos[b]) > 0) {
        const bool exists = Adjacent(m, Prev(e), d, may_read, outside);
        if (*outside) return out;
        if (!exists) {
          out.edge = e;
          out.kind = kInteriorFlip;
          out.new_u = c;
          out.new_w = d;
          return out;
        }
      }
      continue;
    }
    // a->b is a hull edge; c would join the hull between a and b.
    const bool on_hull =
        Adjacent(m, Prev(e), kInfiniteVertex, may_read, outside);
    if (*outside) return out;
    if (on_hull) continue;
    if (!TurnOk(pos, a, c, b)) continue;
    out.edge = e;
    out.kind = kHullAbsorb;
    out.new_u = c;
    return out;
  }
  return out;
}
KINETRI_HD inline FixProposal ProposeFixFlip(const MeshView& m, const Vec2* pos,
                                             uint32_t t) {
  bool outside = false;
  return ProposeFixFlip(m, pos, t, AnyTriangle{}, &outside);
}

// Is the edge of half-edge e not locally Delaunay (with the symbolic
// perturbation)? Hull edges and spokes are always legal in a valid mesh.
KINETRI_HD inline bool IsIllegal(const MeshView& m, const Vec2* pos,
                                 uint32_t e) {
  if (m.origin[e] == kNoVertex) return false;  // free slot
  const uint32_t a = m.origin[e], b = m.Dest(e);
  const uint32_t c = m.Apex(e), d = m.Across(e);
  if (a == kInfiniteVertex || b == kInfiniteVertex || c == kInfiniteVertex ||
      d == kInfiniteVertex) {
    return false;
  }
  return InCircleSoS(pos[a], pos[b], pos[c], pos[d]) > 0;
}

// The six triangles a flip of e reads or writes: its two triangles and their
// four neighbours. Flips with disjoint footprints can run concurrently.
KINETRI_HD inline void FlipFootprint(const MeshView& m, uint32_t e,
                                     uint32_t out[6]) {
  const uint32_t f = m.twin[e];
  out[0] = TriangleOf(e);
  out[1] = TriangleOf(f);
  out[2] = TriangleOf(m.twin[Next(e)]);
  out[3] = TriangleOf(m.twin[Prev(e)]);
  out[4] = TriangleOf(m.twin[Next(f)]);
  out[5] = TriangleOf(m.twin[Prev(f)]);
}

}  // namespace kinetri::core::rules

#endif  // KINETRI_CORE_FLIP_RULES_H_
