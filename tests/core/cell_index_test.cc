// The cell index of radius queries (core/cell_index.h): in both forms
// (dense cells, and the occupied cells of each row for clustered points)
// the runs of a disk hold every site within r of the query, whatever the
// rounding, and little else; the limits decide the form before sorting.
#include "core/cell_index.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <random>
#include <vector>

#include "core/predicates.h"
#include "core/triangulation.h"
#include "tests/core/test_util.h"

namespace kinetri::core {
namespace {

CellIndex::Limits Dense() {
  CellIndex::Limits l;
  l.max_dense_cells = SIZE_MAX;
  return l;
}
CellIndex::Limits Sparse() {
  CellIndex::Limits l;
  l.max_dense_cells = 0;
  l.max_rows = SIZE_MAX;
  return l;
}

// Sites within r of q (exact) from the index's runs, sorted; *scanned
// counts the candidates.
std::vector<uint32_t> FromRuns(const CellIndex& g, const Vec2& q, double r,
                               size_t* scanned) {
  std::vector<uint32_t> out;
  g.ForEachRun(q, r, [&](uint32_t b, uint32_t e) {
    EXPECT_LT(b, e);
    *scanned += e - b;
    for (uint32_t s = b; s < e; ++s) {
      if (CompareDistanceToRadius(q, g.positions()[s], r) <= 0) {
        out.push_back(g.site(s));
      }
    }
    return true;
  });
  std::sort(out.begin(), out.end());
  return out;
}

std::vector<uint32_t> Brute(const TriangulationView& v, const Vec2& q,
                            double r) {
  std::vector<uint32_t> out;
  for (uint32_t i = 0; i < v.num_sites; ++i) {
    if (CompareDistanceToRadius(q, v.pos[v.sites[i]], r) <= 0) {
      out.push_back(v.sites[i]);
    }
  }
  std::sort(out.begin(), out.end());
  return out;
}

// The runs of a disk, as (begin, end) pairs.
std::vector<std::pair<uint32_t, uint32_t>> Runs(const CellIndex& g,
                                                const Vec2& q, double r) {
  std::vector<std::pair<uint32_t, uint32_t>> runs;
  g.ForEachRun(q, r, [&](uint32_t b, uint32_t e) {
    runs.push_back({b, e});
    return true;
  });
  return runs;
}

// Checks both forms (the sparse one found by rank and by binary search:
// the same runs); returns how many of the sparse builds were ranked.
int CheckBothForms(const std::vector<Vec2>& pts,
                   const std::vector<double>& radii, uint64_t seed) {
  int ranked = 0;
  auto t = Triangulation::Create(pts);
  EXPECT_TRUE(t.ok());
  if (!t.ok()) return ranked;
  const TriangulationView v = t->view();
  std::mt19937_64 rng(seed);
  std::uniform_int_distribution<size_t> pick(0, pts.size() - 1);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  for (double r : radii) {
    const auto dense = CellIndex::Build(v, r, Dense());
    const auto sparse = CellIndex::Build(v, r, Sparse());
    CellIndex::Limits searched = Sparse();
    searched.rank_rows = false;
    const auto sparse_searched = CellIndex::Build(v, r, searched);
    EXPECT_TRUE(dense && sparse && sparse_searched) << "r=" << r;
    if (!dense || !sparse || !sparse_searched) return ranked;
    EXPECT_FALSE(sparse_searched->ranked());
    ranked += sparse->ranked();
    EXPECT_FALSE(dense->sparse());
    EXPECT_TRUE(sparse->sparse());
    // The same cells, so the same mean occupancy; never more cells kept
    // than sites in the sparse form.
    EXPECT_DOUBLE_EQ(dense->occupancy(), sparse->occupancy());
    EXPECT_LE(sparse->num_cells(), v.num_sites);
    size_t scanned_dense = 0, scanned_sparse = 0, found = 0;
    for (int k = 0; k < 300; ++k) {
      // Queries at sites, next to them, on cell borders and far outside.
      Vec2 q = pts[pick(rng)];
      if (k % 3 == 1) q = {q.x + r * u(rng), q.y + r * u(rng)};
      if (k % 7 == 2) q = {q.x + r, q.y - r};
      if (k % 31 == 5) q = {q.x + 50 * r * u(rng), q.y - 1e3 * r};
      // Radii exactly reaching a site: sites on the circle.
      double rq = r;
      if (k % 5 == 3) {
        const Vec2 p = pts[pick(rng)];
        rq = std::hypot(p.x - q.x, p.y - q.y);
        if (!(rq > 0.0) || rq > 4 * r) rq = r;
      }
      const auto want = Brute(v, q, rq);
      EXPECT_EQ(Runs(*sparse, q, rq), Runs(*sparse_searched, q, rq))
          << "r=" << rq << " q=" << q.x << "," << q.y;
      const auto from_dense = FromRuns(*dense, q, rq, &scanned_dense);
      const auto from_sparse = FromRuns(*sparse, q, rq, &scanned_sparse);
      EXPECT_EQ(from_dense, want)
          << "dense r=" << rq << " q=" << q.x << "," << q.y;
      EXPECT_EQ(from_sparse, want)
          << "sparse r=" << rq << " q=" << q.x << "," << q.y;
      if (from_dense != want || from_sparse != want) return ranked;
      found += want.size();
    }
    // Both forms scan the same cells.
    EXPECT_EQ(scanned_dense, scanned_sparse) << "r=" << r;
    EXPECT_GT(found, 0u);
  }
  return ranked;
}

TEST(CellIndex, BothFormsFindEveryDiskUniform) {
  EXPECT_GT(CheckBothForms(testing::UniformPoints(3000, 1),
                           {0.004, 0.02, 0.05, 0.3}, 2),
            0);
}

TEST(CellIndex, BothFormsFindEveryDiskClustered) {
  EXPECT_GT(
      CheckBothForms(testing::ClusteredPoints(3000, 3), {1e-4, 0.003, 0.02}, 4),
      0);
}

TEST(CellIndex, BothFormsFindEveryDiskOnALattice) {
  // Cocircular sites, and sites exactly on cell borders.
  CheckBothForms(testing::Lattice(40), {1.0, 2.0, 2.5, 7.0}, 5);
}

TEST(CellIndex, BothFormsFindEveryDiskFarFromTheOrigin) {
  CheckBothForms(testing::UniformPoints(2000, 6, 1.0, 1e9), {0.01, 0.05}, 7);
  CheckBothForms(testing::UniformPoints(2000, 8, 1e-9), {1e-11, 5e-11}, 9);
}

// Squares much wider than a cell (a point between clusters, in cells sized
// for the clusters): the ranked form skips the rows it finds empty in the
// bitmap, across all of a row's words, and must give the same runs as the
// binary searches.
TEST(CellIndex, WideSquaresSkipEmptyRowsOfTheBitmap) {
  const auto pts = testing::ClusteredPoints(4000, 21);
  auto t = Triangulation::Create(pts);
  ASSERT_TRUE(t.ok());
  const TriangulationView v = t->view();
  const double side = 1.2e-3;  // about 14 words per row: the bitmap is kept
  const auto ranked = CellIndex::Build(v, side, Sparse());
  CellIndex::Limits searched_limits = Sparse();
  searched_limits.rank_rows = false;
  const auto searched = CellIndex::Build(v, side, searched_limits);
  ASSERT_TRUE(ranked && searched);
  ASSERT_TRUE(ranked->ranked());
  std::mt19937_64 rng(22);
  std::uniform_int_distribution<size_t> pick(0, pts.size() - 1);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  size_t found = 0, runs = 0;
  for (int k = 0; k < 400; ++k) {
    // Anywhere in the box (mostly between the clusters), radii of 1 to
    // 1000 cells; every 4th query centred near a multiple of 64 cells.
    Vec2 q = k % 2 == 0 ? pts[pick(rng)] : Vec2{u(rng), u(rng)};
    if (k % 4 == 3) q.x = 64 * side * std::floor(q.x / (64 * side));
    const double r = side * std::pow(1000.0, u(rng));
    const auto want = Brute(v, q, r);
    const auto got_runs = Runs(*ranked, q, r);
    ASSERT_EQ(got_runs, Runs(*searched, q, r))
        << "r=" << r << " q=" << q.x << "," << q.y;
    size_t scanned = 0;
    ASSERT_EQ(FromRuns(*ranked, q, r, &scanned), want)
        << "r=" << r << " q=" << q.x << "," << q.y;
    found += want.size();
    runs += got_runs.size();
  }
  EXPECT_GT(found, 0u);
  EXPECT_GT(runs, 0u);
}

// Squares whose columns start and end at every side of a 64-column word
// boundary, over rows with sites in exactly those columns: any bit the
// ranked form's masks get wrong changes the runs.
TEST(CellIndex, SquaresAtWordBoundariesSkipOnlyEmptyRows) {
  const std::vector<uint32_t> marked = {0,   1,   62,  63,  64,  65,  126,
                                        127, 128, 129, 190, 191, 192, 200};
  // Sites at cell centres (side 1, the box starting at 0.5): one in each
  // marked column, in a row of its own pattern, and the box's corners.
  std::vector<Vec2> pts = {{0.5, 0.5}, {200.5, 10.5}};
  for (uint32_t c : marked) {
    pts.push_back({c + 0.5, (c * 7 % 11) + 0.5});
    pts.push_back({c + 0.5, (c * 3 % 11) + 0.5});
  }
  std::sort(pts.begin(), pts.end(), [](const Vec2& a, const Vec2& b) {
    return a.x != b.x ? a.x < b.x : a.y < b.y;
  });
  pts.erase(std::unique(pts.begin(), pts.end()), pts.end());
  auto t = Triangulation::Create(pts);
  ASSERT_TRUE(t.ok());
  const TriangulationView v = t->view();
  const auto ranked = CellIndex::Build(v, 1.0, Sparse());
  CellIndex::Limits searched_limits = Sparse();
  searched_limits.rank_rows = false;
  const auto searched = CellIndex::Build(v, 1.0, searched_limits);
  ASSERT_TRUE(ranked && searched);
  ASSERT_TRUE(ranked->ranked());
  size_t runs = 0;
  for (uint32_t a : marked) {
    for (uint32_t b : marked) {
      if (b < a) continue;
      for (int row = 0; row <= 10; ++row) {
        // The square spans exactly columns a..b (and as many rows).
        const double r = (b - a) / 2.0 + 0.25;
        const Vec2 q{0.5 + (a + b + 1) / 2.0, row + 1.0};
        const auto got = Runs(*ranked, q, r);
        ASSERT_EQ(got, Runs(*searched, q, r))
            << "columns " << a << ".." << b << " row " << row;
        size_t scanned = 0;
        ASSERT_EQ(FromRuns(*ranked, q, r, &scanned), Brute(v, q, r))
            << "columns " << a << ".." << b << " row " << row;
        runs += got.size();
      }
    }
  }
  EXPECT_GT(runs, 0u);
}

// Columns too many to count (more than 4 per site: each row's sites are
// sorted instead): the box is 1000 times wider than high.
TEST(CellIndex, SparseFormOfAWideBox) {
  auto pts = testing::ClusteredPoints(3000, 11);
  for (Vec2& p : pts) p.x *= 1000.0;
  auto t = Triangulation::Create(pts);
  ASSERT_TRUE(t.ok());
  const TriangulationView v = t->view();
  std::mt19937_64 rng(12);
  std::uniform_int_distribution<size_t> pick(0, pts.size() - 1);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  for (double r : {0.002, 0.02}) {
    const auto sparse = CellIndex::Build(v, r, Sparse());
    ASSERT_TRUE(sparse);
    EXPECT_TRUE(sparse->sparse());
    size_t scanned = 0, found = 0;
    for (int k = 0; k < 300; ++k) {
      Vec2 q = pts[pick(rng)];
      if (k % 3 == 1) q = {q.x + r * u(rng), q.y + r * u(rng)};
      const auto want = Brute(v, q, r);
      ASSERT_EQ(FromRuns(*sparse, q, r, &scanned), want)
          << "r=" << r << " q=" << q.x << "," << q.y;
      found += want.size();
    }
    EXPECT_GT(found, 0u);
  }
}

TEST(CellIndex, LimitsDecideTheForm) {
  const auto pts = testing::ClusteredPoints(2000, 10);
  auto t = Triangulation::Create(pts);
  ASSERT_TRUE(t.ok());
  const TriangulationView v = t->view();
  const double r = 1e-3;  // the box needs about 10^6 cells
  CellIndex::Limits l;
  l.max_dense_cells = 4 * 2000 + 64;
  l.min_sparse_cells = l.max_dense_cells;
  l.max_rows = l.max_dense_cells;
  const auto g = CellIndex::Build(v, r, l);
  ASSERT_TRUE(g);
  EXPECT_TRUE(g->sparse());
  // Clustered: a site sees many more sites in its cell than the mean
  // density over the box would put there.
  EXPECT_GT(g->occupancy(), 1.0);
  // Too many rows, or a box that would fit the dense form after all.
  l.max_rows = 100;
  EXPECT_FALSE(CellIndex::Build(v, r, l));
  l.max_rows = SIZE_MAX;
  l.min_sparse_cells = SIZE_MAX;
  EXPECT_FALSE(CellIndex::Build(v, r, l));
  // A large radius fits the dense form.
  const auto d = CellIndex::Build(v, 0.1, l);
  ASSERT_TRUE(d);
  EXPECT_FALSE(d->sparse());
}

// The sampled estimate tells crowded cells from ordinary ones before an
// index is built (the k-nearest queries pick the form by it): low, never
// above the crowding threshold, for even points; large for clusters.
TEST(CellIndex, SampledOccupancySeparatesClustersFromEvenPoints) {
  for (const bool clustered : {false, true}) {
    const auto pts = clustered ? testing::ClusteredPoints(100000, 12)
                               : testing::UniformPoints(100000, 12);
    auto t = Triangulation::Create(pts);
    ASSERT_TRUE(t.ok());
    const TriangulationView v = t->view();
    const double side = CellIndex::SideForOccupancy(v, 2.0);
    const auto exact = CellIndex::Build(v, side, Dense());
    ASSERT_TRUE(exact);
    const double estimate = CellIndex::EstimateOccupancy(v, side, 16, SIZE_MAX);
    if (clustered) {
      EXPECT_GT(exact->occupancy(), 24.0);
      EXPECT_GT(estimate, 24.0) << "exact " << exact->occupancy();
      EXPECT_LT(estimate, 2.0 * exact->occupancy());
    } else {
      EXPECT_LT(exact->occupancy(), 4.0);
      EXPECT_GE(estimate, 1.0);
      EXPECT_LT(estimate, 6.0) << "exact " << exact->occupancy();
    }
    // More cells than allowed: no estimate.
    EXPECT_EQ(CellIndex::EstimateOccupancy(v, side, 16, 10), INFINITY);
  }
}

}  // namespace
}  // namespace kinetri::core
