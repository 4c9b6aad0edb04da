// The parallel strip build against the serial CGAL build: the same
// triangles (equal slot for slot in the canonical layout) for any number of
// strips, on random, clustered and degenerate inputs.
#include "core/strip_builder.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <numeric>
#include <random>
#include <vector>

#include "core/cgal_builder.h"
#include "core/mesh.h"
#include "core/spatial_order.h"
#include "tests/core/test_util.h"

namespace kinetri::core {
namespace {

// The points numbered along the Hilbert curve, as a triangulation numbers
// its sites (the builders insert them in that order).
std::vector<Vec2> SpatiallyOrdered(const std::vector<Vec2>& raw) {
  std::vector<Vec2> pts;
  for (uint32_t i : HilbertOrder(raw)) pts.push_back(raw[i]);
  return pts;
}

// Site ids with one per distinct position (the first of each).
std::vector<uint32_t> DistinctSites(const std::vector<Vec2>& pts) {
  std::vector<uint32_t> ids(pts.size());
  std::iota(ids.begin(), ids.end(), 0u);
  std::stable_sort(ids.begin(), ids.end(), [&](uint32_t a, uint32_t b) {
    return LexLess(pts[a], pts[b]);
  });
  std::vector<uint32_t> sites;
  for (size_t i = 0; i < ids.size(); ++i) {
    if (i == 0 || pts[ids[i]] != pts[ids[i - 1]]) sites.push_back(ids[i]);
  }
  std::sort(sites.begin(), sites.end());
  return sites;
}

// Builds serially and in `strips` strips: the meshes must be equal.
StripBuildStats ExpectSameAsSerial(const std::vector<Vec2>& pts,
                                   const std::vector<uint32_t>& sites,
                                   uint32_t strips) {
  Mesh serial = BuildDelaunayWithCgal(pts, sites);
  StripBuildStats stats;
  bool cancelled = false;
  Mesh striped =
      BuildDelaunayInStrips(pts, sites, strips, nullptr, &cancelled, &stats);
  EXPECT_FALSE(cancelled);
  EXPECT_EQ(serial.empty(), striped.empty());
  if (serial.empty() || striped.empty()) return stats;
  // Both in the canonical layout already.
  EXPECT_EQ(serial.num_triangles(), striped.num_triangles()) << strips;
  EXPECT_TRUE(serial.origin() == striped.origin()) << strips << " strips";
  EXPECT_TRUE(serial.twin() == striped.twin()) << strips << " strips";
  EXPECT_TRUE(serial.vertex_edge() == striped.vertex_edge());
  return stats;
}

TEST(StripBuilder, UniformPointsAnyStripCount) {
  const auto pts = SpatiallyOrdered(testing::UniformPoints(20000, 7));
  const auto sites = DistinctSites(pts);
  for (uint32_t strips : {2u, 3u, 5u, 8u, 13u}) {
    const StripBuildStats s = ExpectSameAsSerial(pts, sites, strips);
    EXPECT_EQ(s.strips, strips);
    EXPECT_FALSE(s.serial_fallback);
    EXPECT_GT(s.seam_triangles, 0u);
    EXPECT_GT(s.seam_flips, 0u);  // the stitches are not Delaunay by luck
  }
}

TEST(StripBuilder, ClusteredPoints) {
  const auto pts = SpatiallyOrdered(testing::ClusteredPoints(30000, 11));
  const auto sites = DistinctSites(pts);
  for (uint32_t strips : {2u, 4u, 7u}) {
    EXPECT_FALSE(ExpectSameAsSerial(pts, sites, strips).serial_fallback);
  }
}

// An integer lattice: every strip boundary runs through columns of equal x
// (split by y), hull edges are collinear chains, and nearly every quad is
// cocircular, decided by the symbolic perturbation.
TEST(StripBuilder, LatticeCocircularAndCollinear) {
  for (int side : {4, 9, 40, 101}) {
    const auto pts = SpatiallyOrdered(testing::Lattice(side));
    const auto sites = DistinctSites(pts);
    for (uint32_t strips : {2u, 3u, 6u}) {
      const StripBuildStats s = ExpectSameAsSerial(pts, sites, strips);
      if (side >= 40) {
        EXPECT_FALSE(s.serial_fallback) << side;
      }
    }
  }
}

// Points on one circle (all cocircular) and on a few vertical lines.
TEST(StripBuilder, CircleAndColumns) {
  std::vector<Vec2> circle;
  for (int i = 0; i < 720; ++i) {
    // Exactly representable points of the circle of radius 5 (3-4-5 family
    // rotated by quarter turns) plus a rational parametrisation.
    const double t = (i - 360) / 97.0;
    circle.push_back({5 * (1 - t * t) / (1 + t * t), 5 * 2 * t / (1 + t * t)});
  }
  circle.push_back({0, 0});
  auto pts = SpatiallyOrdered(circle);
  ExpectSameAsSerial(pts, DistinctSites(pts), 4);

  std::vector<Vec2> columns;
  std::mt19937_64 rng(5);
  std::uniform_real_distribution<double> y(0.0, 1.0);
  for (int c = 0; c < 5; ++c) {
    for (int i = 0; i < 400; ++i) columns.push_back({0.25 * c, y(rng)});
  }
  pts = SpatiallyOrdered(columns);
  for (uint32_t strips : {2u, 3u, 4u, 9u}) {
    ExpectSameAsSerial(pts, DistinctSites(pts), strips);
  }
}

// Duplicates are not sites; the strips see only the sites given.
TEST(StripBuilder, SubsetOfThePositions) {
  const auto pts = SpatiallyOrdered(testing::WithDuplicates(5000, 3, 13));
  const auto sites = DistinctSites(pts);
  ASSERT_LT(sites.size(), pts.size());
  ExpectSameAsSerial(pts, sites, 4);
}

// A strip whose sites are collinear cannot be triangulated on its own: the
// build is serial then, and still right.
TEST(StripBuilder, CollinearStripFallsBackToSerial) {
  std::vector<Vec2> pts;
  for (int i = 0; i < 200; ++i) pts.push_back({0.0, double(i)});
  std::mt19937_64 rng(3);
  std::uniform_real_distribution<double> u(1.0, 2.0);
  for (int i = 0; i < 200; ++i) pts.push_back({u(rng), 200 * u(rng)});
  pts = SpatiallyOrdered(pts);
  const StripBuildStats s = ExpectSameAsSerial(pts, DistinctSites(pts), 2);
  EXPECT_TRUE(s.serial_fallback);
  EXPECT_EQ(s.strips, 1u);

  // All collinear: no triangulation at all, like the serial build.
  const auto line = SpatiallyOrdered(testing::Collinear(500, 2));
  EXPECT_TRUE(BuildDelaunayInStrips(line, DistinctSites(line), 4).empty());
}

// Points in convex position (every site on its strip's hull) are built
// serially: stitching hulls that large costs more than the strips save.
TEST(StripBuilder, ConvexPositionBuildsSerially) {
  std::vector<Vec2> parabola;
  for (int i = 0; i < 20000; ++i) {
    const double t = i / 1000.0;
    parabola.push_back({t, t * t});
  }
  const auto pts = SpatiallyOrdered(parabola);
  const StripBuildStats s = ExpectSameAsSerial(pts, DistinctSites(pts), 4);
  EXPECT_TRUE(s.serial_fallback);
  EXPECT_EQ(s.strips, 1u);
}

// Regression: sites inserted in a straight spatial order along a convex
// curve each land outside the hull next to the last one and cost a
// quadratic number of flips (80K points on a parabola took 2.3 s in 2
// strips; 200K took 12.5 s when this test was written against the straight
// order). Insertion in rounds keeps it near linear: 200K such points take
// about 0.15-0.4 s, serially (the curve in one quadrant of the bounding
// box) and in strips.
TEST(StripBuilder, ConvexCurveIsNotQuadratic) {
  std::vector<Vec2> raw;
  for (int i = 0; i < 200000; ++i) {
    const double t = i / 10000.0;
    raw.push_back({t, t * t});
  }
  for (uint32_t strips : {1u, 2u}) {
    std::vector<Vec2> curve = raw;
    if (strips == 1) {  // the curve in one quadrant of the bounding box
      curve.push_back({-1000.0, -1000.0});
      curve.push_back({1000.0, 1000.0});
    }
    const auto pts = SpatiallyOrdered(curve);
    const auto t0 = std::chrono::steady_clock::now();
    const Mesh mesh = BuildDelaunayInStrips(pts, DistinctSites(pts), strips);
    const double s =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - t0)
            .count();
    EXPECT_FALSE(mesh.empty());
    EXPECT_LT(s, 4.0) << strips << " strips";
  }
}

TEST(StripBuilder, CancelledBuildReturnsNothing) {
  const auto pts = SpatiallyOrdered(testing::UniformPoints(50000, 9));
  const auto sites = DistinctSites(pts);
  CancelToken token([] { return true; }, CancelToken::Clock::time_point::max(),
                    CancelToken::Clock::duration::zero());
  bool cancelled = false;
  EXPECT_TRUE(BuildDelaunayInStrips(pts, sites, 4, &token, &cancelled).empty());
  EXPECT_TRUE(cancelled);
}

TEST(StripBuilder, DefaultStripCountFollowsSizeAndThreads) {
  EXPECT_EQ(DefaultStripCount(1000), 1u);
  EXPECT_GE(DefaultStripCount(size_t{1} << 22), 1u);
  EXPECT_LE(DefaultStripCount(size_t{1} << 30), 64u);
}

// The canonical layout does not depend on the order in which a builder
// emitted the triangles or on where each triangle starts.
TEST(StripBuilder, SortedLayoutIsCanonical) {
  const auto pts = SpatiallyOrdered(testing::UniformPoints(3000, 21));
  Mesh a = BuildDelaunayWithCgal(pts, DistinctSites(pts));
  // A shuffled, rotated copy of the same triangles.
  const uint32_t nt = a.num_triangles();
  std::vector<uint32_t> perm(nt), rot(nt);
  std::iota(perm.begin(), perm.end(), 0u);
  std::mt19937_64 rng(4);
  std::shuffle(perm.begin(), perm.end(), rng);
  for (uint32_t& r : rot) r = static_cast<uint32_t>(rng() % 3);
  std::vector<uint32_t> new_of_old(nt);
  for (uint32_t i = 0; i < nt; ++i) new_of_old[perm[i]] = i;
  auto moved = [&](uint32_t e) {
    return 3 * new_of_old[e / 3] + (e % 3 + rot[e / 3]) % 3;
  };
  std::vector<uint32_t> origin(a.origin().size()), twin(a.twin().size());
  for (uint32_t e = 0; e < 3 * nt; ++e) {
    origin[moved(e)] = a.origin()[e];
    twin[moved(e)] = moved(a.twin()[e]);
  }
  Mesh b(a.num_vertices(), std::move(origin), std::move(twin));
  a.SortTrianglesByVertex();
  b.SortTrianglesByVertex();
  EXPECT_TRUE(a.origin() == b.origin());
  EXPECT_TRUE(a.twin() == b.twin());
  // Slot 0 of every triangle holds its smallest vertex.
  for (uint32_t t = 0; t < nt; ++t) {
    const uint32_t* o = &a.origin()[3 * t];
    EXPECT_LT(o[0], std::min(o[1], o[2]));
  }
}

}  // namespace
}  // namespace kinetri::core
