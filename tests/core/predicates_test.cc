// Exact predicates vs CGAL's exact kernel on random and degenerate inputs.
#include "core/predicates.h"

#include <CGAL/Exact_predicates_inexact_constructions_kernel.h>
#include <gtest/gtest.h>

#include <cmath>
#include <random>

namespace kinetri::core {
namespace {

using Kernel = CGAL::Exact_predicates_inexact_constructions_kernel;
using P = Kernel::Point_2;

P ToCgal(const Vec2& v) { return P(v.x, v.y); }

int CgalOrient(const Vec2& a, const Vec2& b, const Vec2& c) {
  return static_cast<int>(CGAL::orientation(ToCgal(a), ToCgal(b), ToCgal(c)));
}
int CgalInCircle(const Vec2& a, const Vec2& b, const Vec2& c, const Vec2& d) {
  // side_of_oriented_circle > 0: d inside for counter-clockwise a, b, c.
  return static_cast<int>(CGAL::side_of_oriented_circle(ToCgal(a), ToCgal(b),
                                                        ToCgal(c), ToCgal(d)));
}
int CgalCompareDistance(const Vec2& q, const Vec2& a, const Vec2& b) {
  return static_cast<int>(
      CGAL::compare_distance_to_point(ToCgal(q), ToCgal(a), ToCgal(b)));
}

// Generators of increasingly nasty inputs.
class Gen {
 public:
  explicit Gen(uint64_t seed) : rng_(seed) {}
  double Uniform(double lo, double hi) {
    return std::uniform_real_distribution<double>(lo, hi)(rng_);
  }
  int Int(int lo, int hi) {
    return std::uniform_int_distribution<int>(lo, hi)(rng_);
  }
  Vec2 Point(double scale, double offset) {
    return {offset + scale * Uniform(-1, 1), offset + scale * Uniform(-1, 1)};
  }
  // Moves v by a few ulps.
  Vec2 Nudge(Vec2 v) {
    for (int k = Int(0, 3); k > 0; --k)
      v.x = std::nextafter(v.x, Int(0, 1) ? 1e300 : -1e300);
    for (int k = Int(0, 3); k > 0; --k)
      v.y = std::nextafter(v.y, Int(0, 1) ? 1e300 : -1e300);
    return v;
  }
  std::mt19937_64& rng() { return rng_; }

