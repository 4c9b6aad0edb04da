// The mark-free host+device searches (core/query_search.h) against brute
// force: the code the CUDA kernels run, tested on the CPU.
#include "core/query_search.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <vector>

#include "core/queries.h"
#include "tests/core/test_util.h"

namespace kinetri::core {
namespace {

using testing::BruteRank;
using testing::QueryPoints;

// Disks SmallDiskSearch took whole, and ones it left to RadiusSearch.
int small_disks = 0, large_disks = 0;

// External ids of the points of the emitted sites, ascending; fails if a
// site is emitted twice.
std::vector<uint32_t> RadiusIds(const TriangulationView& v, const Vec2& q,
                                double r, uint32_t root, uint32_t self) {
  std::vector<uint32_t> sites, ids;
  const uint32_t count = RadiusSearch(v, q, r, root, [&](uint32_t s) {
    sites.push_back(s);
    for (uint32_t p = s; p != kNoVertex; p = v.dup_next[p]) {
      if (v.ext_of_int[p] != self) ids.push_back(v.ext_of_int[p]);
    }
  });
  EXPECT_EQ(count, sites.size());
  std::sort(sites.begin(), sites.end());
  EXPECT_TRUE(std::adjacent_find(sites.begin(), sites.end()) == sites.end())
      << "a site was emitted twice";
  EXPECT_EQ(CountPointsWithin(v, q, r, root, self), ids.size());
  // The breadth-first search of small disks: the same sites where the disk
  // fits, none where it does not; DiskSearch either way.
  std::vector<uint32_t> small;
  uint32_t small_count = 0;
  auto collect = [&](uint32_t s) { small.push_back(s); };
  if (SmallDiskSearch(v, q, r, root, collect, &small_count)) {
    ++small_disks;
    EXPECT_LE(sites.size(), kSmallDiskSites);
    EXPECT_EQ(small_count, small.size());
    std::sort(small.begin(), small.end());
    EXPECT_EQ(small, sites);
  } else {
    ++large_disks;
    EXPECT_TRUE(small.empty());
  }
  small.clear();
  EXPECT_EQ(DiskSearch(v, q, r, root, collect), sites.size());
  std::sort(small.begin(), small.end());
  EXPECT_EQ(small, sites);
  std::sort(ids.begin(), ids.end());
  return ids;
}

std::vector<uint32_t> KnnIds(const TriangulationView& v, const Vec2& q,
                             uint32_t k, uint32_t root, uint32_t self) {
  std::vector<KnnEntry> buf(k);
  const uint32_t got = KNearestSearch(v, q, k, root, self, buf.data());
  std::vector<uint32_t> ids;
  for (uint32_t i = 0; i < got; ++i) ids.push_back(v.ext_of_int[buf[i].point]);
  return ids;
}

void CheckSearches(const std::vector<Vec2>& pts, uint64_t seed) {
  auto t = Triangulation::Create(pts);
  ASSERT_TRUE(t.ok()) << t.status();
  const uint32_t n = pts.size();
  if (n == 0) return;
  const TriangulationView v = t->query_view();
  // The same view without the member rows of coincident points: the
  // searches then walk each site's chain (its own code path).
  TriangulationView chains = v;
  chains.site_member_offsets = nullptr;
  chains.site_members = nullptr;
  double typical = 0.0;
  for (size_t i = 1; i < std::min<size_t>(n, 50); ++i) {
    typical =
        std::max(typical, std::hypot(pts[i].x - pts[0].x, pts[i].y - pts[0].y));
  }
  const auto qs = QueryPoints(pts, 200, seed);
  for (size_t i = 0; i < qs.size(); ++i) {
    const uint32_t root = WalkToNearestSite(v, qs[i], v.sites[0]);
    const auto rank = BruteRank(pts, qs[i], kNoVertex);
    for (double r : {0.0, typical * 0.05, typical * 0.2, typical}) {
      std::vector<uint32_t> want;
      for (uint32_t id : rank) {
        if (CompareDistanceToRadius(qs[i], pts[id], r) <= 0) want.push_back(id);
      }
      std::sort(want.begin(), want.end());
      ASSERT_EQ(RadiusIds(v, qs[i], r, root, kNoVertex), want)
          << "radius " << r << " query " << i;
    }
    for (uint32_t k : {1u, 4u, 17u, 32u, 40u, n + 3}) {
      std::vector<uint32_t> want(rank.begin(),
                                 rank.begin() + std::min<size_t>(k, n));
      ASSERT_EQ(KnnIds(v, qs[i], k, root, kNoVertex), want)
          << "k=" << k << " query " << i;
      ASSERT_EQ(KnnIds(chains, qs[i], k, root, kNoVertex), want)
          << "k=" << k << " query " << i << " (chains)";
    }
  }
  // Queries around the points themselves, excluding them.
  for (uint32_t id = 0; id < std::min<uint32_t>(n, 150); ++id) {
    const uint32_t in = v.int_of_ext[id];
    const uint32_t root = v.rep[in];
    const auto rank = BruteRank(pts, pts[id], id);
    for (uint32_t k : {1u, 8u, n + 1}) {
      std::vector<uint32_t> want(
          rank.begin(), rank.begin() + std::min<size_t>(k, rank.size()));
      ASSERT_EQ(KnnIds(v, pts[id], k, root, id), want)
          << "k=" << k << " point " << id;
      ASSERT_EQ(KnnIds(chains, pts[id], k, root, id), want)
          << "k=" << k << " point " << id << " (chains)";
    }
    std::vector<uint32_t> want;
    for (uint32_t j : rank) {
      if (CompareDistanceToRadius(pts[id], pts[j], typical * 0.2) <= 0)
        want.push_back(j);
    }
    std::sort(want.begin(), want.end());
    ASSERT_EQ(RadiusIds(v, pts[id], typical * 0.2, root, id), want);
  }
}

TEST(QuerySearch, Uniform) {
  small_disks = large_disks = 0;
  CheckSearches(testing::UniformPoints(1500, 3), 4);
  // Both ways of searching a disk were taken.
  EXPECT_GT(small_disks, 100);
  EXPECT_GT(large_disks, 100);
}
TEST(QuerySearch, Clustered) {
  CheckSearches(testing::ClusteredPoints(1500, 5), 6);
}
TEST(QuerySearch, LatticeWithManyTies) {
  CheckSearches(testing::Lattice(25), 7);
}
TEST(QuerySearch, Duplicates) {
  CheckSearches(testing::WithDuplicates(400, 3, 8), 9);
}
TEST(QuerySearch, Collinear) { CheckSearches(testing::Collinear(200, 10), 11); }
TEST(QuerySearch, TinySets) {
  CheckSearches({{0.5, 0.5}}, 12);
  CheckSearches({{0, 0}, {1, 0}}, 13);
  CheckSearches({{0, 0}, {1, 0}, {0, 1}}, 14);
  CheckSearches({{0, 0}, {0, 0}, {1, 1}}, 15);
}
TEST(QuerySearch, ExtremeScales) {
  CheckSearches(testing::UniformPoints(500, 16, 1e-12, 3e-12), 17);
  CheckSearches(testing::UniformPoints(500, 18, 1e12, -5e11), 19);
}
TEST(QuerySearch, AfterMotion) {
  auto pts = testing::UniformPoints(1000, 20);
  auto t = Triangulation::Create(pts);
  ASSERT_TRUE(t.ok());
  std::mt19937_64 rng(21);
  std::normal_distribution<double> g(0, 0.01);
  std::vector<Vec2> d(pts.size());
  for (size_t i = 0; i < pts.size(); ++i) {
    d[i] = {g(rng), g(rng)};
    pts[i] = {pts[i].x + d[i].x, pts[i].y + d[i].y};
  }
  ASSERT_TRUE(t->ApplyDisplacements(DisplacementBatch::Dense(d)).ok());
  // The neighbour rows must follow the step (built again after a change).
  const TriangulationView v = t->query_view();
  for (uint32_t id = 0; id < 200; ++id) {
    const auto rank = BruteRank(pts, pts[id], id);
    const uint32_t root = v.rep[v.int_of_ext[id]];
    std::vector<uint32_t> want(rank.begin(), rank.begin() + 8);
    ASSERT_EQ(KnnIds(v, pts[id], 8, root, id), want);
  }
}

}  // namespace
}  // namespace kinetri::core
