// Start sites of position queries' walks (core/hint_grid.h): every hint is
// a site, crowded cells are refined so that the hint lies next to the query
// whatever the density contrast, and the grid stays O(sites) in memory.
#include "core/hint_grid.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <random>
#include <vector>

#include "core/triangulation.h"

namespace kinetri::core {
namespace {

// 90 % of the points in four tight clusters (about 10^4 times the density
// of the rest), 10 % uniform.
std::vector<Vec2> HighContrast(size_t n, uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  std::normal_distribution<double> g(0.0, 0.001);
  const Vec2 centers[4] = {{0.2, 0.3}, {0.7, 0.2}, {0.5, 0.8}, {0.81, 0.77}};
  std::vector<Vec2> out(n);
  for (size_t i = 0; i < n; ++i) {
    if (i % 10 == 0) {
      out[i] = {u(rng), u(rng)};
    } else {
      const Vec2& c = centers[i % 4];
      out[i] = {c.x + g(rng), c.y + g(rng)};
    }
  }
  return out;
}

double Distance(const Vec2& a, const Vec2& b) {
  return std::hypot(a.x - b.x, a.y - b.y);
}

bool IsSite(const TriangulationView& v, uint32_t s) {
  return std::binary_search(v.sites, v.sites + v.num_sites, s);
}

TEST(HintGrid, HintsLieNextToTheQueryInDenseClusters) {
  const std::vector<Vec2> pts = HighContrast(200000, 7);
  auto t = Triangulation::Create(pts);
  ASSERT_TRUE(t.ok()) << t.status();
  const TriangulationView v = t->view();
  const HintGrid grid(v);
  const HintGridView g = grid.view();
  // The hint for each site's own position against the site's nearest
  // neighbour (one of its Delaunay neighbours).
  const TriangulationView q = t->query_view();
  double hint_sum = 0.0, nn_sum = 0.0;
  for (uint32_t i = 0; i < v.num_sites; ++i) {
    const uint32_t s = v.sites[i];
    const uint32_t h = g.Hint(v.pos[s]);
    ASSERT_TRUE(IsSite(v, h)) << "hint " << h << " for site " << s;
    hint_sum += Distance(v.pos[h], v.pos[s]);
    double nn = INFINITY;
    for (const uint32_t* w = q.RowBegin(s); w != q.RowEnd(s); ++w) {
      nn = std::min(nn, Distance(v.pos[*w], v.pos[s]));
    }
    nn_sum += nn;
  }
  // A sub-cell holds about four sites: the hint is a site or two away. (A
  // single uniform grid over the bounding box puts thousands of cluster
  // sites in a cell: about 100 times this.)
  EXPECT_LT(hint_sum, 4.0 * nn_sum)
      << "mean hint distance " << hint_sum / v.num_sites
      << ", mean nearest-neighbour distance " << nn_sum / v.num_sites;
}

// Clustered points leave most cells of the grid empty. An empty cell's hint
// is about the site nearest to the cell, not the first cluster its row
// meets: a walk from there would cross that cluster site by site.
TEST(HintGrid, EmptyCellsHintTheSiteNearestToThem) {
  std::mt19937_64 rng(5);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  std::normal_distribution<double> g(0.0, 0.002);
  std::vector<Vec2> centers(80);
  for (Vec2& c : centers) c = {u(rng), u(rng)};
  std::vector<Vec2> pts(40000);
  for (size_t i = 0; i < pts.size(); ++i) {
    const Vec2& c = centers[i % centers.size()];
    pts[i] = {c.x + g(rng), c.y + g(rng)};
  }
  auto t = Triangulation::Create(pts);
  ASSERT_TRUE(t.ok()) << t.status();
  const TriangulationView v = t->view();
  const HintGrid grid(v);
  const HintGridView h = grid.view();
  const double diagonal = std::hypot(1.0 / h.scale.x, 1.0 / h.scale.y);
  int far = 0;
  const int queries = 2000;
  for (int i = 0; i < queries; ++i) {
    const Vec2 q{u(rng), u(rng)};
    double nearest = INFINITY;
    for (uint32_t j = 0; j < v.num_sites; ++j) {
      nearest = std::min(nearest, Distance(q, v.pos[v.sites[j]]));
    }
    const uint32_t hint = h.Hint(q);
    ASSERT_TRUE(IsSite(v, hint));
    if (Distance(q, v.pos[hint]) > nearest + 2.0 * diagonal) ++far;
  }
  // (With each row's nearest non-empty cell instead, most were far.)
  EXPECT_LE(far, queries / 50) << far << " of " << queries;
}

TEST(HintGrid, EveryPositionGetsASiteAndMemoryStaysLinear) {
  std::mt19937_64 rng(3);
  std::uniform_real_distribution<double> u(-0.5, 1.5);
  for (int shape = 0; shape < 3; ++shape) {
    std::vector<Vec2> pts;
    if (shape == 0) pts = HighContrast(50000, 11);
    if (shape == 1) {
      std::uniform_real_distribution<double> w(0.0, 1.0);
      for (int i = 0; i < 50000; ++i) pts.push_back({w(rng), w(rng)});
    }
    if (shape == 2) {
      // Every site in one cell of a coarse grid column: a thin strip.
      std::uniform_real_distribution<double> w(0.0, 1.0);
      for (int i = 0; i < 50000; ++i) pts.push_back({1e-9 * w(rng), w(rng)});
    }
    auto t = Triangulation::Create(pts);
    ASSERT_TRUE(t.ok()) << t.status();
    const TriangulationView v = t->view();
    const HintGrid grid(v);
    EXPECT_LE(grid.cells().size(), size_t{v.num_sites} + 64)
        << "shape " << shape;
    const HintGridView g = grid.view();
    for (int i = 0; i < 20000; ++i) {
      // Inside, outside and on the border of the bounding box.
      const Vec2 p = i % 3 == 0 ? pts[i % pts.size()] : Vec2{u(rng), u(rng)};
      ASSERT_TRUE(IsSite(v, g.Hint(p))) << "shape " << shape << " at " << i;
    }
  }
}

}  // namespace
}  // namespace kinetri::core
