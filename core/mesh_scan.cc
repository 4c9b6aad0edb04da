#include "core/mesh_scan.h"

#include <cmath>

#include "core/flip_rules.h"
#include "core/predicates.h"

namespace kinetri::core {
namespace {

// Where the compiler can, the scan is compiled twice and the one for the
// wider vector units is picked at load time. Both round every operation
// alike (no contraction into FMA: -ffp-contract=off), so the error bounds
// of core/predicates.h hold for both. Not under the sanitizers: the
// resolver that picks runs before they are set up (ThreadSanitizer's
// instrumented resolver crashes at load).
#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__) && \
    !defined(__SANITIZE_ADDRESS__) && !defined(__SANITIZE_THREAD__)
#define KINETRI_VECTOR_CLONES __attribute__((target_clones("avx2", "default")))
#else
#define KINETRI_VECTOR_CLONES
#endif

// A finite triangle (a, b, c) translated to a, with the parts of the
// floating-point filters that all three of its edges share.
struct TranslatedTriangle {
  double bx, by, cx, cy;  // b - a, c - a
  double blift, clift;    // |b - a|^2, |c - a|^2
  double bxcy, cxby;      // the two products of cross(b - a, c - a)
};

// Bit k is set unless the floating-point filter certifies that d[k] lies
// outside the circle through a, b, c (InCircle(a, b, c, d[k]) < 0), for
// the three apexes at once in the lanes of one vector (lane 3 repeats
// lane 0).
//
// It is Shewchuk's filter of InCircle(b, c, d, a), the same four points in
// an odd order (so the opposite sign), which translates to a instead of d:
// the parts that depend on the triangle alone are computed once per
// triangle, not once per edge. Cyclic rotations of (a, b, c) leave the
// sign unchanged, so every edge of the triangle uses the same
// translation.
using Lanes = double __attribute__((vector_size(32)));
__attribute__((always_inline)) inline int InCircleFilteredNotLegal(
    const TranslatedTriangle& t, const Vec2& a, const Vec2 d[3]) {
  const Lanes dx = Lanes{d[0].x, d[1].x, d[2].x, d[0].x} - a.x;
  const Lanes dy = Lanes{d[0].y, d[1].y, d[2].y, d[0].y} - a.y;
  const Lanes dlift = dx * dx + dy * dy;
  const Lanes cxdy = t.cx * dy, dxcy = dx * t.cy;
  const Lanes dxby = dx * t.by, bxdy = t.bx * dy;
  const Lanes det = t.blift * (cxdy - dxcy) + t.clift * (dxby - bxdy) +
                    dlift * (t.bxcy - t.cxby);
  const Lanes zero = {0, 0, 0, 0};
  const Lanes acxdy = cxdy < zero ? -cxdy : cxdy;
  const Lanes adxcy = dxcy < zero ? -dxcy : dxcy;
  const Lanes adxby = dxby < zero ? -dxby : dxby;
  const Lanes abxdy = bxdy < zero ? -bxdy : bxdy;
  const Lanes permanent = (acxdy + adxcy) * t.blift +
                          (adxby + abxdy) * t.clift +
                          (std::fabs(t.bxcy) + std::fabs(t.cxby)) * dlift;
  const Lanes errbound = internal::kIccErrBoundA * permanent;
  // det > errbound: InCircle(a, b, c, d) < 0 certainly (legal).
  const auto legal = det > errbound;
  return (legal[0] ? 0 : 1) | (legal[1] ? 0 : 2) | (legal[2] ? 0 : 4);
}

// The scan, reading the apex across each edge from `across` (kAcross) or
// from the mesh (origin[Prev(twin[e])]).
template <bool kAcross>
__attribute__((always_inline)) inline void ScanBody(
    const MeshView& m, const Vec2* pos, const uint32_t* across, uint32_t lo,
    uint32_t hi, std::vector<uint32_t>* invalid,
    std::vector<uint32_t>* illegal) {
  // The loads that miss the cache are the apexes across the edges
  // (origin[Prev(twin[e])], in a neighbour that may lie far away in slot
  // order) and their positions: both are prefetched ahead, the apex ids
  // kFar triangles ahead, their positions kNear ahead (once the ids are
  // in cache). With `across` the ids are read in slot order, next to the
  // triangle's own; only the positions are prefetched.
  constexpr uint32_t kFar = 16, kNear = 8;
  auto prefetch_apexes = [&](uint32_t u) {
    if constexpr (kAcross) return;
    for (uint32_t k = 0; k < 3; ++k) {
      const uint32_t f = m.twin[3 * u + k];
      if (f < m.num_half_edges) __builtin_prefetch(&m.origin[Prev(f)]);
    }
  };
  auto prefetch_apex_positions = [&](uint32_t u) {
    for (uint32_t k = 0; k < 3; ++k) {
      if constexpr (kAcross) {
        const uint32_t d = across[3 * u + k];
        if (d < kInfiniteVertex) __builtin_prefetch(&pos[d]);
        continue;
      }
      const uint32_t f = m.twin[3 * u + k];
      if (f >= m.num_half_edges) continue;
      const uint32_t d = m.origin[Prev(f)];
      if (d < kInfiniteVertex) __builtin_prefetch(&pos[d]);
    }
  };
  for (uint32_t t = lo; t < hi; ++t) {
    if (t + kFar < hi) prefetch_apexes(t + kFar);
    if (t + kNear < hi) prefetch_apex_positions(t + kNear);
    const uint32_t v[3] = {m.origin[3 * t], m.origin[3 * t + 1],
                           m.origin[3 * t + 2]};
    if (v[0] == kNoVertex) continue;  // free slot
    if (v[0] == kInfiniteVertex || v[1] == kInfiniteVertex ||
        v[2] == kInfiniteVertex) {
      // Ghost: its hull turn decides; its edges are never illegal.
      if (!rules::TriangleOk(m, pos, t)) invalid->push_back(t);
      continue;
    }
    const Vec2 q[3] = {pos[v[0]], pos[v[1]], pos[v[2]]};
    TranslatedTriangle tt;
    tt.bx = q[1].x - q[0].x;
    tt.by = q[1].y - q[0].y;
    tt.cx = q[2].x - q[0].x;
    tt.cy = q[2].y - q[0].y;
    tt.blift = tt.bx * tt.bx + tt.by * tt.by;
    tt.clift = tt.cx * tt.cx + tt.cy * tt.cy;
    tt.bxcy = tt.bx * tt.cy;
    tt.cxby = tt.cx * tt.by;
    // Orient2d(b, c, a): a cyclic rotation, so the sign of (a, b, c), and
    // its filter translates to a as the in-circle filters below do.
    if (Orient2d(q[1], q[2], q[0]) <= 0) invalid->push_back(t);
    // The three edges are filtered together in the lanes of one vector,
    // each from both of its triangles: whether e is the canonical
    // half-edge is a coin toss, and mispredicting it costs more than a
    // second filter. The branch that remains (not certainly legal) is
    // rarely taken.
    uint32_t d[3];
    bool finite[3];
    Vec2 qd[3];
    for (uint32_t k = 0; k < 3; ++k) {
      d[k] = kAcross ? across[3 * t + k] : m.origin[Prev(m.twin[3 * t + k])];
      finite[k] = d[k] != kInfiniteVertex;
      qd[k] = pos[finite[k] ? d[k] : v[0]];
    }
    const int mask = InCircleFilteredNotLegal(tt, q[0], qd);
    if (mask != 0) {
      for (uint32_t k = 0; k < 3; ++k) {
        const uint32_t e = 3 * t + k;
        // Edge e: origin q[k], destination q[k+1], apex q[k+2] (as
        // rules::IsIllegal).
        if ((mask >> k & 1) && finite[k] && e < m.twin[e] &&
            InCircleSoS(q[k], q[(k + 1) % 3], q[(k + 2) % 3], qd[k]) > 0) {
          illegal->push_back(e);
        }
      }
    }
  }
}

}  // namespace

KINETRI_VECTOR_CLONES void ScanTriangles(const MeshView& m, const Vec2* pos,
                                         uint32_t lo, uint32_t hi,
                                         std::vector<uint32_t>* invalid,
                                         std::vector<uint32_t>* illegal) {
  ScanBody<false>(m, pos, nullptr, lo, hi, invalid, illegal);
}

KINETRI_VECTOR_CLONES void ScanTriangles(const MeshView& m, const Vec2* pos,
                                         const uint32_t* across, uint32_t lo,
                                         uint32_t hi,
                                         std::vector<uint32_t>* invalid,
                                         std::vector<uint32_t>* illegal) {
  ScanBody<true>(m, pos, across, lo, hi, invalid, illegal);
}

void FillAcross(const MeshView& m, uint32_t lo, uint32_t hi, uint32_t* across) {
  for (uint32_t e = 3 * lo; e < 3 * hi; ++e) {
    across[e] = m.origin[e] == kNoVertex ? kNoVertex : m.Across(e);
  }
}

}  // namespace kinetri::core
