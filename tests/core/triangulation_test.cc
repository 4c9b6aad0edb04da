// Initial construction: Validate() and edge set == CGAL on every input kind.
#include "core/triangulation.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <random>

#include "core/cell_index.h"
#include "core/hint_grid.h"
#include "core/queries.h"
#include "tests/core/test_util.h"

namespace kinetri::core {
namespace {

using testing::CgalDelaunayEdges;
using testing::EdgesAsPositions;

void ExpectDelaunay(const std::vector<Vec2>& pts) {
  auto t = Triangulation::Create(pts);
  ASSERT_TRUE(t.ok()) << t.status();
  ASSERT_TRUE(t->Validate().ok()) << t->Validate();
  EXPECT_EQ(EdgesAsPositions(*t), CgalDelaunayEdges(pts));
  EXPECT_EQ(t->size(), pts.size());
  for (uint32_t i = 0; i < pts.size(); ++i) {
    ASSERT_EQ(t->Position(i), pts[i]);
  }
}

TEST(Create, TinySets) {
  ExpectDelaunay({});
  ExpectDelaunay({{1, 2}});
  ExpectDelaunay({{1, 2}, {3, 4}});
  ExpectDelaunay({{1, 2}, {1, 2}});
  ExpectDelaunay({{0, 0}, {1, 0}, {0, 1}});
  ExpectDelaunay({{0, 0}, {1, 0}, {2, 0}});
  ExpectDelaunay({{0, 0}, {0, 0}, {0, 0}});
  ExpectDelaunay({{0, 0}, {1, 0}, {0, 1}, {1, 1}});  // cocircular square
}

TEST(Create, RandomAndClustered) {
  ExpectDelaunay(testing::UniformPoints(5000, 1));
  ExpectDelaunay(testing::ClusteredPoints(5000, 2));
}

TEST(Create, LatticeMatchesCgalPerturbation) {
  ExpectDelaunay(testing::Lattice(40));
  ExpectDelaunay(testing::Lattice(17, 0.1));
}

TEST(Create, CollinearAndDuplicates) {
  ExpectDelaunay(testing::Collinear(500, 3));
  ExpectDelaunay(testing::WithDuplicates(1000, 3, 4));
  auto pts = testing::Collinear(50, 5);
  pts.push_back({0.5, 0.25});  // one point off the line makes it planar
  ExpectDelaunay(pts);
}

TEST(Create, ExtremeScales) {
  ExpectDelaunay(testing::UniformPoints(2000, 6, 1e-12));
  ExpectDelaunay(testing::UniformPoints(2000, 7, 1e12));
  ExpectDelaunay(testing::UniformPoints(2000, 8, 1.0, 1e12));
  ExpectDelaunay(testing::UniformPoints(2000, 9, 1e-3, 1e6));
  auto lat = testing::Lattice(20, 1e-12);
  for (auto& p : lat) p = {p.x + 1.0, p.y - 3.0};
  ExpectDelaunay(lat);
}

TEST(Create, RejectsBadCoordinates) {
  const double nan = std::nan("");
  auto t = Triangulation::Create({{0, 0}, {nan, 1}});
  ASSERT_FALSE(t.ok());
  EXPECT_EQ(t.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(t.status().message().find("points[1].x"), std::string::npos)
      << t.status();
  t = Triangulation::Create({{0, 0}, {1, HUGE_VAL}});
  EXPECT_EQ(t.status().code(), absl::StatusCode::kInvalidArgument);
  t = Triangulation::Create({{0, 0}, {1e-200, 1}});
  EXPECT_EQ(t.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(t.status().message().find("exact range"), std::string::npos);
}

TEST(Create, RejectsBadPolicies) {
  const auto pts = testing::UniformPoints(50, 3);
  std::vector<TriangulationOptions> bad(8);
  bad[0].round.max_passes = 0;
  bad[1].round.max_halvings = 31;
  bad[2].round.rebuild_fraction = std::nan("");
  bad[3].round.sparse_fraction = 1.5;
  bad[4].round.max_subdivision_depth = 17;
  bad[5].region.region_triangles = 8;
  bad[6].region.max_passes = 0;
  bad[7].num_threads = -1;
  for (size_t i = 0; i < bad.size(); ++i) {
    auto t = Triangulation::Create(pts, bad[i]);
    ASSERT_FALSE(t.ok()) << i;
    EXPECT_EQ(t.status().code(), absl::StatusCode::kInvalidArgument) << i;
  }
}

// The round executor's pass limit is an option: before RoundStepPolicy a
// hard-coded 64 capped it and made max_passes dead at its default.
TEST(RoundPolicy, MaxPassesIsHonoured) {
  const size_t n = 600;
  const auto pts = testing::UniformPoints(n, 21);
  std::mt19937_64 rng(5);
  std::normal_distribution<double> g(0.0, 0.6 / std::sqrt(double(n)));
  std::vector<Vec2> deltas(n);
  for (auto& d : deltas) d = {g(rng), g(rng)};
  std::vector<Vec2> moved(n);
  for (size_t i = 0; i < n; ++i) {
    moved[i] = {pts[i].x + deltas[i].x, pts[i].y + deltas[i].y};
  }
  for (int passes : {1, 200}) {
    TriangulationOptions opt;
    opt.executor = Executor::kRounds;
    opt.round.rebuild_fraction = 1.0;
    opt.round.reinsert_fraction = 1.0;
    opt.round.max_passes = passes;
    auto t = Triangulation::Create(pts, opt);
    ASSERT_TRUE(t.ok());
    auto r = t->ApplyDisplacements(DisplacementBatch::Dense(deltas));
    ASSERT_TRUE(r.ok()) << r.status();
    ASSERT_TRUE(t->Validate().ok());
    EXPECT_EQ(EdgesAsPositions(*t), CgalDelaunayEdges(moved));
    if (passes == 1) {
      EXPECT_EQ(r->path, UpdatePath::kRebuilt);
      EXPECT_NE(r->fallback_reason.find("after 1 passes"), std::string::npos)
          << r->fallback_reason;
    } else {
      EXPECT_NE(r->path, UpdatePath::kRebuilt) << r->fallback_reason;
      EXPECT_GT(r->failed_attempts + r->local_halvings, 0u);
    }
  }
}

// The step's cell indexes: two radii and one k-nearest index are kept,
// the least recently asked for radius goes, and a step forgets them all.
TEST(CachedCellIndex, TwoRadiiAndOneNearestPerStep) {
  auto t = Triangulation::Create(testing::UniformPoints(2000, 3));
  ASSERT_TRUE(t.ok()) << t.status();
  using Use = Triangulation::CellIndexUse;
  int made = 0;
  auto get = [&](Use use, double key) {
    t->CachedCellIndex(use, key, [&]() -> std::shared_ptr<const CellIndex> {
      ++made;
      return nullptr;  // a kept "walk the graph" decision
    });
  };
  get(Use::kRadius, 0.1);
  get(Use::kRadius, 0.2);
  get(Use::kNearest, 0.0);
  EXPECT_EQ(made, 3);
  get(Use::kRadius, 0.2);  // kept, all three
  get(Use::kRadius, 0.1);  // now the most recently asked for radius
  get(Use::kNearest, 0.0);
  EXPECT_EQ(made, 3);
  EXPECT_FALSE(t->HasCachedCellIndex(Use::kNearest, 0.1));
  get(Use::kRadius, 0.3);  // replaces 0.2, the least recently asked for
  EXPECT_EQ(made, 4);
  EXPECT_FALSE(t->HasCachedCellIndex(Use::kRadius, 0.2));
  EXPECT_TRUE(t->HasCachedCellIndex(Use::kRadius, 0.1));
  EXPECT_TRUE(t->HasCachedCellIndex(Use::kRadius, 0.3));
  EXPECT_TRUE(t->HasCachedCellIndex(Use::kNearest, 0.0));
  std::vector<Vec2> none(t->size(), Vec2{0.0, 0.0});
  ASSERT_TRUE(t->ApplyDisplacements(DisplacementBatch::Dense(none)).ok());
  std::vector<Vec2> small(t->size(), Vec2{1e-6, 0.0});
  ASSERT_TRUE(t->ApplyDisplacements(DisplacementBatch::Dense(small)).ok());
  EXPECT_FALSE(t->HasCachedCellIndex(Use::kRadius, 0.1));
  EXPECT_FALSE(t->HasCachedCellIndex(Use::kRadius, 0.3));
  EXPECT_FALSE(t->HasCachedCellIndex(Use::kNearest, 0.0));
}

// The region executor keeps the apexes across each edge from step to step,
// through the re-insertion of held vertices that the driver does between
// steps (it names every triangle it writes): the dense step after one that
// re-inserted reads them. Validate() checks the kept entries after every
// step, and the mesh is the one a triangulation that never keeps them
// makes.
TEST(RegionSteps, KeepTheApexesAcrossThroughReinsertion) {
  constexpr size_t kN = 3000;
  const std::vector<Vec2> pts = testing::UniformPoints(kN, 21);
  TriangulationOptions keep, fill;
  keep.region.keep_across_flips = 1;  // whatever the step flips
  fill.region.keep_across_flips = 0;
  auto a = Triangulation::Create(pts, keep);
  auto b = Triangulation::Create(pts, fill);
  ASSERT_TRUE(a.ok() && b.ok());
  std::mt19937_64 rng(21);
  const double sigma = 0.15 / std::sqrt(double(kN));
  int kept = 0, kept_after_reinsertion = 0;
  bool reinserted = false;
  for (int s = 0; s < 12; ++s) {
    const DisplacementBatch d = testing::Brownian(kN, sigma, rng);
    auto ra = a->ApplyDisplacements(d);
    auto rb = b->ApplyDisplacements(d);
    ASSERT_TRUE(ra.ok()) << ra.status();
    ASSERT_TRUE(rb.ok()) << rb.status();
    ASSERT_TRUE(a->Validate().ok()) << "step " << s << ": " << a->Validate();
    ASSERT_EQ(a->Edges(), b->Edges()) << "step " << s;
    EXPECT_FALSE(rb->across_kept);
    if (ra->across_kept) {
      ++kept;
      kept_after_reinsertion += reinserted;
    }
    reinserted = ra->path == UpdatePath::kReinserted;
  }
  EXPECT_GE(kept, 6);
  EXPECT_GT(kept_after_reinsertion, 0);
}

// Position queries' hint grid outlives a few steps (a hint is only where a
// walk starts), renumbered with the points when a step renumbers them; age,
// points that join or leave, or coincident points bring a new one. The
// nearest points stay exact throughout.
TEST(CachedHintGrid, ServesAFewLocalStepsThenIsBuiltAgain) {
  std::vector<Vec2> pts = testing::UniformPoints(3000, 4);
  auto t = Triangulation::Create(pts);
  ASSERT_TRUE(t.ok()) << t.status();
  std::mt19937_64 rng(4);
  std::normal_distribution<double> move(0.0, 0.002);  // 0.1 spacings
  std::uniform_real_distribution<double> u(0.0, 1.0);
  auto step = [&] {
    std::vector<Vec2> d(pts.size());
    for (size_t i = 0; i < pts.size(); ++i) {
      d[i] = {move(rng), move(rng)};
      pts[i] = {pts[i].x + d[i].x, pts[i].y + d[i].y};
    }
    auto r = t->ApplyDisplacements(DisplacementBatch::Dense(d));
    ASSERT_TRUE(r.ok()) << r.status();
  };
  auto check_nearest = [&] {
    std::vector<Vec2> qs(300);
    for (Vec2& q : qs) q = {u(rng) * 1.2 - 0.1, u(rng) * 1.2 - 0.1};
    auto nn = Nearest(*t, qs);
    ASSERT_TRUE(nn.ok()) << nn.status();
    for (size_t i = 0; i < qs.size(); ++i) {
      auto d2 = [&](const Vec2& p) {
        return (p.x - qs[i].x) * (p.x - qs[i].x) +
               (p.y - qs[i].y) * (p.y - qs[i].y);
      };
      double best = INFINITY;
      for (const Vec2& p : pts) best = std::min(best, d2(p));
      ASSERT_EQ(nn->row_size(i), 1u);
      ASSERT_EQ(d2(pts[nn->ids[nn->offsets[i]]]), best) << "query " << i;
    }
  };
  const auto built = t->CachedHintGrid();
  for (uint64_t age = 1; age <= 4; ++age) {
    step();
    EXPECT_EQ(t->CachedHintGrid(), built) << "after " << age << " steps";
    check_nearest();
  }
  step();
  const auto rebuilt = t->CachedHintGrid();
  EXPECT_NE(rebuilt, built);
  check_nearest();
  // A step without position queries passes the grid on as well.
  step();
  step();
  EXPECT_EQ(t->CachedHintGrid(), rebuilt);
  // A step rebuilt from scratch renumbers the points: the grid follows,
  // each hint the same point under its new internal id.
  std::vector<uint32_t> old_ext(t->view().ext_of_int,
                                t->view().ext_of_int + t->size());
  const HintGridView before = rebuilt->view();
  {
    std::vector<Vec2> d(pts.size());
    std::normal_distribution<double> jump(0.0, 0.05);  // about 3 spacings
    for (size_t i = 0; i < pts.size(); ++i) {
      d[i] = {jump(rng), jump(rng)};
      pts[i] = {pts[i].x + d[i].x, pts[i].y + d[i].y};
    }
    auto r = t->ApplyDisplacements(DisplacementBatch::Dense(d));
    ASSERT_TRUE(r.ok()) << r.status();
    ASSERT_EQ(r->path, UpdatePath::kRebuilt);
    ASSERT_TRUE(r->renumbered);
  }
  const auto renumbered = t->CachedHintGrid();
  const HintGridView after = renumbered->view();
  ASSERT_EQ(after.side, before.side);
  const uint32_t* new_ext = t->view().ext_of_int;
  for (size_t c = 0; c < size_t{before.side} * before.side; ++c) {
    if (HintGridView::IsRefined(before.cells[c])) continue;
    ASSERT_EQ(new_ext[after.cells[c]], old_ext[before.cells[c]]) << c;
  }
  check_nearest();
  // A point joins: ids may change, a new grid.
  DisplacementBatch join;
  join.add = {{0.5, 0.5}};
  ASSERT_TRUE(t->ApplyDisplacements(join).ok());
  pts.push_back({0.5, 0.5});
  const auto after_join = t->CachedHintGrid();
  EXPECT_NE(after_join, renumbered);
  check_nearest();
  // Two points coincide: a point is no longer a site of its own.
  DisplacementBatch onto = DisplacementBatch::AbsoluteSparse({1}, {pts[0]});
  ASSERT_TRUE(t->ApplyDisplacements(onto).ok());
  pts[1] = pts[0];
  ASSERT_LT(t->num_sites(), t->size());
  EXPECT_NE(t->CachedHintGrid(), after_join);
  check_nearest();
}

}  // namespace
}  // namespace kinetri::core