 private:
  std::mt19937_64 rng_;
};

struct Scale {
  double scale, offset;
};
const Scale kScales[] = {{1.0, 0.0},  {1e-12, 0.0}, {1e12, 0.0},  {1.0, 1e12},
                         {1e-3, 1e6}, {1e-9, 1.0},  {1e20, -1e25}};

TEST(Orient2d, MatchesCgalOnRandomAndNearDegenerate) {
  Gen g(1);
  for (const Scale& s : kScales) {
    for (int i = 0; i < 20000; ++i) {
      Vec2 a = g.Point(s.scale, s.offset), b = g.Point(s.scale, s.offset);
      Vec2 c;
      switch (i % 3) {
        case 0:
          c = g.Point(s.scale, s.offset);
          break;
        case 1: {  // on the line ab, rounded, then nudged
          const double t = g.Uniform(-2, 2);
          c = g.Nudge({a.x + t * (b.x - a.x), a.y + t * (b.y - a.y)});
          break;
        }
        default:
          c = g.Nudge(a);
      }
      ASSERT_EQ(Orient2d(a, b, c), CgalOrient(a, b, c))
          << "scale " << s.scale << " offset " << s.offset << " i " << i;
    }
  }
}

TEST(Orient2d, ExactlyCollinearIsZero) {
  Gen g(2);
  for (int i = 0; i < 10000; ++i) {
    const int t = g.Int(-1000, 1000), u = g.Int(-1000, 1000);
    const double k = std::ldexp(1.0, g.Int(-60, 60));
    Vec2 a{k * 1, k * 2}, b{k * (1 + 3.0 * t), k * (2 + 5.0 * t)},
        c{k * (1 + 3.0 * u), k * (2 + 5.0 * u)};
    EXPECT_EQ(Orient2d(a, b, c), 0);
    EXPECT_EQ(CgalOrient(a, b, c), 0);
  }
}

TEST(InCircle, MatchesCgalOnRandomAndNearDegenerate) {
  Gen g(3);
  for (const Scale& s : kScales) {
    for (int i = 0; i < 20000; ++i) {
      Vec2 a = g.Point(s.scale, s.offset), b = g.Point(s.scale, s.offset),
           c = g.Point(s.scale, s.offset);
      if (CgalOrient(a, b, c) == 0) continue;
      if (CgalOrient(a, b, c) < 0) std::swap(a, b);
      Vec2 d;
      if (i % 2 == 0) {
        d = g.Point(s.scale, s.offset);
      } else {  // close to the circle: reflect a across the centre, nudge
        const double ax = b.x - a.x, ay = b.y - a.y, bx = c.x - a.x,
                     by = c.y - a.y;
        const double den = 2 * (ax * by - ay * bx);
        const double ux =
            (by * (ax * ax + ay * ay) - ay * (bx * bx + by * by)) / den;
        const double uy =
            (ax * (bx * bx + by * by) - bx * (ax * ax + ay * ay)) / den;
        d = g.Nudge({a.x + 2 * ux, a.y + 2 * uy});
      }
      ASSERT_EQ(InCircle(a, b, c, d), CgalInCircle(a, b, c, d))
          << "scale " << s.scale << " offset " << s.offset << " i " << i;
    }
  }
}

TEST(InCircle, ExactlyCocircularIsZeroAndSoSIsConsistent) {
  // Integer points on circles x^2 + y^2 = 25 and 65 (many lattice points).
  const std::vector<Vec2> circle25 = {{5, 0},   {4, 3},  {3, 4},  {0, 5},
                                      {-3, 4},  {-4, 3}, {-5, 0}, {-4, -3},
                                      {-3, -4}, {0, -5}, {3, -4}, {4, -3}};
  Gen g(4);
  for (int i = 0; i < 5000; ++i) {
    std::vector<Vec2> p = circle25;
    std::shuffle(p.begin(), p.end(), g.rng());
    const double k = std::ldexp(1.0, g.Int(-40, 40));
    const Vec2 off{g.Int(-100, 100) * k, g.Int(-100, 100) * k};
    for (Vec2& v : p) v = {off.x + k * v.x, off.y + k * v.y};
    Vec2 a = p[0], b = p[1], c = p[2], d = p[3];
    if (Orient2d(a, b, c) < 0) std::swap(a, b);
    ASSERT_EQ(InCircle(a, b, c, d), 0);
    ASSERT_EQ(CgalInCircle(a, b, c, d), 0);
    const int s = InCircleSoS(a, b, c, d);
    ASSERT_NE(s, 0);
    // Consistency: the same quadrilateral seen from the other diagonal side
    // gives the opposite decision for flipping. With (a, b, c) ccw and d
    // across edge a-b, the edge a-b is illegal iff s > 0 and then the
    // flipped edge c-d must be legal: InCircleSoS(c, d, b, a)... checked via
    // the symmetric test on the other triangle of edge a-b.
    if (Orient2d(b, a, d) > 0) {
      ASSERT_EQ(InCircleSoS(b, a, d, c), s) << "SoS not symmetric";
      // Exactly one diagonal of a convex cocircular quad is legal.
      if (Orient2d(d, c, a) > 0 && Orient2d(c, d, b) > 0) {
        ASSERT_EQ(InCircleSoS(d, c, a, b), -s) << "both or no diagonal legal";
      }
    }
  }
}

TEST(CompareDistance, MatchesCgal) {
  Gen g(5);
  for (const Scale& s : kScales) {
    for (int i = 0; i < 20000; ++i) {
      Vec2 q = g.Point(s.scale, s.offset), a = g.Point(s.scale, s.offset);
      Vec2 b;
      if (i % 2 == 0) {
        b = g.Point(s.scale, s.offset);
      } else {  // mirror of a through q's axis: exactly or nearly equidistant
        b = g.Nudge({2 * q.x - a.x, 2 * q.y - a.y});
      }
      ASSERT_EQ(CompareDistance(q, a, b), CgalCompareDistance(q, a, b));
    }
  }
}

TEST(CompareDistanceToRadius, MatchesExactRational) {
  Gen g(6);
  for (int i = 0; i < 20000; ++i) {
    // Integer coordinates and radius so the exact answer is computable in
    // 64-bit integers.
    const Vec2 q{double(g.Int(-1000, 1000)), double(g.Int(-1000, 1000))};
    const Vec2 p{double(g.Int(-1000, 1000)), double(g.Int(-1000, 1000))};
    const int64_t dx = int64_t(q.x - p.x), dy = int64_t(q.y - p.y);
    const int64_t d2 = dx * dx + dy * dy;
    const int64_t r = (i % 2) ? int64_t(std::sqrt(double(d2))) + g.Int(-1, 1)
                              : g.Int(0, 3000);
    const int expect = (d2 > r * r) - (d2 < r * r);
    ASSERT_EQ(CompareDistanceToRadius(q, p, double(r)), expect);
    // Scaled by a power of two the answer is the same.
    const double k = std::ldexp(1.0, g.Int(-90, 90));
    ASSERT_EQ(CompareDistanceToRadius({q.x * k, q.y * k}, {p.x * k, p.y * k},
                                      double(r) * k),
              expect);
  }
}

TEST(CompareCloser, IsATotalOrderOnDistinctPoints) {
  const Vec2 q{0, 0};
  // Four points at the same distance: order by larger x, then larger y.
  const Vec2 e{1, 0}, n{0, 1}, w{-1, 0}, s{0, -1};
  EXPECT_LT(CompareCloser(q, e, n), 0);
  EXPECT_LT(CompareCloser(q, n, s), 0);
  EXPECT_LT(CompareCloser(q, s, w), 0);
  EXPECT_GT(CompareCloser(q, w, e), 0);
  EXPECT_EQ(CompareCloser(q, e, e), 0);
}

}  // namespace
}  // namespace kinetri::core
