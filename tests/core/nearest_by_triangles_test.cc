// The nearest Delaunay neighbour of every vertex from one pass over the
// triangles (core/nearest_by_triangles.h) equals the walk around each fan
// (FirstNeighbor) and brute force, including on a lattice, where every
// vertex has four neighbours at the same distance, and on meshes large
// enough that the pass has several parts (the vertices on their borders
// take offers from two parts).
#include "core/nearest_by_triangles.h"

#include <gtest/gtest.h>

#include <memory>
#include <random>
#include <vector>

#include "core/queries.h"
#include "core/query_walks.h"
#include "core/triangulation.h"
#include "tests/core/test_util.h"

namespace kinetri::core {
namespace {

std::vector<NearestNeighbor> ByTriangles(const Triangulation& t) {
  const TriangulationView v = t.view();
  std::vector<NearestNeighbor> out(v.num_points);
  t.Run([&] {
    NearestNeighborsByTriangles(v.mesh, v.pos, v.vertex_edge, v.num_points,
                                out.data());
  });
  return out;
}

// Every vertex against the walk around its fan; a sample against brute
// force (in external ids).
void ExpectWalkAnswers(const Triangulation& t) {
  const TriangulationView v = t.view();
  ASSERT_TRUE(v.planar());
  ASSERT_EQ(v.num_sites, v.num_points);
  // Several parts of 16384 slots, so some vertices lie on their borders.
  ASSERT_GT(v.mesh.num_half_edges / 3, 3u * 16384u);
  const std::vector<NearestNeighbor> got = ByTriangles(t);
  for (uint32_t in = 0; in < v.num_points; ++in) {
    const uint32_t want = FirstNeighbor(v, v.pos[in], in, false);
    ASSERT_EQ(got[in].id, want) << "vertex " << in;
    ASSERT_EQ(got[in].d2, SquaredDistance(v.pos[in], v.pos[want]));
  }
  const std::vector<Vec2> pts = t.Positions();
  std::mt19937_64 rng(5);
  for (int s = 0; s < 40; ++s) {
    const uint32_t ext = static_cast<uint32_t>(rng() % pts.size());
    const uint32_t in = v.int_of_ext[ext];
    EXPECT_EQ(v.ext_of_int[got[in].id],
              testing::BruteRank(pts, pts[ext], ext)[0])
        << "point " << ext;
  }
}

TEST(NearestByTriangles, UniformPointsAfterSteps) {
  const size_t n = 60000;
  auto t = Triangulation::Create(testing::UniformPoints(n, 31));
  ASSERT_TRUE(t.ok()) << t.status();
  ExpectWalkAnswers(*t);
  std::mt19937_64 rng(32);
  for (int s = 0; s < 3; ++s) {
    ASSERT_TRUE(
        t->ApplyDisplacements(testing::Brownian(n, 0.2 / std::sqrt(n), rng))
            .ok());
  }
  ExpectWalkAnswers(*t);
}

TEST(NearestByTriangles, LatticeTiesFollowTheQueryOrder) {
  auto t = Triangulation::Create(testing::Lattice(180, 0.5));
  ASSERT_TRUE(t.ok()) << t.status();
  ExpectWalkAnswers(*t);
}

TEST(NearestByTriangles, SameForOneAndAllThreads) {
  const auto pts = testing::ClusteredPoints(50000, 33);
  TriangulationOptions one;
  one.num_threads = 1;
  auto a = Triangulation::Create(pts, one);
  auto b = Triangulation::Create(pts);
  ASSERT_TRUE(a.ok() && b.ok());
  const std::vector<NearestNeighbor> x = ByTriangles(*a), y = ByTriangles(*b);
  ASSERT_EQ(x.size(), y.size());
  for (size_t i = 0; i < x.size(); ++i) {
    ASSERT_EQ(x[i].id, y[i].id);
    ASSERT_EQ(x[i].d2, y[i].d2);
  }
}

// The public query takes this path whenever every point is a site: its
// rows must be the walk's (in external ids, with distances).
TEST(NearestByTriangles, AllNearestNeighborsUsesIt) {
  auto t = Triangulation::Create(testing::Lattice(150, 1.0));
  ASSERT_TRUE(t.ok());
  auto all = AllNearestNeighbors(*t);
  ASSERT_TRUE(all.ok());
  const TriangulationView v = t->view();
  ASSERT_EQ(all->num_queries(), v.num_points);
  for (uint32_t ext = 0; ext < v.num_points; ++ext) {
    uint32_t nn = kNoVertex;
    double d = 0.0;
    ASSERT_TRUE(NearestOtherPoint(v, v.int_of_ext[ext], &nn, &d));
    ASSERT_EQ(all->row_size(ext), 1u);
    ASSERT_EQ(all->ids[ext], nn) << "point " << ext;
    ASSERT_EQ(all->distances[ext], d);
  }
}

}  // namespace
}  // namespace kinetri::core
