// Points that join and leave with a step (DisplacementBatch::add / remove):
// after every step Validate() passes, the edge set equals CGAL's, the
// positions equal a model that applies the documented numbering, and
// queries equal brute force. Built for every executor (executor_under_test).
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <random>

#include "core/queries.h"
#include "core/triangulation.h"
#include "tests/core/executor_under_test.h"
#include "tests/core/test_util.h"

namespace kinetri::core {
namespace {

// The model: moves, then removals (survivors keep their order), then the
// joining points appended.
std::vector<Vec2> ModelAfter(std::vector<Vec2> pts,
                             const DisplacementBatch& b) {
  const bool delta = b.mode == DisplacementBatch::Mode::kDelta;
  std::vector<uint8_t> gone(pts.size(), 0);
  for (uint32_t id : b.remove) gone[id] = 1;
  auto move = [&](uint32_t id, const Vec2& v) {
    if (gone[id]) return;
    pts[id] = delta ? Vec2{pts[id].x + v.x, pts[id].y + v.y} : v;
  };
  if (b.ids.empty()) {
    for (uint32_t i = 0; i < b.values.size(); ++i) move(i, b.values[i]);
  } else {
    for (size_t i = 0; i < b.ids.size(); ++i) move(b.ids[i], b.values[i]);
  }
  std::vector<Vec2> out;
  for (size_t i = 0; i < pts.size(); ++i) {
    if (!gone[i]) out.push_back(pts[i]);
  }
  out.insert(out.end(), b.add.begin(), b.add.end());
  return out;
}

void ExpectExact(const Triangulation& t, const std::vector<Vec2>& model,
                 const std::string& where) {
  ASSERT_TRUE(t.Validate().ok()) << where << ": " << t.Validate();
  ASSERT_EQ(t.size(), model.size()) << where;
  ASSERT_EQ(t.Positions(), model) << where;
  ASSERT_EQ(testing::EdgesAsPositions(t), testing::CgalDelaunayEdges(model))
      << where;
}

void ExpectQueriesMatchBruteForce(const Triangulation& t,
                                  const std::vector<Vec2>& model,
                                  std::mt19937_64& rng,
                                  const std::string& where) {
  if (model.empty()) return;
  std::vector<uint32_t> ids;
  for (int k = 0; k < 20; ++k) ids.push_back(rng() % model.size());
  auto r = KNearestOfPoints(t, ids, 5, /*exclude_self=*/true);
  ASSERT_TRUE(r.ok()) << r.status();
  for (size_t i = 0; i < ids.size(); ++i) {
    auto rank = testing::BruteRank(model, model[ids[i]], ids[i]);
    rank.resize(std::min<size_t>(rank.size(), 5));
    const std::vector<uint32_t> row(r->ids.begin() + r->offsets[i],
                                    r->ids.begin() + r->offsets[i + 1]);
    ASSERT_EQ(row, rank) << where << ": 5-NN of point " << ids[i];
  }
}

// Steps of the random scenarios, and how many of them were rebuilt.
int g_steps = 0, g_rebuilt = 0;

void RunScenario(uint64_t seed) {
  std::mt19937_64 rng(seed);
  size_t n = 100 + rng() % 1500;
  const int kind = static_cast<int>(rng() % 4);
  std::vector<Vec2> model =
      kind == 0   ? testing::UniformPoints(n, seed)
      : kind == 1 ? testing::ClusteredPoints(n, seed)
      : kind == 2 ? testing::Lattice(static_cast<int>(std::sqrt(n)), 0.125)
                  : testing::WithDuplicates(n / 2, 2, seed);
  // The moves too are repaired locally (no cost-model rebuilds), so that
  // every rebuild counted below comes from the changes.
  TriangulationOptions opt = testing::ExecutorOptions();
  opt.round.rebuild_fraction = 1.0;
  opt.round.max_passes = 64;
  opt.region.held_vertex_cost = 0.0;
  auto t = Triangulation::Create(model, opt);
  ASSERT_TRUE(t.ok());
  std::uniform_real_distribution<double> u(-0.2, 1.2);
  for (int s = 0; s < 10; ++s) {
    n = model.size();
    const std::string where = "seed " + std::to_string(seed) + " step " +
                              std::to_string(s) + " kind " +
                              std::to_string(kind);
    DisplacementBatch b;
    const int moves = static_cast<int>(rng() % 3);
    std::normal_distribution<double> g(0, 0.05 / std::sqrt(double(n) + 1));
    std::vector<uint8_t> gone(n, 0);
    // Leaving: random points, sometimes a run of hull-ish extremes.
    const size_t leave = n ? rng() % std::max<size_t>(1, n / 10) : 0;
    for (size_t k = 0; k < leave; ++k) {
      const uint32_t id = rng() % n;
      if (gone[id]) continue;
      gone[id] = 1;
      b.remove.push_back(id);
    }
    if (rng() % 3 == 0 && n > 0) {  // the leftmost point (on the hull)
      uint32_t best = 0;
      for (uint32_t i = 1; i < n; ++i) {
        if (model[i].x < model[best].x) best = i;
      }
      if (!gone[best]) {
        gone[best] = 1;
        b.remove.push_back(best);
      }
    }
    if (moves == 1) {
      std::vector<Vec2> d(n);
      for (auto& v : d) v = {g(rng), g(rng)};
      b.values = std::move(d);
    } else if (moves == 2) {
      for (uint32_t i = 0; i < n; i += 7) {
        if (gone[i]) continue;
        b.ids.push_back(i);
        b.values.push_back({g(rng), g(rng)});
      }
    }
    // Joining: inside and outside the current points, on existing points,
    // and pairs on each other.
    const size_t join = rng() % (n / 8 + 80);
    for (size_t k = 0; k < join; ++k) {
      const int what = static_cast<int>(rng() % 6);
      if (what == 0 && n > 0) {
        b.add.push_back(model[rng() % n]);
      } else if (what == 1 && !b.add.empty()) {
        b.add.push_back(b.add[rng() % b.add.size()]);
      } else if (kind == 2 && what < 4) {
        b.add.push_back(
            {std::round(u(rng) * 40) / 320, std::round(u(rng) * 40) / 320});
      } else {
        b.add.push_back({u(rng), u(rng)});
      }
    }
    const std::vector<Vec2> expected = ModelAfter(model, b);
    auto r = t->ApplyDisplacements(b);
    ASSERT_TRUE(r.ok()) << where << ": " << r.status();
    EXPECT_EQ(r->removed_points, b.remove.size()) << where;
    EXPECT_EQ(r->added_points, b.add.size()) << where;
    ++g_steps;
    if (r->path == UpdatePath::kRebuilt) ++g_rebuilt;
    model = expected;
    ExpectExact(*t, model, where);
    ExpectQueriesMatchBruteForce(*t, model, rng, where);
  }
}

TEST(JoinLeave, RandomScenariosStayExact) {
  for (uint64_t seed = 1; seed <= 24; ++seed) {
    RunScenario(seed);
    if (HasFatalFailure()) return;
  }
  // The changes are made locally, not by rebuilding.
  EXPECT_LT(g_rebuilt, g_steps / 10) << g_rebuilt << " of " << g_steps;
  std::printf("%d of %d steps rebuilt\n", g_rebuilt, g_steps);
}

TEST(JoinLeave, LargeBatchesStayLocal) {
  std::vector<Vec2> model = testing::UniformPoints(20000, 7);
  auto t = Triangulation::Create(model, testing::ExecutorOptions());
  ASSERT_TRUE(t.ok());
  std::mt19937_64 rng(7);
  DisplacementBatch b;
  for (uint32_t i = 0; i < 20000; i += 10) b.remove.push_back(i);
  std::uniform_real_distribution<double> u(0, 1);
  for (int k = 0; k < 2000; ++k) b.add.push_back({u(rng), u(rng)});
  std::vector<Vec2> expected = ModelAfter(model, b);
  auto r = t->ApplyDisplacements(b);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_EQ(r->path, UpdatePath::kLocal) << r->fallback_reason;
  EXPECT_EQ(r->moved_points, 0u);
  EXPECT_EQ(r->num_points, expected.size());
  ExpectExact(*t, expected, "large batch");
  ExpectQueriesMatchBruteForce(*t, expected, rng, "large batch");
  // Past 1/8 of the points (and 4096), rebuilding is cheaper: same result.
  b = {};
  for (uint32_t i = 0; i < 20000; i += 5) b.remove.push_back(i);
  for (int k = 0; k < 4000; ++k) b.add.push_back({u(rng), u(rng)});
  expected = ModelAfter(expected, b);
  r = t->ApplyDisplacements(b);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_EQ(r->path, UpdatePath::kRebuilt);
  EXPECT_NE(r->fallback_reason.find("rebuilding is cheaper"), std::string::npos)
      << r->fallback_reason;
  EXPECT_EQ(r->removed_points, 4000u);
  EXPECT_EQ(r->added_points, 4000u);
  ExpectExact(*t, expected, "rebuilt batch");
}

TEST(JoinLeave, CoincidentSitesHandOverTheirVertex) {
  // Three copies of every point: removing the representative (the smallest
  // id) hands the vertex to the next copy; removing all copies removes the
  // site.
  std::vector<Vec2> model = testing::WithDuplicates(300, 3, 3);
  auto t = Triangulation::Create(model, testing::ExecutorOptions());
  ASSERT_TRUE(t.ok());
  DisplacementBatch b;
  for (uint32_t i = 0; i < 100; ++i) b.remove.push_back(i);
  b.remove.push_back(150);
  b.remove.push_back(450);
  b.remove.push_back(750);  // the three copies of one point, if paired
  std::sort(b.remove.begin(), b.remove.end());
  b.remove.erase(std::unique(b.remove.begin(), b.remove.end()), b.remove.end());
  b.add = {model[200], model[200], {0.5, 0.5}};
  const std::vector<Vec2> expected = ModelAfter(model, b);
  auto r = t->ApplyDisplacements(b);
  ASSERT_TRUE(r.ok()) << r.status();
  ExpectExact(*t, expected, "duplicates");
  std::mt19937_64 rng(3);
  ExpectQueriesMatchBruteForce(*t, expected, rng, "duplicates");
}

TEST(JoinLeave, DownToALineAndBack) {
  std::vector<Vec2> model = {{0, 0}, {1, 0}, {0, 1}, {1, 1}, {0.5, 0.5}};
  auto t = Triangulation::Create(model, testing::ExecutorOptions());
  ASSERT_TRUE(t.ok());
  ASSERT_TRUE(t->is_planar());
  // Leave only a collinear pair plus a coincident point: line mode.
  DisplacementBatch b;
  b.remove = {2, 3, 4};
  b.add = {{1, 0}};
  auto r = t->ApplyDisplacements(b);
  ASSERT_TRUE(r.ok()) << r.status();
  model = {{0, 0}, {1, 0}, {1, 0}};
  ExpectExact(*t, model, "line");
  EXPECT_FALSE(t->is_planar());
  // Points join off the line: planar again.
  b = {};
  b.add = {{0.5, 2}, {0.5, -2}};
  ASSERT_TRUE(t->ApplyDisplacements(b).ok());
  model.push_back({0.5, 2});
  model.push_back({0.5, -2});
  ExpectExact(*t, model, "planar again");
  EXPECT_TRUE(t->is_planar());
  // Everything leaves, then points join an empty set.
  b = {};
  b.remove = {0, 1, 2, 3, 4};
  ASSERT_TRUE(t->ApplyDisplacements(b).ok());
  ExpectExact(*t, {}, "empty");
  b = {};
  b.add = {{0, 0}, {3, 0}, {0, 3}, {1, 1}};
  ASSERT_TRUE(t->ApplyDisplacements(b).ok());
  ExpectExact(*t, b.add, "refilled");
  EXPECT_EQ(t->steps(), 4u);
}

TEST(JoinLeave, RemovingTheWholeHullStaysLocal) {
  const std::vector<Vec2> model = testing::Lattice(12, 1.0);
  auto t = Triangulation::Create(model, testing::ExecutorOptions());
  ASSERT_TRUE(t.ok());
  DisplacementBatch b;
  for (uint32_t i = 0; i < model.size(); ++i) {
    const Vec2& p = model[i];
    if (p.x == 0 || p.y == 0 || p.x == 11 || p.y == 11) b.remove.push_back(i);
  }
  const std::vector<Vec2> expected = ModelAfter(model, b);
  auto r = t->ApplyDisplacements(b);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_EQ(r->path, UpdatePath::kLocal) << r->fallback_reason;
  ExpectExact(*t, expected, "hull removed");
}

TEST(JoinLeave, BadChangesAreRefusedAndChangeNothing) {
  const std::vector<Vec2> model = testing::UniformPoints(50, 9);
  auto t = Triangulation::Create(model, testing::ExecutorOptions());
  ASSERT_TRUE(t.ok());
  DisplacementBatch b;
  b.remove = {3, 50};
  auto r = t->ApplyDisplacements(b);
  EXPECT_EQ(r.status().code(), absl::StatusCode::kNotFound);
  EXPECT_NE(r.status().message().find("remove[1] = 50"), std::string::npos);
  b.remove = {3, 3};
  EXPECT_EQ(t->ApplyDisplacements(b).status().code(),
            absl::StatusCode::kInvalidArgument);
  b.remove = {3};
  b.add = {{0.5, std::nan("")}};
  r = t->ApplyDisplacements(b);
  EXPECT_EQ(r.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(r.status().message().find("add[0].y is NaN"), std::string::npos);
  b = DisplacementBatch::Sparse({3}, {{0.01, 0}});
  b.remove = {3};
  r = t->ApplyDisplacements(b);
  EXPECT_EQ(r.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(r.status().message().find("leaves"), std::string::npos);
  // A dense batch still needs one value per point (the leaving ones too).
  b = DisplacementBatch::Dense(std::vector<Vec2>(49));
  b.remove = {3};
  EXPECT_EQ(t->ApplyDisplacements(b).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(t->steps(), 0u);
  ExpectExact(*t, model, "after refusals");
  // A dense batch with a leaving point: its value is not used.
  std::vector<Vec2> d(50, Vec2{0.001, 0});
  d[3] = {1e6, 1e6};
  b = DisplacementBatch::Dense(d);
  b.remove = {3};
  ASSERT_TRUE(t->ApplyDisplacements(b).ok());
  ExpectExact(*t, ModelAfter(model, b), "dense with a leaving point");
}

}  // namespace
}  // namespace kinetri::core
