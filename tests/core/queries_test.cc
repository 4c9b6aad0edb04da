// Every query kind against brute force on random and degenerate inputs.
// Built for the host executors and, with KINETRI_TEST_DEVICE /
// KINETRI_TEST_CUDA, for the device executor's queries (the same calls of
// core/queries.h then run on its emulated or CUDA backend).
#include "core/queries.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <functional>
#include <numeric>
#include <random>
#include <thread>

#if defined(__SSE2__)
#include <xmmintrin.h>
#endif

#include "core/cell_index.h"
#include "core/predicates.h"
#include "tests/core/executor_under_test.h"
#include "tests/core/test_util.h"

namespace kinetri::core {
namespace {

using testing::BruteRank;
using testing::QueryPoints;

// A triangulation on the executor under test.
absl::StatusOr<Triangulation> Make(const std::vector<Vec2>& pts) {
  return Triangulation::Create(pts, testing::ExecutorOptions());
}

std::vector<uint32_t> Row(const NeighborLists& r, size_t i) {
  return {r.ids.begin() + r.offsets[i], r.ids.begin() + r.offsets[i + 1]};
}

void CheckAllQueries(const std::vector<Vec2>& pts, uint64_t seed) {
  auto t = Make(pts);
  ASSERT_TRUE(t.ok()) << t.status();
  const uint32_t n = pts.size();
  // All-points nearest neighbour.
  auto all = AllNearestNeighbors(*t);
  ASSERT_TRUE(all.ok());
  ASSERT_EQ(all->num_queries(), n);
  for (uint32_t i = 0; i < n; ++i) {
    const auto rank = BruteRank(pts, pts[i], i);
    const auto row = Row(*all, i);
    if (rank.empty()) {
      EXPECT_TRUE(row.empty());
    } else {
      ASSERT_EQ(row.size(), 1u);
      EXPECT_EQ(row[0], rank[0]) << "all-NN of " << i;
      EXPECT_DOUBLE_EQ(
          all->distances[all->offsets[i]],
          std::hypot(pts[i].x - pts[rank[0]].x, pts[i].y - pts[rank[0]].y));
    }
  }
  // k-NN of positions and of points.
  const auto qs = QueryPoints(pts, 300, seed);
  std::vector<uint32_t> ids(std::min<uint32_t>(n, 300));
  std::iota(ids.begin(), ids.end(), 0);
  for (int k : {1, 4, 17, 40, int(n) + 3}) {
    auto r = KNearest(*t, qs, k);
    ASSERT_TRUE(r.ok());
    for (size_t i = 0; i < qs.size(); ++i) {
      auto rank = BruteRank(pts, qs[i], kNoVertex);
      rank.resize(std::min<size_t>(rank.size(), k));
      ASSERT_EQ(Row(*r, i), rank) << "kNN k=" << k << " query " << i;
    }
    for (bool exclude : {true, false}) {
      auto rp = KNearestOfPoints(*t, ids, k, exclude);
      ASSERT_TRUE(rp.ok());
      for (size_t i = 0; i < ids.size(); ++i) {
        auto rank = BruteRank(pts, pts[ids[i]], exclude ? ids[i] : kNoVertex);
        rank.resize(std::min<size_t>(rank.size(), k));
        ASSERT_EQ(Row(*rp, i), rank) << "kNN of point " << ids[i];
      }
      // Both ways of finding the k nearest (best first over the graph, and
      // growing disks over a cell index) give these rows exactly. The cells
      // serve k up to 64 (beyond, both plans are the graph's rows: not run
      // twice, since a k of n + 3 is slow on a GPU thread).
      if (k > 64) continue;
      for (auto plan : {RowOptions::Plan::kGraph, RowOptions::Plan::kCells}) {
        RowOptions forced;
        forced.plan = plan;
        auto alt = KNearest(*t, qs, k, {}, forced);
        auto alt_p = KNearestOfPoints(*t, ids, k, exclude, {}, forced);
        ASSERT_TRUE(alt.ok() && alt_p.ok());
        for (auto [got, ref] : {std::pair{&*alt, &*r}, {&*alt_p, &*rp}}) {
          EXPECT_EQ(got->offsets, ref->offsets) << "plan k=" << k;
          EXPECT_EQ(got->ids, ref->ids) << "plan k=" << k;
          EXPECT_EQ(got->distances, ref->distances) << "plan k=" << k;
          EXPECT_EQ(got->truncated, ref->truncated) << "plan k=" << k;
        }
      }
    }
  }
  // Fixed radius, including radii that hit points exactly.
  double typical = 0.0;
  for (size_t i = 1; i < std::min<size_t>(n, 50); ++i) {
    typical =
        std::max(typical, std::hypot(pts[i].x - pts[0].x, pts[i].y - pts[0].y));
  }
  for (double r : {0.0, typical * 0.05, typical * 0.2, typical}) {
    for (uint32_t cap : {0u, 5u}) {
      auto res = WithinRadius(*t, qs, r, cap);
      ASSERT_TRUE(res.ok());
      for (size_t i = 0; i < qs.size(); ++i) {
        std::vector<uint32_t> want;
        for (uint32_t id : BruteRank(pts, qs[i], kNoVertex)) {
          if (CompareDistanceToRadius(qs[i], pts[id], r) <= 0)
            want.push_back(id);
        }
        const bool cut = cap && want.size() > cap;
        if (cut) want.resize(cap);
        ASSERT_EQ(Row(*res, i), want) << "FRNN r=" << r << " query " << i;
        EXPECT_EQ(res->truncated[i] != 0, cut);
      }
      auto resp = WithinRadiusOfPoints(*t, ids, r, true, cap);
      ASSERT_TRUE(resp.ok());
      for (size_t i = 0; i < ids.size(); ++i) {
        std::vector<uint32_t> want;
        for (uint32_t id : BruteRank(pts, pts[ids[i]], ids[i])) {
          if (CompareDistanceToRadius(pts[ids[i]], pts[id], r) <= 0) {
            want.push_back(id);
          }
        }
        if (cap && want.size() > cap) want.resize(cap);
        ASSERT_EQ(Row(*resp, i), want) << "FRNN of point " << ids[i];
      }
      // Both ways of finding the sites of a disk (the graph walk and the
      // cell index) give these rows exactly.
      for (auto plan : {RowOptions::Plan::kGraph, RowOptions::Plan::kCells}) {
        RowOptions forced;
        forced.plan = plan;
        auto alt = WithinRadius(*t, qs, r, cap, {}, forced);
        auto alt_p = WithinRadiusOfPoints(*t, ids, r, true, cap, {}, forced);
        ASSERT_TRUE(alt.ok() && alt_p.ok());
        for (auto [got, ref] : {std::pair{&*alt, &*res}, {&*alt_p, &*resp}}) {
          EXPECT_EQ(got->offsets, ref->offsets) << "plan r=" << r;
          EXPECT_EQ(got->ids, ref->ids) << "plan r=" << r;
          EXPECT_EQ(got->distances, ref->distances) << "plan r=" << r;
          EXPECT_EQ(got->truncated, ref->truncated) << "plan r=" << r;
        }
      }
      // Set-only rows (traversal order, no distances): the same points;
      // rows cut by the cap are still the closest ones, closest first. By
      // the planner's choice and by each way of finding a disk's sites
      // (uncut set-only rows from the cell index have their own scan).
      for (auto plan : {RowOptions::Plan::kAuto, RowOptions::Plan::kGraph,
                        RowOptions::Plan::kCells}) {
        // Traversal order with distances: each row's (id, distance) pairs
        // are the reference's.
        RowOptions traversal;
        traversal.closest_first = false;
        traversal.plan = plan;
        auto tr = WithinRadius(*t, qs, r, cap, {}, traversal);
        ASSERT_TRUE(tr.ok());
        ASSERT_EQ(tr->offsets, res->offsets) << "traversal r=" << r;
        for (size_t i = 0; i < tr->num_queries(); ++i) {
          if (tr->truncated[i]) continue;
          std::vector<std::pair<uint32_t, double>> got, want;
          for (uint64_t k = tr->offsets[i]; k < tr->offsets[i + 1]; ++k) {
            got.push_back({tr->ids[k], tr->distances[k]});
            want.push_back({res->ids[k], res->distances[k]});
          }
          std::sort(got.begin(), got.end());
          std::sort(want.begin(), want.end());
          ASSERT_EQ(got, want) << "traversal r=" << r << " query " << i;
        }
        RowOptions set_only;
        set_only.closest_first = false;
        set_only.distances = false;
        set_only.plan = plan;
        auto sets = WithinRadius(*t, qs, r, cap, {}, set_only);
        auto sets_p = WithinRadiusOfPoints(*t, ids, r, true, cap, {}, set_only);
        ASSERT_TRUE(sets.ok() && sets_p.ok());
        EXPECT_TRUE(sets->distances.empty());
        EXPECT_TRUE(sets_p->distances.empty());
        for (auto [got, ref] : {std::pair{&*sets, &*res}, {&*sets_p, &*resp}}) {
          ASSERT_EQ(got->offsets, ref->offsets) << "set-only r=" << r;
          EXPECT_EQ(got->truncated, ref->truncated);
          for (size_t i = 0; i < got->num_queries(); ++i) {
            auto row = Row(*got, i);
            if (!got->truncated[i]) std::sort(row.begin(), row.end());
            auto want = Row(*ref, i);
            if (!ref->truncated[i]) std::sort(want.begin(), want.end());
            ASSERT_EQ(row, want) << "set-only r=" << r << " query " << i;
          }
        }
      }
    }
  }
}

TEST(Queries, Uniform) { CheckAllQueries(testing::UniformPoints(2000, 1), 2); }

// The k nearest of every point of a large set, by the planner's choice and
// by each plan, against brute force for a sample: the planner scans a cell
// index (kept for the step), dense on evenly spread sets and sparse, with
// cells the size of the clusters', on clustered ones. Positions between
// clusters are answered by the graph from the same step's index.
TEST(Queries, KNearestOfEveryPointByEachPlan) {
  for (bool clustered : {false, true}) {
    const std::vector<Vec2> pts = clustered
                                      ? testing::ClusteredPoints(30000, 31)
                                      : testing::UniformPoints(30000, 32);
    auto t = Make(pts);
    ASSERT_TRUE(t.ok()) << t.status();
    std::vector<uint32_t> all(pts.size());
    std::iota(all.begin(), all.end(), 0);
    for (int k : {2, 8, 33}) {
      auto ref = KNearestOfPoints(*t, all, k, true);
      ASSERT_TRUE(ref.ok()) << ref.status();
      for (uint32_t i = 0; i < pts.size(); i += 499) {
        auto rank = BruteRank(pts, pts[i], i);
        rank.resize(k);
        ASSERT_EQ(Row(*ref, i), rank) << "k=" << k << " point " << i;
      }
      for (auto plan : {RowOptions::Plan::kGraph, RowOptions::Plan::kCells}) {
        RowOptions forced;
        forced.plan = plan;
        auto got = KNearestOfPoints(*t, all, k, true, {}, forced);
        ASSERT_TRUE(got.ok());
        EXPECT_EQ(got->ids, ref->ids) << "k=" << k;
        EXPECT_EQ(got->distances, ref->distances) << "k=" << k;
      }
    }
    // Positions, inside and between the clusters (and far outside), with
    // the step's index built: the planner's rows against brute force.
    std::vector<Vec2> qs = QueryPoints(pts, 300, 33);
    for (double d : {-3.0, 0.5, 40.0}) qs.push_back({d, d});
    auto pos = KNearest(*t, qs, 8);
    ASSERT_TRUE(pos.ok()) << pos.status();
    for (size_t i = 0; i < qs.size(); ++i) {
      auto rank = BruteRank(pts, qs[i], kNoVertex);
      rank.resize(8);
      ASSERT_EQ(Row(*pos, i), rank) << "position " << i;
    }
    if (testing::ExecutorOptions().executor == Executor::kDevice) continue;
    // The planner's decision of this step (made by the batches above, not
    // here): an index, dense for the even set, sparse for the clustered one.
    auto kept = t->CachedCellIndex(Triangulation::CellIndexUse::kNearest, 0.0,
                                   []() -> std::shared_ptr<const CellIndex> {
                                     ADD_FAILURE() << "not cached";
                                     return nullptr;
                                   });
    ASSERT_NE(kept, nullptr);
    EXPECT_EQ(kept->sparse(), clustered);
  }
}

// Growing disks over a cell index where the density jumps (a dense patch
// in an even set: a row's first radius, from the last row's, holds
// thousands of sites or none), for queries inside, at the edge of and far
// outside the sites' box.
TEST(Queries, KNearestFromCellsWhereTheDensityJumps) {
  std::vector<Vec2> pts = testing::UniformPoints(6000, 41);
  std::mt19937_64 rng(42);
  std::uniform_real_distribution<double> u(0.0, 1e-4);
  for (int i = 0; i < 6000; ++i) pts.push_back({0.5 + u(rng), 0.5 + u(rng)});
  auto t = Make(pts);
  ASSERT_TRUE(t.ok()) << t.status();
  std::vector<Vec2> qs = QueryPoints(pts, 400, 43);
  for (double d : {-10.0, 1.0, 1e6}) qs.push_back({d, 0.5});
  for (int i = 0; i < 50; ++i) qs.push_back({0.5 + u(rng), 0.5 + u(rng)});
  std::vector<uint32_t> ids(pts.size());
  std::iota(ids.begin(), ids.end(), 0);
  RowOptions cells;
  cells.plan = RowOptions::Plan::kCells;
  for (int k : {1, 5, 64}) {
    auto r = KNearest(*t, qs, k, {}, cells);
    ASSERT_TRUE(r.ok());
    for (size_t i = 0; i < qs.size(); ++i) {
      auto rank = BruteRank(pts, qs[i], kNoVertex);
      rank.resize(k);
      ASSERT_EQ(Row(*r, i), rank) << "k=" << k << " query " << i;
    }
    auto rp = KNearestOfPoints(*t, ids, k, true, {}, cells);
    auto graph = KNearestOfPoints(*t, ids, k, true);
    ASSERT_TRUE(rp.ok() && graph.ok());
    EXPECT_EQ(rp->ids, graph->ids) << "k=" << k;
    EXPECT_EQ(rp->distances, graph->distances) << "k=" << k;
  }
}
// A batch too small to earn the step's neighbour rows (and one answered
// from cells) reads the sites' neighbours off the mesh: the same rows as
// after a large batch built them, and the rows are built only then (sites
// of several points always build them: their members are listed there).
TEST(Queries, SmallGraphBatchesReadTheMesh) {
  const bool host = testing::ExecutorOptions().executor != Executor::kDevice;
  for (bool duplicates : {false, true}) {
    std::vector<Vec2> pts = testing::UniformPoints(20000, 51);
    if (duplicates) {
      for (int i = 0; i < 500; ++i) pts.push_back(pts[7 * i]);
    }
    auto t = Make(pts);
    ASSERT_TRUE(t.ok()) << t.status();
    const std::vector<Vec2> qs = QueryPoints(pts, 300, 52);
    std::vector<uint32_t> ids(300);
    std::iota(ids.begin(), ids.end(), 100);
    const double r = 3.0 / std::sqrt(double(pts.size()));
    RowOptions graph;
    graph.plan = RowOptions::Plan::kGraph;
    RowOptions cells;
    cells.plan = RowOptions::Plan::kCells;
    RowOptions cut_sorted = graph;
    cut_sorted.closest_first = true;
    // Every small batch of the step, in order.
    auto small = [&] {
      std::vector<absl::StatusOr<NeighborLists>> out;
      out.push_back(Nearest(*t, qs));
      out.push_back(KNearest(*t, qs, 8, {}, graph));
      out.push_back(KNearest(*t, qs, 8, {}, cells));
      out.push_back(KNearestOfPoints(*t, ids, 5, true, {}, graph));
      out.push_back(WithinRadius(*t, qs, r, 0, {}, graph));
      out.push_back(WithinRadius(*t, qs, r, 4, {}, cut_sorted));
      out.push_back(WithinRadiusOfPoints(*t, ids, r, true, 0, {}, graph));
      return out;
    };
    const auto before = small();
    if (host) {
      EXPECT_EQ(t->view_with_cached_rows().adj_offsets != nullptr, duplicates)
          << "rows built by small batches";
    }
    for (size_t i = 0; i < qs.size(); ++i) {
      auto rank = BruteRank(pts, qs[i], kNoVertex);
      rank.resize(8);
      ASSERT_TRUE(before[1].ok() && before[2].ok());
      ASSERT_EQ(Row(*before[1], i), rank) << "query " << i;
      ASSERT_EQ(Row(*before[2], i), rank) << "query " << i;
    }
    // A batch of every point builds them; the small ones give the same.
    std::vector<uint32_t> all(pts.size());
    std::iota(all.begin(), all.end(), 0);
    ASSERT_TRUE(KNearestOfPoints(*t, all, 3, true, {}, graph).ok());
    if (host) {
      EXPECT_NE(t->view_with_cached_rows().adj_offsets, nullptr);
    }
    const auto after = small();
    ASSERT_EQ(before.size(), after.size());
    for (size_t c = 0; c < before.size(); ++c) {
      ASSERT_TRUE(before[c].ok() && after[c].ok()) << "call " << c;
      EXPECT_EQ(before[c]->offsets, after[c]->offsets) << "call " << c;
      EXPECT_EQ(before[c]->ids, after[c]->ids) << "call " << c;
      EXPECT_EQ(before[c]->distances, after[c]->distances) << "call " << c;
      EXPECT_EQ(before[c]->truncated, after[c]->truncated) << "call " << c;
    }
  }
}
// k nearest from cells on a lattice: the k-th distance is shared by up to
// eight points, so the selection of the closest candidates must keep every
// near-tie of its cut and order them exactly (the documented tie order).
TEST(Queries, KNearestFromCellsKeepsTiesAtTheCut) {
  const std::vector<Vec2> pts = testing::Lattice(70, 0.37);
  auto t = Make(pts);
  ASSERT_TRUE(t.ok()) << t.status();
  RowOptions cells;
  cells.plan = RowOptions::Plan::kCells;
  std::vector<uint32_t> all(pts.size());
  std::iota(all.begin(), all.end(), 0);
  std::vector<Vec2> qs;
  for (int i = 0; i < 40; ++i) qs.push_back({0.37 * (i + 0.5), 0.37 * 20.5});
  for (int k : {3, 4, 5, 8, 9, 12, 20}) {
    auto of_points = KNearestOfPoints(*t, all, k, true, {}, cells);
    ASSERT_TRUE(of_points.ok()) << of_points.status();
    for (uint32_t i = 0; i < pts.size(); i += 37) {
      auto rank = BruteRank(pts, pts[i], i);
      rank.resize(k);
      ASSERT_EQ(Row(*of_points, i), rank) << "k=" << k << " point " << i;
    }
    auto of_positions = KNearest(*t, qs, k, {}, cells);
    ASSERT_TRUE(of_positions.ok()) << of_positions.status();
    for (size_t i = 0; i < qs.size(); ++i) {
      auto rank = BruteRank(pts, qs[i], kNoVertex);
      rank.resize(k);
      ASSERT_EQ(Row(*of_positions, i), rank) << "k=" << k << " query " << i;
    }
  }
}

// k nearest from cells where the closest candidates' squared distances
// differ by less than their rounding, and by less than the 2^-46 the
// small selection's packed keys keep of them: rings of points around each
// query at radii equal up to a random 2^-47 relative (squared distances
// up to 2^-46, the packing's resolution), an inner ring of 5
// and an outer one of 4 at 1.6 times the radius. The cut falls inside a
// ring (k = 3, 7: the near ties go to the exact order), in the gap after
// one (k = 5, 9: the packed order is fixed by the exact pass alone), and
// beyond both; every row equals brute force.
TEST(Queries, KNearestFromCellsOrdersDistancesCloserThanTheirRounding) {
  std::vector<Vec2> pts = testing::UniformPoints(5000, 71);
  std::mt19937_64 rng(72);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  const double rho = 0.2 / std::sqrt(5000.0);
  std::vector<Vec2> qs;
  for (int c = 0; c < 60; ++c) {
    const Vec2 q{0.1 + 0.8 * u(rng), 0.1 + 0.8 * u(rng)};
    qs.push_back(q);
    for (int j = 0; j < 9; ++j) {
      const double radius =
          (j < 5 ? rho : 1.6 * rho) * (1.0 + std::ldexp(u(rng), -47));
      const double angle = 2.0 * M_PI * (j + 0.3 * u(rng)) / 9.0;
      pts.push_back(
          {q.x + radius * std::cos(angle), q.y + radius * std::sin(angle)});
    }
  }
  auto t = Make(pts);
  ASSERT_TRUE(t.ok()) << t.status();
  RowOptions cells;
  cells.plan = RowOptions::Plan::kCells;
  for (int k : {1, 3, 5, 7, 8, 9, 12}) {
    auto got = KNearest(*t, qs, k, {}, cells);
    ASSERT_TRUE(got.ok()) << got.status();
    for (size_t i = 0; i < qs.size(); ++i) {
      auto rank = BruteRank(pts, qs[i], kNoVertex);
      rank.resize(k);
      ASSERT_EQ(Row(*got, i), rank) << "k=" << k << " query " << i;
    }
  }
}

#if defined(__SSE2__)
// A position at a site is at squared distance 0 from it. With denormals
// read as zero (the MXCSR flag a program built with -ffast-math sets),
// k nearest from cells still puts that site first and the rest in order.
// The flag is set before the triangulation is made: its threads take the
// floating-point settings of the thread that made it.
TEST(Queries, KNearestFromCellsAtSitesWithDenormalsAreZero) {
  const std::vector<Vec2> pts = testing::UniformPoints(6000, 81);
  std::vector<Vec2> qs;
  std::vector<std::vector<uint32_t>> want;
  for (uint32_t i = 0; i < pts.size(); i += 61) {
    qs.push_back(pts[i]);
    want.push_back(BruteRank(pts, pts[i], kNoVertex));
    want.back().resize(8);
  }
  const unsigned csr = _mm_getcsr();
  _mm_setcsr(csr | 0x0040);  // DAZ
  absl::StatusOr<NeighborLists> got;
  {
    auto t = Make(pts);
    ASSERT_TRUE(t.ok()) << t.status();
    RowOptions cells;
    cells.plan = RowOptions::Plan::kCells;
    got = KNearest(*t, qs, 8, {}, cells);
  }
  _mm_setcsr(csr);
  ASSERT_TRUE(got.ok()) << got.status();
  for (size_t i = 0; i < qs.size(); ++i) {
    ASSERT_EQ(Row(*got, i), want[i]) << "query " << i;
  }
}
#endif

// Radius batches answered from cells: positions walk to their nearest
// sites first, so a large batch of them builds the step's neighbour rows
// for those walks (they were walked over the mesh before); a batch of
// points starts at its sites and does not. The rows equal brute force.
TEST(Queries, LargeRadiusPositionBatchesBuildRowsForTheirWalks) {
  if (testing::ExecutorOptions().executor == Executor::kDevice) {
    GTEST_SKIP() << "the device executor keeps its own rows";
  }
  const std::vector<Vec2> pts = testing::UniformPoints(20000, 61);
  const double r = 3.0 / std::sqrt(double(pts.size()));
  RowOptions cells;
  cells.plan = RowOptions::Plan::kCells;
  std::vector<uint32_t> all(pts.size());
  std::iota(all.begin(), all.end(), 0);
  auto by_points = Make(pts);
  ASSERT_TRUE(by_points.ok()) << by_points.status();
  ASSERT_TRUE(
      WithinRadiusOfPoints(*by_points, all, r, true, 0, {}, cells).ok());
  EXPECT_EQ(by_points->view_with_cached_rows().adj_offsets, nullptr);
  auto by_positions = Make(pts);
  ASSERT_TRUE(by_positions.ok()) << by_positions.status();
  const std::vector<Vec2> qs = QueryPoints(pts, 20000, 62);
  auto rows = WithinRadius(*by_positions, qs, r, 0, {}, cells);
  ASSERT_TRUE(rows.ok()) << rows.status();
  EXPECT_NE(by_positions->view_with_cached_rows().adj_offsets, nullptr);
  for (size_t i = 0; i < qs.size(); i += 97) {
    std::vector<uint32_t> want;
    for (uint32_t j = 0; j < pts.size(); ++j) {
      if (CompareDistanceToRadius(qs[i], pts[j], r) <= 0) want.push_back(j);
    }
    std::vector<uint32_t> got(rows->ids.begin() + rows->offsets[i],
                              rows->ids.begin() + rows->offsets[i + 1]);
    std::sort(got.begin(), got.end());
    EXPECT_EQ(got, want) << "query " << i;
  }
}
TEST(Queries, Clustered) {
  CheckAllQueries(testing::ClusteredPoints(2000, 3), 4);
}
TEST(Queries, LatticeWithManyTies) { CheckAllQueries(testing::Lattice(30), 5); }
TEST(Queries, Duplicates) {
  CheckAllQueries(testing::WithDuplicates(400, 3, 6), 7);
}
TEST(Queries, Collinear) { CheckAllQueries(testing::Collinear(300, 8), 9); }
TEST(Queries, TinySets) {
  CheckAllQueries({}, 10);
  CheckAllQueries({{1, 1}}, 11);
  CheckAllQueries({{1, 1}, {1, 1}}, 12);
  CheckAllQueries({{1, 1}, {2, 3}}, 13);
  CheckAllQueries({{0, 0}, {1, 0}, {0, 1}}, 14);
}
TEST(Queries, ExtremeScales) {
  CheckAllQueries(testing::UniformPoints(500, 15, 1e-12), 16);
  CheckAllQueries(testing::UniformPoints(500, 17, 1e12), 18);
  CheckAllQueries(testing::UniformPoints(500, 19, 1.0, 1e12), 20);
}

TEST(Queries, AfterMotion) {
  const size_t n = 1500;
  auto t = Make(testing::UniformPoints(n, 21));
  ASSERT_TRUE(t.ok());
  std::mt19937_64 rng(22);
  std::normal_distribution<double> g(0.0, 0.01);
  for (int s = 0; s < 5; ++s) {
    std::vector<Vec2> d(n);
    for (auto& v : d) v = {g(rng), g(rng)};
    ASSERT_TRUE(t->ApplyDisplacements(DisplacementBatch::Dense(d)).ok());
  }
  const auto pts = t->Positions();
  auto all = AllNearestNeighbors(*t);
  ASSERT_TRUE(all.ok());
  for (uint32_t i = 0; i < n; ++i) {
    ASSERT_EQ(Row(*all, i)[0], BruteRank(pts, pts[i], i)[0]);
  }
  const auto qs = QueryPoints(pts, 200, 23);
  auto r = KNearest(*t, qs, 8);
  ASSERT_TRUE(r.ok());
  for (size_t i = 0; i < qs.size(); ++i) {
    auto rank = BruteRank(pts, qs[i], kNoVertex);
    rank.resize(8);
    ASSERT_EQ(Row(*r, i), rank);
  }
}

TEST(Queries, ThreadCountDoesNotChangeResults) {
  const auto pts = testing::UniformPoints(3000, 24);
  TriangulationOptions one;
  one.num_threads = 1;
  auto a = Triangulation::Create(pts, one);
  auto b = Make(pts);
  ASSERT_TRUE(a.ok() && b.ok());
  const auto qs = QueryPoints(pts, 2000, 25);
  auto ra = WithinRadius(*a, qs, 0.03, 0);
  auto rb = WithinRadius(*b, qs, 0.03, 0);
  ASSERT_TRUE(ra.ok() && rb.ok());
  EXPECT_EQ(ra->offsets, rb->offsets);
  EXPECT_EQ(ra->ids, rb->ids);
}

TEST(Queries, BadArguments) {
  auto t = Make(testing::UniformPoints(100, 26));
  ASSERT_TRUE(t.ok());
  const std::vector<Vec2> q = {{0.5, 0.5}};
  EXPECT_EQ(KNearest(*t, q, 0).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(KNearest(*t, q, -3).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(WithinRadius(*t, q, -1.0, 0).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(WithinRadius(*t, q, std::nan(""), 0).status().code(),
            absl::StatusCode::kInvalidArgument);
  auto bad = KNearest(*t, {{0.5, 0.5}, {std::nan(""), 0}}, 1);
  EXPECT_EQ(bad.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(bad.status().message().find("queries[1].x"), std::string::npos);
  const std::vector<uint32_t> ids = {3, 100};
  auto nf = KNearestOfPoints(*t, ids, 2, true);
  EXPECT_EQ(nf.status().code(), absl::StatusCode::kNotFound);
  EXPECT_NE(nf.status().message().find("ids[1] = 100"), std::string::npos);
  QueryLimits limits;
  limits.max_total_results = 10;
  EXPECT_EQ(WithinRadius(*t, q, 10.0, 0, limits).status().code(),
            absl::StatusCode::kResourceExhausted);
}

// The total limit stops the work while rows are built: a query whose
// answer would be 10^8 results is refused after about the limit's worth.
TEST(Queries, TotalLimitStopsTheWork) {
  const auto pts = testing::UniformPoints(10000, 31);
  auto t = Make(pts);
  ASSERT_TRUE(t.ok());
  std::vector<uint32_t> ids(pts.size());
  std::iota(ids.begin(), ids.end(), 0u);
  QueryLimits limits;
  limits.max_total_results = 50000;
  for (auto plan : {RowOptions::Plan::kGraph, RowOptions::Plan::kCells}) {
    for (bool sets : {false, true}) {  // set-only rows have their own scan
      RowOptions rows;
      rows.plan = plan;
      rows.closest_first = !sets;
      rows.distances = !sets;
      const auto t0 = std::chrono::steady_clock::now();
      auto r = WithinRadiusOfPoints(*t, ids, 10.0, false, 0, limits, rows);
      const double s =
          std::chrono::duration<double>(std::chrono::steady_clock::now() - t0)
              .count();
      EXPECT_EQ(r.status().code(), absl::StatusCode::kResourceExhausted);
      EXPECT_NE(r.status().message().find("50000"), std::string::npos);
      // The whole answer (10^8 results) takes tens of seconds; the refusal
      // builds at most a few rows of 10^4.
      EXPECT_LT(s, 2.0);
    }
  }
  // Exactly at the limit is allowed.
  limits.max_total_results = 10000;
  auto ok = WithinRadiusOfPoints(*t, std::vector<uint32_t>{1}, 10.0, false, 0,
                                 limits);
  ASSERT_TRUE(ok.ok()) << ok.status();
  EXPECT_EQ(ok->ids.size(), 10000u);
}

// QueryLimits::admit is asked, one call at a time, for growing multiples of
// kAdmitStep covering every result kept; its refusal stops the query and is
// what the query returns. A k-NN answer (k per query) is admitted whole
// before it is built.
void ExpectSameAnswer(const NeighborLists& a, const NeighborLists& b,
                      const char* what) {
  EXPECT_EQ(a.offsets, b.offsets) << what;
  EXPECT_EQ(a.ids, b.ids) << what;
  EXPECT_EQ(a.distances, b.distances) << what;
  EXPECT_EQ(a.truncated, b.truncated) << what;
}

// The limit is exact for answers of many rows, whose results the threads
// count in batches (QueryLimits::kCountBatch): an answer of exactly the
// limit is given, one result more is refused, on every plan and row form.
TEST(Queries, TotalLimitIsExactOverManyRows) {
  const auto pts = testing::UniformPoints(20000, 41);
  auto t = Make(pts);
  ASSERT_TRUE(t.ok());
  std::vector<uint32_t> ids(pts.size());
  std::iota(ids.begin(), ids.end(), 0u);
  const std::vector<Vec2> qs = QueryPoints(pts, 15000, 42);
  for (auto plan : {RowOptions::Plan::kGraph, RowOptions::Plan::kCells}) {
    for (bool sets : {false, true}) {
      RowOptions rows;
      rows.plan = plan;
      rows.closest_first = !sets;
      rows.distances = !sets;
      for (bool of_points : {false, true}) {
        auto ask = [&](QueryLimits limits) {
          return of_points ? WithinRadiusOfPoints(*t, ids, 0.012, false, 0,
                                                  limits, rows)
                           : WithinRadius(*t, qs, 0.012, 0, limits, rows);
        };
        auto whole = ask({});
        ASSERT_TRUE(whole.ok()) << whole.status();
        const uint64_t total = whole->ids.size();
        ASSERT_GT(total, 50 * QueryLimits::kCountBatch);
        QueryLimits limits;
        limits.max_total_results = total;
        auto at = ask(limits);
        ASSERT_TRUE(at.ok()) << at.status();
        ExpectSameAnswer(*at, *whole, "at the limit");
        limits.max_total_results = total - 1;
        EXPECT_EQ(ask(limits).status().code(),
                  absl::StatusCode::kResourceExhausted)
            << "plan " << static_cast<int>(plan) << " sets " << sets
            << " of points " << of_points;
      }
    }
  }
}

// Rows cut at max_results count what they keep, not the points they meet
// on the way: an answer of exactly the limit is given though each disk
// holds ~300 points (they once stopped rows near the end as over the
// limit), and one result more is refused.
TEST(Queries, CutRowsCountWhatTheyKeep) {
  const auto pts = testing::UniformPoints(10000, 43);
  auto t = Make(pts);
  ASSERT_TRUE(t.ok());
  std::vector<uint32_t> ids(3000);
  std::iota(ids.begin(), ids.end(), 0u);
  for (auto plan : {RowOptions::Plan::kGraph, RowOptions::Plan::kCells}) {
    for (bool sorted : {true, false}) {
      RowOptions rows;
      rows.plan = plan;
      rows.closest_first = sorted;
      auto whole = WithinRadiusOfPoints(*t, ids, 0.1, true, 4, {}, rows);
      ASSERT_TRUE(whole.ok()) << whole.status();
      ASSERT_EQ(whole->ids.size(), 4 * ids.size());  // every row cut at 4
      QueryLimits limits;
      limits.max_total_results = whole->ids.size();
      auto at = WithinRadiusOfPoints(*t, ids, 0.1, true, 4, limits, rows);
      ASSERT_TRUE(at.ok()) << at.status();
      ExpectSameAnswer(*at, *whole, "cut rows at the limit");
      limits.max_total_results = whole->ids.size() - 1;
      EXPECT_EQ(WithinRadiusOfPoints(*t, ids, 0.1, true, 4, limits, rows)
                    .status()
                    .code(),
                absl::StatusCode::kResourceExhausted);
    }
  }
}

// RowOptions::recycle: an answer built in an earlier answer's memory is the
// answer built fresh, whatever the earlier one held (another kind, size,
// with or without distances); the host executors take its memory.
TEST(Queries, RecycledAnswersAreTheSameAnswers) {
  for (const bool clustered : {false, true}) {
    const auto pts = clustered ? testing::ClusteredPoints(12000, 7)
                               : testing::UniformPoints(12000, 7);
    auto t = Make(pts);
    ASSERT_TRUE(t.ok());
    std::vector<uint32_t> ids(pts.size());
    std::iota(ids.begin(), ids.end(), 0u);
    const std::vector<Vec2> qs = QueryPoints(pts, 2000, 8);
    const double r = clustered ? 0.004 : 0.02;
    RowOptions sets;
    sets.distances = false;
    sets.closest_first = false;
    // Each query, built fresh.
    using Ask = std::function<absl::StatusOr<NeighborLists>(RowOptions)>;
    const std::vector<std::pair<const char*, Ask>> asks = {
        {"all nearest",
         [&](RowOptions o) { return AllNearestNeighbors(*t, o); }},
        {"knn8 of points",
         [&](RowOptions o) {
           return KNearestOfPoints(*t, ids, 8, true, {}, o);
         }},
        {"knn5 of positions",
         [&](RowOptions o) { return KNearest(*t, qs, 5, {}, o); }},
        {"radius of points",
         [&](RowOptions o) {
           return WithinRadiusOfPoints(*t, ids, r, true, 0, {}, o);
         }},
        {"radius sets of points",
         [&](RowOptions o) {
           sets.recycle = o.recycle;
           return WithinRadiusOfPoints(*t, ids, r, false, 0, {}, sets);
         }},
        {"radius of positions, cut at 3",
         [&](RowOptions o) { return WithinRadius(*t, qs, r, 3, {}, o); }},
    };
    std::vector<NeighborLists> fresh;
    for (const auto& [what, ask] : asks) {
      auto a = ask({});
      ASSERT_TRUE(a.ok()) << what << ": " << a.status();
      fresh.push_back(*std::move(a));
    }
    const bool host = t->device_executor() == nullptr;
    // Every query in the memory of every answer (itself included).
    for (size_t i = 0; i < asks.size(); ++i) {
      for (size_t j = 0; j < asks.size(); ++j) {
        // (The device executor builds its answers its own way: once.)
        if (!host && j != i) continue;
        NeighborLists old = fresh[j];
        const uint32_t* old_ids = old.ids.data();
        const bool fits = old.ids.capacity() >= fresh[i].ids.size();
        RowOptions o;
        o.recycle = &old;
        auto a = asks[i].second(o);
        ASSERT_TRUE(a.ok()) << asks[i].first << ": " << a.status();
        ExpectSameAnswer(*a, fresh[i], asks[i].first);
        if (host) {
          EXPECT_TRUE(old.ids.empty())
              << asks[i].first << " in " << asks[j].first;
          if (fits) {
            EXPECT_EQ(a->ids.data(), old_ids)
                << asks[i].first << " in " << asks[j].first;
          }
        }
      }
    }
  }
}

TEST(Queries, AdmitGrowsWithTheAnswer) {
  const auto pts = testing::UniformPoints(10000, 33);
  auto t = Make(pts);
  ASSERT_TRUE(t.ok());
  std::vector<uint32_t> ids(pts.size());
  std::iota(ids.begin(), ids.end(), 0u);
  const uint64_t step = QueryLimits::kAdmitStep;
  for (bool knn : {false, true}) {
    std::vector<uint64_t> grants;
    std::atomic<int> inside{0};
    bool overlapped = false;
    QueryLimits limits;
    limits.admit = [&](uint64_t results) {
      overlapped |= inside.fetch_add(1) != 0;
      std::this_thread::sleep_for(std::chrono::microseconds(200));
      grants.push_back(results);
      inside.fetch_sub(1);
      return absl::OkStatus();
    };
    // ~126 results per row (radius) or 64: 0.6-1.3M in all.
    auto r = knn ? KNearestOfPoints(*t, ids, 64, false, limits)
                 : WithinRadiusOfPoints(*t, ids, 0.063, false, 0, limits);
    ASSERT_TRUE(r.ok()) << r.status();
    const uint64_t total = r->ids.size();
    ASSERT_GT(total, 2 * step);
    ASSERT_FALSE(grants.empty());
    EXPECT_FALSE(overlapped);
    for (size_t i = 0; i < grants.size(); ++i) {
      EXPECT_EQ(grants[i] % step, 0u);
      if (i > 0) {
        EXPECT_GT(grants[i], grants[i - 1]);
      }
    }
    EXPECT_GE(grants.back(), total);
    // (Besides the rounding: what other threads had not counted yet.)
    EXPECT_LT(grants.back(), total + step +
                                 QueryLimits::kCountBatch *
                                     static_cast<uint64_t>(t->num_threads()));
    if (knn) {
      EXPECT_EQ(grants.size(), 1u);
      EXPECT_EQ(total, ids.size() * 64);
    }
    // Refused at the second grant (k-NN, or a batch that ran as one block,
    // as on a GPU: the first, the only one): the query stops with that
    // status.
    const int refuse_at =
        knn ? 1 : static_cast<int>(std::min<size_t>(2, grants.size()));
    int calls = 0;
    limits.admit = [&](uint64_t) {
      return ++calls == refuse_at ? absl::ResourceExhaustedError("no room")
                                  : absl::OkStatus();
    };
    auto refused = knn ? KNearestOfPoints(*t, ids, 64, false, limits)
                       : WithinRadiusOfPoints(*t, ids, 0.063, false, 0, limits);
    EXPECT_EQ(refused.status().code(), absl::StatusCode::kResourceExhausted);
    EXPECT_EQ(refused.status().message(), "no room");
    EXPECT_EQ(calls, refuse_at);
  }
}

// A cut radius row is the closest max_results points even when the disk
// holds far more sites than that (computed by the bounded k-NN expansion).
TEST(Queries, CutRadiusRowsOfHugeDisks) {
  auto pts = testing::UniformPoints(6000, 32);
  for (int i = 0; i < 50; ++i) pts.push_back(pts[i]);  // duplicates too
  auto t = Make(pts);
  ASSERT_TRUE(t.ok());
  const auto qs = QueryPoints(pts, 40, 33);
  for (bool closest_first : {true, false}) {
    RowOptions rows;
    rows.closest_first = closest_first;
    auto r = WithinRadius(*t, qs, 0.7, 7, {}, rows);
    ASSERT_TRUE(r.ok());
    for (size_t i = 0; i < qs.size(); ++i) {
      std::vector<uint32_t> want;
      for (uint32_t id : BruteRank(pts, qs[i], kNoVertex)) {
        if (CompareDistanceToRadius(qs[i], pts[id], 0.7) > 0) break;
        want.push_back(id);
      }
      const bool cut = want.size() > 7;
      if (cut) want.resize(7);
      auto got = Row(*r, i);
      if (!closest_first) std::sort(got.begin(), got.end());
      if (!closest_first) std::sort(want.begin(), want.end());
      EXPECT_EQ(got, want) << "query " << i;
      EXPECT_EQ(r->truncated[i] != 0, cut) << "query " << i;
    }
  }
}

// Many coincident points: each query emits the first ids of the big site
// instead of walking and sorting all of them (quadratic before: 200K
// identical points, k = 2, all points ran for minutes).
TEST(Queries, HugeSiteOfCoincidentPoints) {
  std::vector<Vec2> pts(30000, Vec2{0.25, 0.5});
  for (int i = 0; i < 10; ++i) pts.push_back({0.1 * i, 0.9 - 0.05 * i});
  auto t = Make(pts);
  ASSERT_TRUE(t.ok());
  std::vector<uint32_t> ids(pts.size());
  std::iota(ids.begin(), ids.end(), 0u);
  auto r = KNearestOfPoints(*t, ids, 2, true);
  ASSERT_TRUE(r.ok());
  EXPECT_EQ(Row(*r, 0), (std::vector<uint32_t>{1, 2}));
  EXPECT_EQ(Row(*r, 1), (std::vector<uint32_t>{0, 2}));
  EXPECT_EQ(Row(*r, 29999), (std::vector<uint32_t>{0, 1}));
  for (uint32_t i : {30000u, 30004u, 30009u}) {
    const auto rank = BruteRank(pts, pts[i], i);
    EXPECT_EQ(Row(*r, i),
              std::vector<uint32_t>(rank.begin(), rank.begin() + 2));
  }
}

// A cancelled or expired token stops a query with CANCELLED or
// DEADLINE_EXCEEDED; a token that fires while the query runs stops it
// promptly (the time from firing to return is measured).
TEST(Queries, CancellationStopsTheWork) {
  const auto pts = testing::UniformPoints(20000, 34);
  auto t = Make(pts);
  ASSERT_TRUE(t.ok());
  std::vector<uint32_t> ids(pts.size());
  std::iota(ids.begin(), ids.end(), 0u);
  {
    CancelToken cancelled([] { return true; });
    QueryLimits limits;
    limits.cancel = &cancelled;
    EXPECT_EQ(KNearestOfPoints(*t, ids, 8, true, limits).status().code(),
              absl::StatusCode::kCancelled);
    CancelToken expired(nullptr, std::chrono::steady_clock::now());
    limits.cancel = &expired;
    EXPECT_EQ(
        WithinRadiusOfPoints(*t, ids, 0.05, true, 0, limits).status().code(),
        absl::StatusCode::kDeadlineExceeded);
  }
  // The whole answer (20000 rows of ~20000) takes far longer than the
  // 100 ms after which the token fires; both ways of scanning a disk stop.
  for (auto plan : {RowOptions::Plan::kGraph, RowOptions::Plan::kCells}) {
    RowOptions rows;
    rows.plan = plan;
    std::atomic<bool> flag{false};
    CancelToken token([&] { return flag.load(); });
    QueryLimits limits;
    limits.cancel = &token;
    std::chrono::steady_clock::time_point fired;
    std::thread canceller([&] {
      std::this_thread::sleep_for(std::chrono::milliseconds(100));
      fired = std::chrono::steady_clock::now();
      flag = true;
    });
    auto r = WithinRadiusOfPoints(*t, ids, 10.0, true, 0, limits, rows);
    const auto done = std::chrono::steady_clock::now();
    canceller.join();
    EXPECT_EQ(r.status().code(), absl::StatusCode::kCancelled);
    const double stop_ms =
        std::chrono::duration<double, std::milli>(done - fired).count();
    std::printf("query stopped %.1f ms after cancellation\n", stop_ms);
    // ThreadSanitizer (which runs this test for the stop word's hand-off)
    // slows the scan 5-15x, AddressSanitizer 2-3x: a CI run under TSan
    // stopped 75.6 ms after the token fired. Only the normal build holds
    // it to 50 ms (KINETRI_SLOW_MACHINE relaxes that 10x).
    const double limit_ms = testing::BySanitizer(50.0, 150.0, 500.0);
    EXPECT_LT(stop_ms,
              limit_ms * (std::getenv("KINETRI_SLOW_MACHINE") ? 10 : 1));
  }
}

// A batch asked in blocks (as the server does) with the batch size as a
// hint plans once for the batch: the blocks share the step's cached cell
// index, answer exactly as the graph walk, and a step replaces the index
// (a stale one would answer for the old positions).
TEST(Queries, BlocksOfABatchShareTheStepsCellIndex) {
  const size_t n = 4000;
  auto t = Make(testing::UniformPoints(n, 50));
  ASSERT_TRUE(t.ok());
  std::vector<uint32_t> ids(n);
  std::iota(ids.begin(), ids.end(), 0u);
  std::mt19937_64 rng(51);
  std::normal_distribution<double> g(0.0, 0.003);
  const double r = std::sqrt(20.0 / (3.14159 * n));
  for (int step = 0; step < 3; ++step) {
    RowOptions graph;
    graph.plan = RowOptions::Plan::kGraph;
    auto want = WithinRadiusOfPoints(*t, ids, r, true, 0, {}, graph);
    ASSERT_TRUE(want.ok());
    RowOptions hinted;
    hinted.batch_queries = n;
    const size_t block = 100;  // far below n / 8: alone, they would walk
    for (size_t first = 0; first < n; first += block) {
      auto got = WithinRadiusOfPoints(
          *t, absl::MakeConstSpan(ids).subspan(first, block), r, true, 0, {},
          hinted);
      ASSERT_TRUE(got.ok());
      for (size_t i = 0; i < block; ++i) {
        ASSERT_EQ(Row(*got, i), Row(*want, first + i))
            << "step " << step << " point " << first + i;
      }
    }
    std::vector<Vec2> d(n);
    for (auto& v : d) v = {g(rng), g(rng)};
    ASSERT_TRUE(t->ApplyDisplacements(DisplacementBatch::Dense(d)).ok());
  }
}

// The executor under test answers exactly as the host's region executor
// (ids, distances bit for bit, truncation flags) on the same points, before
// and after steps: a device executor refreshes its copy of the query view
// with every step, never answers from a stale one.
TEST(Queries, SameAnswersAsTheHostExecutorAcrossSteps) {
  auto pts = testing::ClusteredPoints(3000, 40);
  for (int i = 0; i < 30; ++i) pts.push_back(pts[7 * i]);  // coincident
  auto t = Make(pts);
  auto host = Triangulation::Create(pts);
  ASSERT_TRUE(t.ok() && host.ok());
  std::vector<uint32_t> ids(pts.size());
  std::iota(ids.begin(), ids.end(), 0u);
  std::mt19937_64 rng(41);
  std::normal_distribution<double> g(0.0, 0.002);
  for (int step = 0; step < 3; ++step) {
    const auto qs = QueryPoints(host->Positions(), 500, 42 + step);
    auto same = [&](const absl::StatusOr<NeighborLists>& a,
                    const absl::StatusOr<NeighborLists>& b, const char* what) {
      ASSERT_TRUE(a.ok()) << a.status();
      ASSERT_TRUE(b.ok()) << b.status();
      EXPECT_EQ(a->offsets, b->offsets) << what << " step " << step;
      EXPECT_EQ(a->ids, b->ids) << what << " step " << step;
      EXPECT_EQ(a->distances, b->distances) << what << " step " << step;
      EXPECT_EQ(a->truncated, b->truncated) << what << " step " << step;
    };
    same(AllNearestNeighbors(*t), AllNearestNeighbors(*host), "all-NN");
    same(KNearest(*t, qs, 9), KNearest(*host, qs, 9), "kNN");
    same(KNearestOfPoints(*t, ids, 5, true),
         KNearestOfPoints(*host, ids, 5, true), "kNN of points");
    same(WithinRadius(*t, qs, 0.01, 0), WithinRadius(*host, qs, 0.01, 0),
         "radius");
    same(WithinRadiusOfPoints(*t, ids, 0.02, true, 6),
         WithinRadiusOfPoints(*host, ids, 0.02, true, 6), "cut radius");
    std::vector<Vec2> d(pts.size());
    for (auto& v : d) v = {g(rng), g(rng)};
    ASSERT_TRUE(t->ApplyDisplacements(DisplacementBatch::Dense(d)).ok());
    ASSERT_TRUE(host->ApplyDisplacements(DisplacementBatch::Dense(d)).ok());
  }
#if defined(KINETRI_TEST_DEVICE) || defined(KINETRI_TEST_CUDA)
  // The answers came from the device: it holds the query view.
  ASSERT_NE(t->device_executor(), nullptr);
  EXPECT_GT(t->device_bytes(), 0u);
#endif
}

}  // namespace
}  // namespace kinetri::core
