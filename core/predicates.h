// Exact geometric predicates with floating-point filters, host+device.
//
//   Orient2d(a, b, c)  > 0 iff a, b, c turn counter-clockwise.
//   InCircle(a, b, c, d) > 0 iff d lies strictly inside the circle through
//                          a, b, c (which must be counter-clockwise).
//   InCircleSoS        as InCircle, with exact cocircularity broken by a
//                          symbolic perturbation (see below): never 0 for four
//                          distinct points with a, b, c counter-clockwise.
//   CompareDistance(q, a, b)  sign of |q-a|^2 - |q-b|^2.
//   CompareDistanceToRadius(q, p, r)  sign of |q-p|^2 - r^2.
//
// Each predicate first evaluates the determinant in double precision and
// returns when the result exceeds a forward error bound (Shewchuk 1997,
// "Adaptive Precision Floating-Point Arithmetic and Fast Robust Geometric
// Predicates": ccwerrboundA / iccerrboundA). Otherwise it re-evaluates the
// determinant exactly with expansions (core/expansion.h). The filter uses a
// strict comparison so that an underflowed bound can never certify a zero.
//
// Exactness domain: every coordinate is 0 or has magnitude in
// [kMinAbsCoordinate, kMaxAbsCoordinate]. Then no partial product of the exact
// evaluation underflows or overflows. Triangulation rejects other input.
//
// Symbolic perturbation: the lifted height |p|^2 of each point is perturbed by
// an infinitesimal that grows with the point's lexicographic (x, y) rank, the
// scheme CGAL's Delaunay_triangulation_2 uses. The triangulation it selects
// for cocircular points is therefore unique and identical to CGAL's, and
// Lawson flips always terminate. It depends only on coordinates, never on
// point numbering, so renumbering cannot change the mesh.
#ifndef KINETRI_CORE_PREDICATES_H_
#define KINETRI_CORE_PREDICATES_H_

#include <cmath>

#include "core/expansion.h"
#include "core/hd.h"
#include "core/vec2.h"

