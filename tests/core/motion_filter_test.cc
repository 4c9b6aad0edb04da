// Vertex tolerances (core/motion_filter.h): each certificate holds under
// every motion it allows (checked with the exact predicates), is not
// needlessly small (a motion a little past it breaks the answer), and a
// step through the filter ends at CGAL's triangulation.
#include "core/motion_filter.h"

#include <gtest/gtest.h>

#include <cmath>
#include <random>
#include <utility>
#include <vector>

#include "core/predicates.h"
#include "core/triangulation.h"
#include "tests/core/test_util.h"

namespace kinetri::core {
namespace {

using testing::CgalDelaunayEdges;
using testing::EdgesAsPositions;

Vec2 Add(Vec2 a, Vec2 d, double k) { return {a.x + k * d.x, a.y + k * d.y}; }

Vec2 Unit(Vec2 d) {
  const double l = std::hypot(d.x, d.y);
  return {d.x / l, d.y / l};
}

Vec2 RandomWithin(std::mt19937_64& rng, double r) {
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  for (;;) {
    const Vec2 d{u(rng), u(rng)};
    if (d.x * d.x + d.y * d.y <= 1.0) return {r * d.x, r * d.y};
  }
}

TEST(MotionFilter, OrientToleranceIsSoundAndTight) {
  std::mt19937_64 rng(7);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  int tested = 0;
  for (int i = 0; i < 2000; ++i) {
    Vec2 a{u(rng), u(rng)}, b{u(rng), u(rng)}, c{u(rng), u(rng)};
    // Every fourth triangle is a sliver: c close to segment ab.
    if (i % 4 == 0)
      c = Add(Add(a, {b.x - a.x, b.y - a.y}, u(rng)), {1, 1}, 1e-6 * u(rng));
    if (Orient2d(a, b, c) < 0) std::swap(a, b);
    const double h = OrientTolerance(a, b, c);
    if (Orient2d(a, b, c) <= 0) {
      EXPECT_EQ(h, 0.0);
      continue;
    }
    ASSERT_GT(h, 0.0);
    ++tested;
    for (int k = 0; k < 20; ++k) {
      EXPECT_GT(Orient2d(Add(a, RandomWithin(rng, h), 1.0),
                         Add(b, RandomWithin(rng, h), 1.0),
                         Add(c, RandomWithin(rng, h), 1.0)),
                0);
    }
    // Squeeze the vertex opposite the longest side onto it from both
    // sides: within h it stays positive, a little past it it flips.
    Vec2 p[3] = {a, b, c};
    int lo = 0;
    double longest = -1.0;
    for (int j = 0; j < 3; ++j) {
      const Vec2 s = p[j], t = p[(j + 1) % 3];
      const double l = std::hypot(t.x - s.x, t.y - s.y);
      if (l > longest) longest = l, lo = j;
    }
    const Vec2 s = p[lo], t = p[(lo + 1) % 3], o = p[(lo + 2) % 3];
    const Vec2 n = Unit({s.y - t.y, t.x - s.x});  // from st towards o
    auto squeezed = [&](double k) {
      Vec2 q[3];
      q[lo] = Add(s, n, k);
      q[(lo + 1) % 3] = Add(t, n, k);
      q[(lo + 2) % 3] = Add(o, n, -k);
      return Orient2d(q[0], q[1], q[2]);
    };
    EXPECT_GT(squeezed(0.999 * h), 0);
    EXPECT_LT(squeezed(1.01 * h), 0);
  }
  EXPECT_GT(tested, 1500);
  EXPECT_EQ(OrientTolerance({0, 0}, {1, 1}, {2, 2}), 0.0);
  EXPECT_EQ(OrientTolerance({0, 0}, {0, 1}, {1, 0}), 0.0);  // clockwise
}

TEST(MotionFilter, EdgeToleranceIsSoundAndNotTooSmall) {
  // The interior edges of a Delaunay triangulation, uniform and clustered.
  int tested = 0, broken_past = 0, squeezed = 0;
  std::mt19937_64 rng(11);
  for (const auto& pts :
       {testing::UniformPoints(300, 12), testing::ClusteredPoints(300, 13)}) {
    auto t = Triangulation::Create(pts, {});
    ASSERT_TRUE(t.ok());
    const TriangulationView v = t->view();
    const MeshView& m = v.mesh;
    for (uint32_t e = 0; e < m.num_half_edges; ++e) {
      const uint32_t a = m.origin[e], b = m.Dest(e), r = m.Apex(e),
                     s = m.Across(e);
      if (a >= kInfiniteVertex || b >= kInfiniteVertex ||
          r >= kInfiniteVertex || s >= kInfiniteVertex || m.twin[e] < e) {
        continue;
      }
      const Vec2 p = v.pos[a], q = v.pos[b], pr = v.pos[r], ps = v.pos[s];
      const double h = EdgeTolerance(p, q, pr, ps);
      ASSERT_LT(InCircle(p, q, pr, ps), 0);  // a generic mesh: strict
      ASSERT_GT(h, 0.0);
      // What the filter promises: while both triangles stay positive.
      const double k =
          std::min({h, OrientTolerance(p, q, pr), OrientTolerance(q, p, ps)});
      ++tested;
      for (int i = 0; i < 20; ++i) {
        const Vec2 p2 = Add(p, RandomWithin(rng, k), 1.0),
                   q2 = Add(q, RandomWithin(rng, k), 1.0),
                   r2 = Add(pr, RandomWithin(rng, k), 1.0),
                   s2 = Add(ps, RandomWithin(rng, k), 1.0);
        EXPECT_LT(InCircle(p2, q2, r2, s2), 0);
      }
      // Radially about the centre of the annulus: p and q out, r and s
      // in. Within h the edge stays legal; past about twice h (the bound
      // gives up at most half the annulus) they have crossed.
      const double ux = q.x - p.x, uy = q.y - p.y, vx = ps.x - pr.x,
                   vy = ps.y - pr.y;
      const double c1 = 0.5 * (ux * ux + uy * uy);
      const double c2 =
          vx * (0.5 * (pr.x + ps.x) - p.x) + vy * (0.5 * (pr.y + ps.y) - p.y);
      const double det = ux * vy - uy * vx;
      const Vec2 o{p.x + (c1 * vy - uy * c2) / det,
                   p.y + (ux * c2 - c1 * vx) / det};
      auto radial = [&](double d) {
        return InCircle(Add(p, Unit({p.x - o.x, p.y - o.y}), d),
                        Add(q, Unit({q.x - o.x, q.y - o.y}), d),
                        Add(pr, Unit({pr.x - o.x, pr.y - o.y}), -d),
                        Add(ps, Unit({ps.x - o.x, ps.y - o.y}), -d));
      };
      if (h < OrientTolerance(p, q, pr) && h < OrientTolerance(q, p, ps)) {
        ++squeezed;
        EXPECT_LT(radial(0.999 * h), 0);
        if (radial(2.05 * h) > 0) ++broken_past;
      }
    }
  }
  EXPECT_GT(tested, 1000);
  // Past 2h the radial motion breaks nearly every edge (it need not where
  // the quad stops being convex first).
  EXPECT_GT(broken_past, 0.8 * squeezed);
  // Exactly cocircular: no margin.
  EXPECT_EQ(EdgeTolerance({0, 0}, {1, 1}, {1, 0}, {0, 1}), 0.0);
}

// A sequence through the filter with the default policy: tiny Brownian
// motion (about 1e-5 of the local spacing) is filtered, and every step
// ends at CGAL's mesh.
TEST(MotionFilter, TinyMotionLooksAtFewVerticesAndStaysExact) {
  const size_t n = 20000;
  // Clustered points are about 15x closer than uniform ones.
  const double uniform_sigma = 1e-5 / std::sqrt(double(n));
  for (const auto& [pts, sigma] :
       {std::pair{testing::UniformPoints(n, 21), uniform_sigma},
        std::pair{testing::ClusteredPoints(n, 22), uniform_sigma / 15}}) {
    auto t = Triangulation::Create(pts, {});
    ASSERT_TRUE(t.ok());
    std::mt19937_64 rng(23);
    uint64_t quiet = 0;
    // Step 4 moves 100x more: too many loud vertices, the filter backs off.
    for (int s = 0; s < 10; ++s) {
      auto r = t->ApplyDisplacements(
          testing::Brownian(n, (s == 4 ? 100 : 1) * sigma, rng));
      ASSERT_TRUE(r.ok()) << r.status();
      quiet += r->quiet_points;
      ASSERT_EQ(EdgesAsPositions(*t), CgalDelaunayEdges(t->Positions()))
          << "step " << s;
    }
    EXPECT_GT(quiet, 3.5 * n);
  }
}

// Forced on, over many steps of motion comparable to the tolerances: most
// vertices stay quiet for several steps while their neighbours are reset
// around them, which is where a tolerance that forgets how far a quiet
// vertex has already gone would certify a broken mesh.
TEST(MotionFilter, QuietVerticesAccumulateMotionSafely) {
  TriangulationOptions o;
  o.region.filter_estimate = 1.0;
  o.region.filter_fraction = 1.0;
  o.region.sparse_fraction = 1.0;
  const size_t n = 4000;
  for (double sigma : {3e-4, 1e-3}) {
    auto t = Triangulation::Create(testing::UniformPoints(n, 41), o);
    ASSERT_TRUE(t.ok());
    std::mt19937_64 rng(42);
    uint64_t quiet = 0;
    for (int s = 0; s < 60; ++s) {
      auto r = t->ApplyDisplacements(
          testing::Brownian(n, sigma / std::sqrt(double(n)), rng));
      ASSERT_TRUE(r.ok()) << r.status();
      quiet += r->quiet_points;
      ASSERT_EQ(EdgesAsPositions(*t), CgalDelaunayEdges(t->Positions()))
          << "sigma " << sigma << " step " << s;
    }
    EXPECT_GT(quiet, 60 * n / 2);
  }
}

// The hull moves (the whole set grows and turns a little each step) and a
// few points cross it, with the filter forced on.
TEST(MotionFilter, HullMotionThroughTheFilter) {
  TriangulationOptions o;
  o.region.filter_estimate = 1.0;
  o.region.filter_fraction = 1.0;
  const size_t n = 3000;
  auto t = Triangulation::Create(testing::UniformPoints(n, 31), o);
  ASSERT_TRUE(t.ok());
  for (int s = 0; s < 10; ++s) {
    const auto cur = t->Positions();
    std::vector<Vec2> d(n);
    for (size_t i = 0; i < n; ++i) {
      const double x = cur[i].x - 0.5, y = cur[i].y - 0.5;
      d[i] = {1e-6 * x - 1e-6 * y, 1e-6 * y + 1e-6 * x};
      if (i % 500 == 0) d[i] = {2.0 * x * (s % 2 ? -0.4 : 1.0), 0.0};
    }
    auto r = t->ApplyDisplacements(DisplacementBatch::Dense(std::move(d)));
    ASSERT_TRUE(r.ok()) << r.status();
    ASSERT_EQ(EdgesAsPositions(*t), CgalDelaunayEdges(t->Positions()))
        << "step " << s;
  }
}

// A cocircular lattice has no margin anywhere: every moved vertex is loud.
TEST(MotionFilter, CocircularLatticeIsAlwaysLooked) {
  TriangulationOptions o;
  o.region.filter_estimate = 1.0;
  o.region.filter_fraction = 1.0;
  const auto pts = testing::Lattice(30);
  auto t = Triangulation::Create(pts, o);
  ASSERT_TRUE(t.ok());
  std::vector<uint32_t> ids = {17, 301, 450, 899};
  std::vector<Vec2> d(ids.size(), Vec2{1e-9, 0.0});
  auto r = t->ApplyDisplacements(DisplacementBatch::Sparse(ids, d));
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_EQ(r->quiet_points, 0u);
  EXPECT_EQ(EdgesAsPositions(*t), CgalDelaunayEdges(t->Positions()));
}

}  // namespace
}  // namespace kinetri::core