namespace kinetri::core {

// 2^100 and 2^-100: see "Exactness domain" above.
inline constexpr double kMaxAbsCoordinate = 1.2676506002282294e30;
inline constexpr double kMinAbsCoordinate = 7.888609052210118e-31;

KINETRI_HD inline bool InExactDomain(double v) {
  const double a = std::fabs(v);
  return a == 0.0 || (a >= kMinAbsCoordinate && a <= kMaxAbsCoordinate);
}

namespace internal {
inline constexpr double kEps = 1.1102230246251565e-16;  // 2^-53
inline constexpr double kCcwErrBoundA = (3.0 + 16.0 * kEps) * kEps;
inline constexpr double kIccErrBoundA = (10.0 + 96.0 * kEps) * kEps;
inline constexpr double kDistErrBound = 16.0 * kEps;

KINETRI_HD inline int SignOf(double v) { return (v > 0.0) - (v < 0.0); }

KINETRI_HD inline int Orient2dExactBody(const Vec2& a, const Vec2& b,
                                        const Vec2& c) {
  using namespace exact;
  const Expansion<2> acx = Diff(a.x, c.x), acy = Diff(a.y, c.y);
  const Expansion<2> bcx = Diff(b.x, c.x), bcy = Diff(b.y, c.y);
  Expansion<8> left, right;
  Multiply(acx, bcy, left);
  Multiply(acy, bcx, right);
  Negate(right);
  Expansion<16> det;
  Sum(left, right, det);
  return Sign(det);
}

KINETRI_HD inline int InCircleExactBody(const Vec2& a, const Vec2& b,
                                        const Vec2& c, const Vec2& d) {
  using namespace exact;
  const Expansion<2> adx = Diff(a.x, d.x), ady = Diff(a.y, d.y);
  const Expansion<2> bdx = Diff(b.x, d.x), bdy = Diff(b.y, d.y);
  const Expansion<2> cdx = Diff(c.x, d.x), cdy = Diff(c.y, d.y);
  // lift(p) * cross(q, r) for the three cyclic rotations.
  auto term = [](const Expansion<2>& px, const Expansion<2>& py,
                 const Expansion<2>& qx, const Expansion<2>& qy,
                 const Expansion<2>& rx, const Expansion<2>& ry,
                 Expansion<512>& out) {
    Expansion<8> xx, yy, q1, q2;
    Multiply(px, px, xx);
    Multiply(py, py, yy);
    Expansion<16> lift;
    Sum(xx, yy, lift);
    Multiply(qx, ry, q1);
    Multiply(qy, rx, q2);
    Negate(q2);
    Expansion<16> cross;
    Sum(q1, q2, cross);
    Multiply(lift, cross, out);
  };
  Expansion<512> ta, tb, tc;
  term(adx, ady, bdx, bdy, cdx, cdy, ta);
  term(bdx, bdy, cdx, cdy, adx, ady, tb);
  term(cdx, cdy, adx, ady, bdx, bdy, tc);
  Expansion<1024> ab;
  Sum(ta, tb, ab);
  Expansion<1536> det;
  Sum(ab, tc, det);
  return Sign(det);
}

KINETRI_HD inline int CompareDistanceExactBody(const Vec2& q, const Vec2& a,
                                               const Vec2& b) {
  using namespace exact;
  const Expansion<2> ax = Diff(q.x, a.x), ay = Diff(q.y, a.y);
  const Expansion<2> bx = Diff(q.x, b.x), by = Diff(q.y, b.y);
  Expansion<8> axx, ayy, bxx, byy;
  Multiply(ax, ax, axx);
  Multiply(ay, ay, ayy);
  Multiply(bx, bx, bxx);
  Multiply(by, by, byy);
  Expansion<16> da, db;
  Sum(axx, ayy, da);
  Sum(bxx, byy, db);
  Negate(db);
  Expansion<32> det;
  Sum(da, db, det);
  return Sign(det);
}

KINETRI_HD inline int CompareDistanceToRadiusExactBody(const Vec2& q,
                                                       const Vec2& p,
                                                       double r) {
  using namespace exact;
  const Expansion<2> dx = Diff(q.x, p.x), dy = Diff(q.y, p.y);
  Expansion<8> xx, yy;
  Multiply(dx, dx, xx);
  Multiply(dy, dy, yy);
  Expansion<16> d;
  Sum(xx, yy, d);
  Expansion<2> rr;
  double hi, lo;
  TwoProduct(r, r, hi, lo);
  rr.n = 0;
  if (lo != 0.0) rr.c[rr.n++] = -lo;
  rr.c[rr.n++] = -hi;
  Expansion<18> det;
  Sum(d, rr, det);
  return Sign(det);
}

// The exact fallbacks as called: out of line (KINETRI_COLD). The CUDA
// build's device code (KINETRI_EXACT_EXTERN) calls them as true functions
// of core/device/exact_extern.cu, relocatable device code compiled at NVVM
// -O1 (docs/DEVICE.md: at -O3 CUDA 13.0 got them wrong on an H200).
#if defined(__CUDA_ARCH__) && defined(KINETRI_EXACT_EXTERN)
__device__ int Orient2dExactExtern(const Vec2& a, const Vec2& b, const Vec2& c);
__device__ int InCircleExactExtern(const Vec2& a, const Vec2& b, const Vec2& c,
                                   const Vec2& d);
__device__ int CompareDistanceExactExtern(const Vec2& q, const Vec2& a,
                                          const Vec2& b);
__device__ int CompareDistanceToRadiusExactExtern(const Vec2& q, const Vec2& p,
                                                  double r);
KINETRI_HD inline int Orient2dExact(const Vec2& a, const Vec2& b,
                                    const Vec2& c) {
  return Orient2dExactExtern(a, b, c);
}
KINETRI_HD inline int InCircleExact(const Vec2& a, const Vec2& b, const Vec2& c,
                                    const Vec2& d) {
  return InCircleExactExtern(a, b, c, d);
}
KINETRI_HD inline int CompareDistanceExact(const Vec2& q, const Vec2& a,
                                           const Vec2& b) {
  return CompareDistanceExactExtern(q, a, b);
}
KINETRI_HD inline int CompareDistanceToRadiusExact(const Vec2& q, const Vec2& p,
                                                   double r) {
  return CompareDistanceToRadiusExactExtern(q, p, r);
}
#else
KINETRI_HD KINETRI_COLD inline int Orient2dExact(const Vec2& a, const Vec2& b,
                                                 const Vec2& c) {
  return Orient2dExactBody(a, b, c);
}
KINETRI_HD KINETRI_COLD inline int InCircleExact(const Vec2& a, const Vec2& b,
                                                 const Vec2& c, const Vec2& d) {
  return InCircleExactBody(a, b, c, d);
}
KINETRI_HD KINETRI_COLD inline int CompareDistanceExact(const Vec2& q,
                                                        const Vec2& a,
                                                        const Vec2& b) {
  return CompareDistanceExactBody(q, a, b);
}
KINETRI_HD KINETRI_COLD inline int CompareDistanceToRadiusExact(const Vec2& q,
                                                                const Vec2& p,
                                                                double r) {
  return CompareDistanceToRadiusExactBody(q, p, r);
}
#endif
}  // namespace internal

KINETRI_HD inline int Orient2d(const Vec2& a, const Vec2& b, const Vec2& c) {
  const double detleft = (a.x - c.x) * (b.y - c.y);
  const double detright = (a.y - c.y) * (b.x - c.x);
  const double det = detleft - detright;
  const double detsum = std::fabs(detleft) + std::fabs(detright);
  const double errbound = internal::kCcwErrBoundA * detsum;
  if (det > errbound || -det > errbound) return internal::SignOf(det);
  return internal::Orient2dExact(a, b, c);
}

KINETRI_HD inline int InCircle(const Vec2& a, const Vec2& b, const Vec2& c,
                               const Vec2& d) {
  const double adx = a.x - d.x, ady = a.y - d.y;
  const double bdx = b.x - d.x, bdy = b.y - d.y;
  const double cdx = c.x - d.x, cdy = c.y - d.y;
  const double bdxcdy = bdx * cdy, cdxbdy = cdx * bdy;
  const double alift = adx * adx + ady * ady;
  const double cdxady = cdx * ady, adxcdy = adx * cdy;
  const double blift = bdx * bdx + bdy * bdy;
  const double adxbdy = adx * bdy, bdxady = bdx * ady;
  const double clift = cdx * cdx + cdy * cdy;
  const double det = alift * (bdxcdy - cdxbdy) + blift * (cdxady - adxcdy) +
                     clift * (adxbdy - bdxady);
  const double permanent = (std::fabs(bdxcdy) + std::fabs(cdxbdy)) * alift +
                           (std::fabs(cdxady) + std::fabs(adxcdy)) * blift +
                           (std::fabs(adxbdy) + std::fabs(bdxady)) * clift;
  const double errbound = internal::kIccErrBoundA * permanent;
  if (det > errbound || -det > errbound) return internal::SignOf(det);
  return internal::InCircleExact(a, b, c, d);
}

// Requires Orient2d(a, b, c) > 0 and four pairwise distinct points.
KINETRI_HD inline int InCircleSoS(const Vec2& a, const Vec2& b, const Vec2& c,
                                  const Vec2& d) {
  const int s = InCircle(a, b, c, d);
  if (s != 0) return s;
  // The four points are cocircular. Sort them lexicographically; the
  // perturbation of the largest one dominates. If that point is d, d is
  // pushed outside; otherwise the sign is the orientation of the triangle in
  // which d replaces that point. If that orientation is 0, the next largest
  // decides (two rounds always suffice for distinct cocircular points).
  const Vec2* pts[4] = {&a, &b, &c, &d};
  for (int i = 1; i < 4; ++i) {  // insertion sort, 4 elements
    const Vec2* key = pts[i];
    int j = i - 1;
    while (j >= 0 && LexLess(*key, *pts[j])) {
      pts[j + 1] = pts[j];
      --j;
    }
    pts[j + 1] = key;
  }
  for (int i = 3; i > 1; --i) {
    const Vec2* p = pts[i];
    if (p == &d) return -1;
    int o = 0;
    if (p == &c) o = Orient2d(a, b, d);
    if (p == &b) o = Orient2d(a, d, c);
    if (p == &a) o = Orient2d(d, b, c);
    if (o != 0) return o;
  }
  return -1;  // unreachable for valid input
}

KINETRI_HD inline int CompareDistance(const Vec2& q, const Vec2& a,
                                      const Vec2& b) {
  const double ax = q.x - a.x, ay = q.y - a.y;
  const double bx = q.x - b.x, by = q.y - b.y;
  const double da = ax * ax + ay * ay;
  const double db = bx * bx + by * by;
  const double diff = da - db;
  const double errbound = internal::kDistErrBound * (da + db);
  if (diff > errbound || -diff > errbound) return internal::SignOf(diff);
  return internal::CompareDistanceExact(q, a, b);
}

KINETRI_HD inline int CompareDistanceToRadius(const Vec2& q, const Vec2& p,
                                              double r) {
  const double dx = q.x - p.x, dy = q.y - p.y;
  const double d = dx * dx + dy * dy;
  const double rr = r * r;
  const double diff = d - rr;
  const double errbound = internal::kDistErrBound * (d + rr);
  if (diff > errbound || -diff > errbound) return internal::SignOf(diff);
  return internal::CompareDistanceToRadiusExact(q, p, r);
}

// Total "closer to q" order on distinct positions: exact squared distance,
// then larger x, then larger y. It is the distance order for q moved by an
// infinitesimal (+eps, +eps^2), so it has no ties between distinct sites and
// Delaunay greedy routing stays valid under it (queries rely on this).
// Returns < 0 if a precedes b.
KINETRI_HD inline int CompareCloser(const Vec2& q, const Vec2& a,
                                    const Vec2& b) {
  const int d = CompareDistance(q, a, b);
  if (d != 0) return d;
  if (a.x != b.x) return a.x > b.x ? -1 : 1;
  if (a.y != b.y) return a.y > b.y ? -1 : 1;
  return 0;
}

}  // namespace kinetri::core

#endif  // KINETRI_CORE_PREDICATES_H_
