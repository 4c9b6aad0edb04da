// Unit tests beneath every executor: the mesh and its flip, the per-element
// rules (core/flip_rules.h), the dense scan (core/mesh_scan.h) against
// them, vertex removal and insertion
// (core/vertex_ops.h) and the serial stack loops of the region executor,
// each against CGAL's triangulation of the same points.
#include <gtest/gtest.h>
#include <tbb/task_arena.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <numeric>
#include <random>
#include <string>
#include <utility>
#include <vector>

#include "core/cancel.h"
#include "core/cgal_builder.h"
#include "core/flip_rules.h"
#include "core/kinetic.h"
#include "core/mesh.h"
#include "core/mesh_scan.h"
#include "core/region_executor.h"
#include "core/spatial_order.h"
#include "core/vertex_ops.h"
#include "tests/core/test_util.h"

namespace kinetri::core {
namespace {

using EdgeSet = std::vector<std::pair<uint32_t, uint32_t>>;

EdgeSet FiniteEdges(const Mesh& mesh) {
  EdgeSet out;
  const MeshView m = mesh.view();
  for (uint32_t e = 0; e < mesh.num_half_edges(); ++e) {
    const uint32_t a = m.origin[e];
    if (a == kNoVertex) continue;
    const uint32_t b = m.Dest(e);
    if (a == kInfiniteVertex || b == kInfiniteVertex || e > m.twin[e]) continue;
    out.emplace_back(std::min(a, b), std::max(a, b));
  }
  std::sort(out.begin(), out.end());
  return out;
}

std::vector<uint32_t> AllSites(size_t n) {
  std::vector<uint32_t> s(n);
  std::iota(s.begin(), s.end(), 0u);
  return s;
}

// Twins are involutions with reversed endpoints; vertex_edge leaves its
// vertex.
void ExpectConsistent(const Mesh& mesh) {
  const MeshView m = mesh.view();
  for (uint32_t e = 0; e < mesh.num_half_edges(); ++e) {
    if (m.origin[e] == kNoVertex) continue;
    ASSERT_EQ(m.twin[m.twin[e]], e);
    ASSERT_EQ(m.origin[m.twin[e]], m.Dest(e));
  }
  for (uint32_t v = 0; v < mesh.num_vertices(); ++v) {
    const uint32_t e = mesh.vertex_edge()[v];
    if (e != kNoEdge) {
      ASSERT_EQ(m.origin[e], v);
    }
  }
}

std::vector<Vec2> Shifted(std::vector<Vec2> pts, double by) {
  for (Vec2& p : pts) p = {p.x + by, p.y + by};
  return pts;
}

double MeshScanTestArea(const std::vector<Vec2>& pts) {
  double x0 = pts[0].x, x1 = x0, y0 = pts[0].y, y1 = y0;
  for (const Vec2& p : pts) {
    x0 = std::min(x0, p.x);
    x1 = std::max(x1, p.x);
    y0 = std::min(y0, p.y);
    y1 = std::max(y1, p.y);
  }
  return (x1 - x0) * (y1 - y0);
}

uint32_t InteriorEdge(const Mesh& mesh) {
  const MeshView m = mesh.view();
  for (uint32_t e = 0; e < mesh.num_half_edges(); ++e) {
    if (!m.IsGhost(TriangleOf(e)) && !m.IsGhost(TriangleOf(m.twin[e]))) {
      return e;
    }
  }
  return kNoEdge;
}

TEST(Mesh, FourFlipsAreTheIdentityAndKeepTwins) {
  const auto pts = testing::UniformPoints(200, 1);
  Mesh mesh = BuildDelaunayWithCgal(pts, AllSites(pts.size()));
  const std::vector<uint32_t> origin = mesh.origin(), twin = mesh.twin();
  const uint32_t e = InteriorEdge(mesh);
  ASSERT_NE(e, kNoEdge);
  const MeshView m = mesh.view();
  const uint32_t c = m.Apex(e), d = m.Across(e);
  m.Flip(e);
  mesh.UpdateVertexEdgesAfterFlip(e);
  // The flipped slot now joins the two apexes (d -> c, see mesh.h).
  EXPECT_EQ(m.origin[e], d);
  EXPECT_EQ(m.Dest(e), c);
  ExpectConsistent(mesh);
  for (int k = 0; k < 3; ++k) m.Flip(e);
  EXPECT_EQ(mesh.origin(), origin);
  EXPECT_EQ(mesh.twin(), twin);
}

// Mesh::Fingerprint: equal meshes (a copy) give equal fingerprints, on one
// thread or all; one changed entry of any array changes it, and putting
// it back restores it; a flip changes it.
TEST(Mesh, FingerprintFollowsEveryEntry) {
  const auto pts = testing::UniformPoints(30000, 4);
  Mesh mesh = BuildDelaunayWithCgal(pts, AllSites(pts.size()));
  const uint64_t f = mesh.Fingerprint();
  const Mesh copy = mesh;
  EXPECT_EQ(copy.Fingerprint(), f);
  uint64_t one_thread = 0;
  tbb::task_arena(1).execute([&] { one_thread = mesh.Fingerprint(); });
  EXPECT_EQ(one_thread, f);
  std::vector<uint32_t>& ve = mesh.mutable_vertex_edge();
  for (const uint32_t v : {0u, 12345u, 29999u}) {
    const uint32_t old = ve[v];
    ve[v] = old + 1;
    EXPECT_NE(mesh.Fingerprint(), f) << "vertex_edge " << v;
    ve[v] = old;
  }
  for (const uint32_t e : {0u, 77777u, mesh.num_half_edges() - 1}) {
    const uint32_t o = mesh.origin()[e], t = mesh.twin()[e];
    mesh.SetHalfEdge(e, o ^ 1u, t);
    EXPECT_NE(mesh.Fingerprint(), f) << "origin " << e;
    mesh.SetHalfEdge(e, o, t ^ 4u);
    EXPECT_NE(mesh.Fingerprint(), f) << "twin " << e;
    mesh.SetHalfEdge(e, o, t);
  }
  EXPECT_EQ(mesh.Fingerprint(), f);
  const uint32_t e = InteriorEdge(mesh);
  ASSERT_NE(e, kNoEdge);
  mesh.view().Flip(e);
  EXPECT_NE(mesh.Fingerprint(), f);
}

// The fingerprint in parts: its sums followed entry by entry (Change, as
// the device executor applies an attempt's changes) equal the sums of the
// changed mesh, and combine into its fingerprint.
TEST(Mesh, FingerprintSumsFollowChangedEntries) {
  const auto pts = testing::UniformPoints(20000, 5);
  Mesh mesh = BuildDelaunayWithCgal(pts, AllSites(pts.size()));
  Mesh::FingerprintSums sums = mesh.FingerprintParts();
  EXPECT_EQ(sums.Combine(), mesh.Fingerprint());
  const Mesh before = mesh;
  // Flip a few hundred edges (each changes several half-edges), then
  // follow every entry that differs.
  std::mt19937 rng(6);
  int flipped = 0;
  for (int k = 0; k < 2000 && flipped < 300; ++k) {
    const uint32_t e = rng() % mesh.num_half_edges();
    const MeshView m = mesh.view();
    if (m.origin[e] == kInfiniteVertex ||
        m.origin[Next(e)] == kInfiniteVertex ||
        m.origin[Prev(e)] == kInfiniteVertex) {
      continue;
    }
    const uint32_t t = m.twin[e];
    if (m.origin[Prev(t)] == kInfiniteVertex) continue;
    m.Flip(e);
    mesh.UpdateVertexEdgesAfterFlip(e);
    ++flipped;
  }
  ASSERT_GT(flipped, 100);
  int changed = 0;
  for (uint32_t i = 0; i < mesh.num_half_edges(); ++i) {
    if (before.origin()[i] != mesh.origin()[i]) {
      sums.Change(0, i, before.origin()[i], mesh.origin()[i]);
      ++changed;
    }
    if (before.twin()[i] != mesh.twin()[i]) {
      sums.Change(1, i, before.twin()[i], mesh.twin()[i]);
    }
  }
  for (uint32_t v = 0; v < mesh.num_vertices(); ++v) {
    if (before.vertex_edge()[v] != mesh.vertex_edge()[v]) {
      sums.Change(2, v, before.vertex_edge()[v], mesh.vertex_edge()[v]);
    }
  }
  EXPECT_GT(changed, 0);
  const Mesh::FingerprintSums again = mesh.FingerprintParts();
  for (int k = 0; k < 3; ++k) {
    EXPECT_EQ(sums.s0[k], again.s0[k]) << k;
    EXPECT_EQ(sums.s1[k], again.s1[k]) << k;
  }
  EXPECT_EQ(sums.Combine(), mesh.Fingerprint());
  EXPECT_NE(sums.Combine(), before.Fingerprint());
}

// content_version() names the contents: reading keeps it, every member
// that may write renews it (the device executor skips its pass over the
// host mesh while it is unchanged), a copy keeps it while it equals the
// original, and a moved-from mesh gets a new one.
TEST(Mesh, ContentVersionChangesWithEveryWritingAccess) {
  const auto pts = testing::UniformPoints(500, 7);
  Mesh mesh = BuildDelaunayWithCgal(pts, AllSites(pts.size()));
  const uint64_t v0 = mesh.content_version();
  EXPECT_NE(v0, 0u);
  // Reading: const members, a const view, a fingerprint.
  const Mesh& reader = mesh;
  (void)reader.view().Dest(0);
  (void)reader.origin();
  (void)reader.vertex_edge();
  (void)reader.Fingerprint();
  EXPECT_EQ(mesh.content_version(), v0);
  // Each writing access renews it, even one that writes nothing.
  std::vector<uint64_t> seen = {v0};
  auto renewed = [&](const char* what) {
    const uint64_t v = mesh.content_version();
    EXPECT_EQ(std::count(seen.begin(), seen.end(), v), 0) << what;
    EXPECT_EQ(mesh.content_version(), v) << what << " (asked twice)";
    seen.push_back(v);
  };
  (void)mesh.view();
  renewed("view()");
  mesh.SetHalfEdge(0, mesh.origin()[0], mesh.twin()[0]);
  renewed("SetHalfEdge");
  (void)mesh.mutable_vertex_edge();
  renewed("mutable_vertex_edge");
  const uint32_t e = InteriorEdge(mesh);
  ASSERT_NE(e, kNoEdge);
  {
    const MeshView w = mesh.view();
    w.Flip(e);
    w.Unflip(e);
  }
  renewed("Flip + Unflip");
  mesh.UpdateVertexEdgesAfterFlip(e);
  renewed("UpdateVertexEdgesAfterFlip");
  mesh.RebuildVertexEdges();
  renewed("RebuildVertexEdges");
  std::vector<uint32_t> o = mesh.origin(), t = mesh.twin(),
                        ve = mesh.vertex_edge();
  mesh.SwapArrays(&o, &t, &ve);
  renewed("SwapArrays");
  std::vector<uint32_t> touched;
  ASSERT_TRUE(VertexOps::Remove(mesh, pts, 17, &touched, nullptr));
  renewed("VertexOps::Remove");
  mesh.Compact();
  renewed("Compact");
  mesh.SortTrianglesByVertex();
  renewed("SortTrianglesByVertex");
  std::vector<uint32_t> same(mesh.num_vertices());
  std::iota(same.begin(), same.end(), 0u);
  mesh.RenumberVertices(same);
  renewed("RenumberVertices");
  // A copy names the same contents until one of the two writes.
  const uint64_t v = mesh.content_version();
  Mesh copy = mesh;
  EXPECT_EQ(copy.content_version(), v);
  copy.RebuildVertexEdges();
  EXPECT_NE(copy.content_version(), v);
  EXPECT_EQ(mesh.content_version(), v);
  // Moved: the new owner keeps the number, the emptied one does not.
  Mesh moved = std::move(mesh);
  EXPECT_EQ(moved.content_version(), v);
  EXPECT_NE(mesh.content_version(), v);  // NOLINT(bugprone-use-after-move)
  Mesh assigned;
  assigned = std::move(moved);
  EXPECT_EQ(assigned.content_version(), v);
  EXPECT_NE(moved.content_version(), v);  // NOLINT(bugprone-use-after-move)
  // Two meshes built apart never share a number.
  const Mesh other = BuildDelaunayWithCgal(pts, AllSites(pts.size()));
  EXPECT_NE(other.content_version(), assigned.content_version());
}

// Unflip undoes a flip exactly (every origin and twin), including a chain
// of flips undone in reverse (what a stopped step does with its log).
TEST(Mesh, UnflipUndoesFlipsInReverse) {
  const auto pts = testing::UniformPoints(400, 3);
  Mesh mesh = BuildDelaunayWithCgal(pts, AllSites(pts.size()));
  const std::vector<uint32_t> origin = mesh.origin(), twin = mesh.twin();
  const MeshView m = mesh.view();
  std::mt19937 rng(4);
  std::vector<uint32_t> log;
  for (int i = 0; i < 200; ++i) {
    const uint32_t e = rng() % mesh.num_half_edges();
    if (m.IsGhost(TriangleOf(e)) || m.IsGhost(TriangleOf(m.twin[e]))) continue;
    // Only flips that keep a triangulation (convex quads).
    const Vec2 a = pts[m.origin[e]], b = pts[m.Dest(e)];
    const Vec2 c = pts[m.Apex(e)], d = pts[m.Across(e)];
    if (Orient2d(d, c, a) <= 0 || Orient2d(c, d, b) <= 0) continue;
    m.Flip(e);
    log.push_back(e);
  }
  ASSERT_GT(log.size(), 100u);
  EXPECT_NE(mesh.origin(), origin);
  for (auto it = log.rbegin(); it != log.rend(); ++it) m.Unflip(*it);
  EXPECT_EQ(mesh.origin(), origin);
  EXPECT_EQ(mesh.twin(), twin);
}

TEST(Mesh, CompactFillsFreedSlots) {
  const auto pts = testing::UniformPoints(300, 2);
  Mesh mesh = BuildDelaunayWithCgal(pts, AllSites(pts.size()));
  std::vector<uint32_t> touched;
  ASSERT_TRUE(VertexOps::Remove(mesh, pts, 17, &touched, nullptr));
  EXPECT_TRUE(mesh.has_free_triangles());
  const uint32_t before = mesh.num_triangles();
  mesh.Compact();
  EXPECT_FALSE(mesh.has_free_triangles());
  EXPECT_EQ(mesh.num_triangles(), before - 2);
  ExpectConsistent(mesh);
}

TEST(FlipRules, OrientationAndHullTurns) {
  const std::vector<Vec2> pts = {{0, 0}, {4, 0}, {1, 3}, {3, 3}, {2, 1}};
  Mesh mesh = BuildDelaunayWithCgal(pts, AllSites(pts.size()));
  const MeshView m = mesh.view();
  for (uint32_t t = 0; t < mesh.num_triangles(); ++t) {
    EXPECT_TRUE(rules::TriangleOk(m, pts.data(), t)) << t;
  }
  // Vertex 4 jumps below the hull edge 0-1: a finite triangle inverts and
  // the ghost triangle of that hull edge has a repair (hull absorption) or
  // the inverted triangle an interior flip.
  std::vector<Vec2> moved = pts;
  moved[4] = {2, -1};
  int invalid = 0, proposals = 0;
  for (uint32_t t = 0; t < mesh.num_triangles(); ++t) {
    if (rules::TriangleOk(m, moved.data(), t)) continue;
    ++invalid;
    if (rules::ProposeFixFlip(m, moved.data(), t).edge != kNoEdge) {
      ++proposals;
    }
  }
  EXPECT_GT(invalid, 0);
  EXPECT_GT(proposals, 0);
  std::vector<uint32_t> bad;
  for (uint32_t t = 0; t < mesh.num_triangles(); ++t) {
    if (!rules::TriangleOk(m, moved.data(), t)) bad.push_back(t);
  }
  ASSERT_TRUE(RegionExecutor::FixSerial(mesh, moved, bad, nullptr, nullptr,
                                        nullptr, nullptr));
  std::vector<uint32_t> all(mesh.num_triangles());
  std::iota(all.begin(), all.end(), 0u);
  RegionExecutor::LegalizeSerial(mesh, moved, all, nullptr);
  EXPECT_EQ(FiniteEdges(mesh),
            FiniteEdges(BuildDelaunayWithCgal(moved, AllSites(moved.size()))));
  ExpectConsistent(mesh);
}

TEST(FlipRules, IllegalEdgeIsTheOneInsideTheCircle) {
  // Quad a, b with apexes c (above) and d (below): d inside the circle of
  // (a, b, c) makes the shared edge illegal; after the flip it is legal.
  const auto pts = testing::UniformPoints(400, 3);
  Mesh mesh = BuildDelaunayWithCgal(pts, AllSites(pts.size()));
  const MeshView m = mesh.view();
  const uint32_t e = InteriorEdge(mesh);
  ASSERT_FALSE(rules::IsIllegal(m, pts.data(), e));
  m.Flip(e);  // the other diagonal of a Delaunay quad is illegal
  EXPECT_TRUE(rules::IsIllegal(m, pts.data(), e));
  m.Flip(e);
  m.Flip(e);
  m.Flip(e);
  EXPECT_FALSE(rules::IsIllegal(m, pts.data(), e));
}

TEST(FlipRules, NonConvexQuadHasNoInteriorFlip) {
  // Triangle (0,1,2) with 2 pushed through edge 0-1 so far that the quad
  // with the triangle across is not convex: no flip can repair it.
  const std::vector<Vec2> pts = {{0, 0},  {4, 0}, {2, 1},  {2, -1},
                                 {-3, 3}, {7, 3}, {2, -6}, {2, 6}};
  Mesh mesh = BuildDelaunayWithCgal(pts, AllSites(pts.size()));
  const MeshView m = mesh.view();
  std::vector<Vec2> moved = pts;
  moved[2] = {2, -5};  // far past vertex 3
  int stuck = 0;
  for (uint32_t t = 0; t < mesh.num_triangles(); ++t) {
    if (rules::TriangleOk(m, moved.data(), t)) continue;
    if (rules::ProposeFixFlip(m, moved.data(), t).edge == kNoEdge) ++stuck;
  }
  EXPECT_GT(stuck, 0);
}

// The hold-back rule: a stuck triangle's culprit is the moving vertex whose
// old position alone repairs it (here the one pushed far through an edge,
// not its neighbour that moved a little); without it, every moving corner.
TEST(FlipRules, CulpritIsTheVertexWhoseOldPositionRepairs) {
  const std::vector<Vec2> pts = {{0, 0},  {4, 0}, {2, 1},  {2, -1},
                                 {-3, 3}, {7, 3}, {2, -6}, {2, 6}};
  Mesh mesh = BuildDelaunayWithCgal(pts, AllSites(pts.size()));
  const MeshView m = mesh.view();
  std::vector<Vec2> moved = pts;
  moved[2] = {2, -5};   // far past vertex 3: no flip repairs it
  moved[0] = {0.1, 0};  // a neighbour that moved a little
  auto moving = [&](uint32_t u) { return moved[u] != pts[u]; };
  int stuck = 0;
  for (uint32_t t = 0; t < mesh.num_triangles(); ++t) {
    if (rules::TriangleOk(m, moved.data(), t)) continue;
    if (rules::ProposeFixFlip(m, moved.data(), t).edge != kNoEdge) continue;
    ++stuck;
    uint32_t v[3], e[3];
    const int n = rules::Culprits(m, moved.data(), pts.data(), t, moving, v, e);
    ASSERT_EQ(n, 1) << t;
    EXPECT_EQ(v[0], 2u) << t;
    EXPECT_EQ(m.origin[e[0]], 2u) << t;  // a half-edge leaving it
    EXPECT_TRUE(
        rules::TriangleOk(m, rules::PosWith{moved.data(), 2, pts[2]}, t));
    // Vertex 2 may not be held (held already): the others that moved.
    auto others = [&](uint32_t u) { return u != 2 && moving(u); };
    const int k = rules::Culprits(m, moved.data(), pts.data(), t, others, v, e);
    for (int i = 0; i < k; ++i) {
      EXPECT_EQ(v[i], 0u) << t;
      EXPECT_EQ(m.origin[e[i]], 0u) << t;
    }
    // Nothing moving: no culprit.
    auto none = [](uint32_t) { return false; };
    EXPECT_EQ(rules::Culprits(m, moved.data(), pts.data(), t, none, v, e), 0);
  }
  EXPECT_GT(stuck, 0);
}

// ForEachStarAndHullRing lists every triangle whose validity reads the
// vertex: moving the vertex anywhere changes no other triangle's
// TriangleOk (hull vertices included, whose hull neighbours' turns read
// them).
TEST(FlipRules, StarAndHullRingHoldEveryTriangleAVertexDecides) {
  const auto pts = testing::UniformPoints(300, 17);
  Mesh mesh = BuildDelaunayWithCgal(pts, AllSites(pts.size()));
  const MeshView m = mesh.view();
  std::mt19937_64 rng(18);
  std::uniform_real_distribution<double> u(-0.5, 1.5);
  for (uint32_t v = 0; v < pts.size(); ++v) {
    std::vector<uint8_t> listed(mesh.num_triangles(), 0);
    rules::ForEachStarAndHullRing(m, mesh.vertex_edge()[v],
                                  [&](uint32_t t) { listed[t] = 1; });
    for (int trial = 0; trial < 4; ++trial) {
      const rules::PosWith elsewhere{pts.data(), v, Vec2{u(rng), u(rng)}};
      for (uint32_t t = 0; t < mesh.num_triangles(); ++t) {
        if (listed[t]) continue;
        ASSERT_EQ(rules::TriangleOk(m, pts.data(), t),
                  rules::TriangleOk(m, elsewhere, t))
            << "vertex " << v << ", triangle " << t;
      }
    }
  }
}

// The bounded fix rule (what a region executor runs in parallel) asks
// before it reads any triangle but its own, stops at the first refusal, and
// proposes what the unbounded rule proposes whenever nothing was refused.
TEST(FlipRules, BoundedProposalAsksBeforeReadingAndAgrees) {
  // Numbered as a triangulation numbers them: points along a Hilbert
  // curve, triangles by vertex (so that slot windows are regions).
  const auto raw = testing::UniformPoints(3000, 41);
  std::vector<Vec2> pts;
  for (uint32_t i : HilbertOrder(raw)) pts.push_back(raw[i]);
  Mesh mesh = BuildDelaunayWithCgal(pts, AllSites(pts.size()));
  mesh.SortTrianglesByVertex();
  const MeshView m = mesh.view();
  std::mt19937_64 rng(42);
  std::normal_distribution<double> g(0.0, 0.4 / std::sqrt(3000.0));
  std::vector<Vec2> moved = pts;
  for (Vec2& p : moved) p = {p.x + g(rng), p.y + g(rng)};
  const uint32_t nt = mesh.num_triangles();
  int invalid = 0, ghosts = 0, flips = 0, refused_windows = 0,
      agreed_windows = 0;
  for (uint32_t t = 0; t < nt; ++t) {
    if (rules::TriangleOk(m, moved.data(), t)) continue;
    ++invalid;
    ghosts += m.IsGhost(t) ? 1 : 0;
    const rules::FixProposal want = rules::ProposeFixFlip(m, moved.data(), t);
    flips += want.edge != kNoEdge ? 1 : 0;
    // Everything allowed: the same proposal; record what it asks for.
    std::vector<uint32_t> asked;
    bool outside = false;
    auto record = [&](uint32_t x) {
      asked.push_back(x);
      return true;
    };
    rules::FixProposal got =
        rules::ProposeFixFlip(m, moved.data(), t, record, &outside);
    EXPECT_FALSE(outside);
    EXPECT_EQ(got.edge, want.edge) << t;
    EXPECT_EQ(got.kind, want.kind) << t;
    std::sort(asked.begin(), asked.end());
    asked.erase(std::unique(asked.begin(), asked.end()), asked.end());
    // It reads nothing it did not ask for: on a copy of the mesh where
    // every other triangle is garbage (edges that lead back to themselves
    // from a poison vertex: 0, the infinite vertex, or one of t's own, which
    // the rules compare against), asking only for what it asked, it agrees.
    std::vector<uint8_t> keep(nt, 0);
    keep[t] = 1;
    for (uint32_t x : asked) keep[x] = 1;
    for (uint32_t poison : {0u, kInfiniteVertex, m.origin[3 * t],
                            m.origin[3 * t + 1], m.origin[3 * t + 2]}) {
      std::vector<uint32_t> origin(m.origin, m.origin + m.num_half_edges);
      std::vector<uint32_t> twin(m.twin, m.twin + m.num_half_edges);
      for (uint32_t x = 0; x < nt; ++x) {
        if (keep[x]) continue;
        for (uint32_t e = 3 * x; e < 3 * x + 3; ++e) {
          origin[e] = poison;
          twin[e] = e;
        }
      }
      MeshView poisoned = m;
      poisoned.origin = origin.data();
      poisoned.twin = twin.data();
      bool out = false;
      const rules::FixProposal p = rules::ProposeFixFlip(
          poisoned, moved.data(), t, [&](uint32_t y) { return keep[y] != 0; },
          &out);
      EXPECT_FALSE(out);
      EXPECT_EQ(p.edge, want.edge) << t << " poison " << poison;
      EXPECT_EQ(p.new_u, want.new_u) << t;
      EXPECT_EQ(p.new_w, want.new_w) << t;
    }
    // Refusing any one triangle it asked for is reported.
    for (uint32_t x : asked) {
      if (x == t) continue;
      bool out = false;
      rules::ProposeFixFlip(
          m, moved.data(), t, [&](uint32_t y) { return y != x; }, &out);
      EXPECT_TRUE(out) << "triangle " << t << " read " << x
                       << " after it was refused";
    }
    // Windows of slots around t, as regions are: no refusal, same answer.
    for (uint32_t w : {16u, 64u, 256u}) {
      const uint32_t lo = t > w ? t - w : 0, hi = t + w;
      bool out = false;
      got = rules::ProposeFixFlip(
          m, moved.data(), t, [&](uint32_t y) { return y >= lo && y < hi; },
          &out);
      if (out) {
        ++refused_windows;
        continue;
      }
      ++agreed_windows;
      EXPECT_EQ(got.edge, want.edge) << t;
      EXPECT_EQ(got.new_u, want.new_u) << t;
      EXPECT_EQ(got.new_w, want.new_w) << t;
    }
  }
  // Not vacuous: hull and interior cases, proposals, refusals, agreement.
  EXPECT_GT(invalid, 100);
  EXPECT_GT(ghosts, 0);
  EXPECT_GT(flips, 50);
  EXPECT_GT(refused_windows, 10);
  EXPECT_GT(agreed_windows, 100);
}

// What ScanTriangles must find: the rules, one element at a time.
void ExpectScanMatchesRules(const Mesh& mesh, const std::vector<Vec2>& pos) {
  const MeshView m = mesh.view();
  const uint32_t nt = mesh.num_triangles();
  std::vector<uint32_t> want_invalid, want_illegal;
  for (uint32_t t = 0; t < nt; ++t) {
    if (m.IsFree(t)) continue;
    if (!rules::TriangleOk(m, pos.data(), t)) want_invalid.push_back(t);
    for (uint32_t e = 3 * t; e < 3 * t + 3; ++e) {
      if (e < m.twin[e] && !m.IsGhost(t) &&
          rules::IsIllegal(m, pos.data(), e)) {
        want_illegal.push_back(e);
      }
    }
  }
  // The apexes across read from a per-half-edge array, as FillAcross
  // writes it (kNoVertex in free slots).
  std::vector<uint32_t> across(m.num_half_edges, 0);
  FillAcross(m, 0, nt, across.data());
  for (uint32_t e = 0; e < m.num_half_edges; ++e) {
    ASSERT_EQ(across[e], m.IsFree(e / 3) ? kNoVertex : m.Across(e)) << e;
  }
  // Both forms of the scan, over the whole range and cut into pieces (as
  // regions cut it).
  for (const uint32_t* apexes : {static_cast<const uint32_t*>(nullptr),
                                 static_cast<const uint32_t*>(across.data())}) {
    for (uint32_t piece : {nt, 7u, 64u}) {
      std::vector<uint32_t> invalid, illegal;
      for (uint32_t lo = 0; lo < nt; lo += piece) {
        const uint32_t hi = std::min(nt, lo + piece);
        if (apexes == nullptr) {
          ScanTriangles(m, pos.data(), lo, hi, &invalid, &illegal);
        } else {
          ScanTriangles(m, pos.data(), apexes, lo, hi, &invalid, &illegal);
        }
      }
      const char* form = apexes == nullptr ? "mesh" : "array";
      EXPECT_EQ(invalid, want_invalid) << form << ", piece " << piece;
      EXPECT_EQ(illegal, want_illegal) << form << ", piece " << piece;
    }
  }
  // It is the array that is read: with every apex across unknown (as on
  // the hull) no edge is illegal.
  std::fill(across.begin(), across.end(), kInfiniteVertex);
  std::vector<uint32_t> invalid, illegal;
  ScanTriangles(m, pos.data(), across.data(), 0, nt, &invalid, &illegal);
  EXPECT_EQ(invalid, want_invalid);
  EXPECT_TRUE(illegal.empty());
}

// Step works on `to` in place (held vertices stand at their old positions
// while it runs): whatever way it ends, every entry is as given when it
// returns. Ends checked: success with held vertices, the cost model's
// rebuild after regions held vertices, and stops at every poll of the
// step (undone: the mesh of `from` again).
TEST(RegionExecutor, StepGivesBackEveryTarget) {
  constexpr size_t kN = 3000;  // under 4 * 2048 triangles: no rebuild sample
  // Vertices and triangles in spatial order, as Triangulation keeps them:
  // regions then hold whole stars, and hold vertices back themselves.
  const std::vector<Vec2> raw = testing::UniformPoints(kN, 11);
  std::vector<Vec2> from;
  for (uint32_t i : HilbertOrder(raw)) from.push_back(raw[i]);
  auto build = [&] {
    Mesh mesh = BuildDelaunayWithCgal(from, AllSites(kN));
    mesh.SortTrianglesByVertex();
    return mesh;
  };
  std::mt19937_64 rng(5);
  std::normal_distribution<double> g(0.0, 0.4 / std::sqrt(double(kN)));
  std::vector<Vec2> to = from;
  for (Vec2& p : to) p = {p.x + g(rng), p.y + g(rng)};
  const std::vector<uint32_t> moved = AllSites(kN);
  const EdgeSet before = FiniteEdges(build());
  RegionStepPolicy policy;
  policy.region_triangles = 256;
  struct Run {
    bool ok;
    RegionStepStats stats;
    std::vector<uint32_t> removed;
    std::string reason;
    Mesh mesh;
  };
  auto run = [&](const RegionStepPolicy& pol, const CancelToken* cancel) {
    Run r{false, {}, {}, {}, build()};
    std::vector<Vec2> work = to;
    std::vector<uint32_t> hints(kN, kNoVertex);
    r.ok = RegionExecutor().Step(r.mesh, from, work, moved, pol, &r.stats,
                                 &r.removed, &hints, &r.reason, cancel);
    EXPECT_EQ(work, to) << r.reason;
    return r;
  };
  // Success, with held vertices; the mesh is Delaunay for `to` (less what
  // was removed for re-insertion).
  Run done = run(policy, nullptr);
  ASSERT_TRUE(done.ok) << done.reason;
  EXPECT_GT(done.stats.held, 0u);
  std::vector<Vec2> kept;
  std::vector<uint32_t> sites;
  std::vector<uint8_t> gone(kN, 0);
  for (uint32_t v : done.removed) gone[v] = 1;
  for (uint32_t v = 0; v < kN; ++v) {
    if (!gone[v]) sites.push_back(v);
  }
  EXPECT_EQ(FiniteEdges(done.mesh),
            FiniteEdges(BuildDelaunayWithCgal(to, sites)));
  // Rebuilt by the cost model once the regions have held their culprits.
  RegionStepPolicy costly = policy;
  costly.held_vertex_cost = 1e12;
  Run rebuilt = run(costly, nullptr);
  EXPECT_FALSE(rebuilt.ok);
  EXPECT_NE(rebuilt.reason.find("rebuilding is cheaper"), std::string::npos)
      << rebuilt.reason;
  EXPECT_EQ(FiniteEdges(rebuilt.mesh), before);
  // Stopped at the k-th poll, for k from the scan to the held vertices.
  int stops = 0;
  for (int k : {0, 1, 3, 10, 30, 60, 100, 200, 400}) {
    std::atomic<int> polls{0};
    CancelToken cancel([&] { return polls.fetch_add(1) >= k; },
                       CancelToken::Clock::time_point::max(),
                       CancelToken::Clock::duration::zero());
    Run stopped = run(policy, &cancel);
    if (stopped.ok) continue;  // past the last poll
    ++stops;
    EXPECT_TRUE(stopped.stats.cancelled) << k << ": " << stopped.reason;
    EXPECT_EQ(FiniteEdges(stopped.mesh), before) << k;
  }
  EXPECT_GE(stops, 3);
}

// The Delaunay mesh of n uniform points (*pos) in spatial order, triangles
// sorted, as Triangulation keeps them: regions then hold whole stars.
Mesh SpatiallyOrderedMesh(size_t n, uint64_t seed, std::vector<Vec2>* pos) {
  const std::vector<Vec2> raw = testing::UniformPoints(n, seed);
  pos->clear();
  for (uint32_t i : HilbertOrder(raw)) pos->push_back(raw[i]);
  Mesh mesh = BuildDelaunayWithCgal(*pos, AllSites(n));
  mesh.SortTrianglesByVertex();
  return mesh;
}

// The apexes across every half-edge that the region executor keeps from
// one step to the next (filled by a dense scan, refreshed by every flip,
// unflip and removal) are the mesh's after every step that keeps them, and
// a step that reads them makes the same mesh as one that fills them
// afresh: dense steps, small and large (held vertices), a sparse one, one
// after the mesh was touched elsewhere, and one whose held vertices are
// removed.
TEST(RegionExecutor, KeepsTheApexesAcrossEachEdge) {
  constexpr size_t kN = 3000;
  std::vector<Vec2> pos;
  Mesh kept = SpatiallyOrderedMesh(kN, 12, &pos);
  Mesh fresh = kept;
  RegionExecutor keeper;
  RegionStepPolicy policy;
  policy.region_triangles = 256;
  policy.keep_across_flips = 1;  // whatever the step flips
  std::mt19937_64 rng(9);
  const double spacing = 1.0 / std::sqrt(double(kN));
  struct StepCase {
    const char* name;
    double sigma;     // in mean spacings
    double fraction;  // of the vertices that move
    int max_halvings;
    bool touch_before;  // the mesh is written elsewhere first
  };
  const StepCase cases[] = {
      {"small, fills", 0.05, 1.0, 8, false},
      {"small, reads", 0.05, 1.0, 8, false},
      {"sparse", 0.3, 0.02, 8, false},
      {"after a touch", 0.05, 1.0, 8, true},
      {"held vertices removed", 0.15, 1.0, 0, false},
  };
  uint32_t held = 0, removed_total = 0;
  for (const StepCase& c : cases) {
    SCOPED_TRACE(c.name);
    if (c.touch_before) {
      (void)kept.view();
      EXPECT_FALSE(keeper.KeepsAcross(kept));
    }
    std::normal_distribution<double> g(0.0, c.sigma * spacing);
    std::uniform_real_distribution<double> u(0.0, 1.0);
    std::vector<Vec2> to = pos;
    std::vector<uint32_t> moved;
    for (uint32_t v = 0; v < kN; ++v) {
      if (u(rng) >= c.fraction) continue;
      to[v] = {to[v].x + g(rng), to[v].y + g(rng)};
      moved.push_back(v);
    }
    RegionStepPolicy pol = policy;
    pol.max_halvings = c.max_halvings;
    auto step = [&](RegionExecutor& x, Mesh& mesh, RegionStepStats* stats,
                    std::vector<uint32_t>* removed) {
      std::vector<Vec2> work = to;
      std::vector<uint32_t> hints(kN, kNoVertex);
      std::string reason;
      const bool ok =
          x.Step(mesh, pos, work, moved, pol, stats, removed, &hints, &reason);
      EXPECT_TRUE(ok) << reason;
      return ok;
    };
    RegionStepStats stats, fresh_stats;
    std::vector<uint32_t> removed, fresh_removed;
    ASSERT_TRUE(step(keeper, kept, &stats, &removed));
    RegionExecutor once;
    ASSERT_TRUE(step(once, fresh, &fresh_stats, &fresh_removed));
    EXPECT_TRUE(keeper.KeepsAcross(kept));
    EXPECT_TRUE(keeper.CheckAcross(kept).ok()) << keeper.CheckAcross(kept);
    EXPECT_EQ(kept.origin(), fresh.origin());
    EXPECT_EQ(kept.twin(), fresh.twin());
    EXPECT_EQ(removed, fresh_removed);
    held += stats.held;
    removed_total += static_cast<uint32_t>(removed.size());
    std::vector<uint8_t> gone(kN, 0);
    for (uint32_t v : removed) gone[v] = 1;
    std::vector<uint32_t> sites;
    for (uint32_t v = 0; v < kN; ++v) {
      if (!gone[v]) sites.push_back(v);
    }
    EXPECT_EQ(FiniteEdges(kept), FiniteEdges(BuildDelaunayWithCgal(to, sites)));
    if (!removed.empty()) break;  // the rest would need re-insertion
    pos = to;
  }
  EXPECT_GT(held, 0u);
  EXPECT_GT(removed_total, 0u);
}

// The array is dropped after a step that flips more than
// keep_across_flips of the triangles; the next dense step then reads the
// mesh, and the one after a step that flipped little fills it again.
TEST(RegionExecutor, DropsTheApexesAcrossAfterManyFlips) {
  constexpr size_t kN = 3000;
  std::vector<Vec2> pos;
  Mesh mesh = SpatiallyOrderedMesh(kN, 13, &pos);
  RegionExecutor x;
  RegionStepPolicy policy;
  policy.region_triangles = 256;
  policy.max_halvings = 60;  // nothing removed
  policy.keep_across_flips = 0.05;
  std::mt19937_64 rng(3);
  const double spacing = 1.0 / std::sqrt(double(kN));
  const std::vector<uint32_t> moved = AllSites(kN);
  struct Expect {
    double sigma;
    bool read_kept;   // the step's scan read kept entries
    bool kept_after;  // they are kept for the next step
  };
  const Expect steps[] = {
      {0.01, false, true},   // fills them (few flips)
      {0.3, true, false},    // reads them, flips many: dropped
      {0.01, false, false},  // reads the mesh; flips few again
      {0.01, false, true},   // fills them
      {0.01, true, true},    // reads them
  };
  for (size_t s = 0; s < std::size(steps); ++s) {
    SCOPED_TRACE(s);
    std::normal_distribution<double> g(0.0, steps[s].sigma * spacing);
    std::vector<Vec2> to = pos;
    for (Vec2& p : to) p = {p.x + g(rng), p.y + g(rng)};
    std::vector<Vec2> work = to;
    std::vector<uint32_t> removed, hints(kN, kNoVertex);
    RegionStepStats stats;
    std::string reason;
    ASSERT_TRUE(x.Step(mesh, pos, work, moved, policy, &stats, &removed, &hints,
                       &reason))
        << reason;
    ASSERT_TRUE(removed.empty());
    const uint64_t flips = stats.flips.interior_fix + stats.flips.hull_absorb +
                           stats.flips.hull_release + stats.flips.delaunay;
    EXPECT_EQ(flips > 0.05 * mesh.num_triangles(), steps[s].sigma > 0.1)
        << flips;
    EXPECT_EQ(stats.across_kept, steps[s].read_kept);
    EXPECT_EQ(x.KeepsAcross(mesh), steps[s].kept_after);
    EXPECT_TRUE(x.CheckAcross(mesh).ok()) << x.CheckAcross(mesh);
    EXPECT_EQ(FiniteEdges(mesh),
              FiniteEdges(BuildDelaunayWithCgal(to, AllSites(kN))));
    pos = to;
  }
}

TEST(MeshScan, FindsWhatTheRulesFind) {
  std::mt19937_64 rng(11);
  struct Case {
    const char* name;
    std::vector<Vec2> pts;
  };
  std::vector<Case> cases = {
      {"uniform", testing::UniformPoints(3000, 5)},
      {"clustered", testing::ClusteredPoints(3000, 6)},
      {"lattice", testing::Lattice(40)},  // every quad cocircular
      // Cocircular too, but with coordinates whose differences round: the
      // floating-point determinants are noise that only the error bounds
      // keep from deciding.
      {"lattice, rounded", Shifted(testing::Lattice(40, 0.1), 1e3)},
      {"huge", testing::UniformPoints(2000, 7, 1e25)},
      {"tiny", testing::UniformPoints(2000, 8, 1e-25)},
      {"offset", testing::UniformPoints(2000, 9, 1e-6, 1e6)},
  };
  for (const Case& c : cases) {
    SCOPED_TRACE(c.name);
    Mesh mesh = BuildDelaunayWithCgal(c.pts, AllSites(c.pts.size()));
    // Unmoved: valid and Delaunay (the lattice only by the perturbation,
    // so every one of its tests reaches the exact predicate).
    ExpectScanMatchesRules(mesh, c.pts);
    const double spacing =
        std::sqrt(MeshScanTestArea(c.pts) / double(c.pts.size()));
    for (double sigma : {1e-3, 0.1, 1.0}) {
      std::normal_distribution<double> g(0.0, sigma * spacing);
      std::vector<Vec2> moved = c.pts;
      for (Vec2& p : moved) p = {p.x + g(rng), p.y + g(rng)};
      ExpectScanMatchesRules(mesh, moved);
    }
    // Exact degeneracies after a move: every other point of the lattice
    // moves onto its right neighbour's column (collinear, cocircular and
    // coincident-with-a-circle cases).
    std::vector<Vec2> snapped = c.pts;
    for (size_t i = 0; i < snapped.size(); i += 2) {
      snapped[i].x = snapped[(i + 1) % snapped.size()].x;
    }
    ExpectScanMatchesRules(mesh, snapped);
  }
  {
    // A rotated lattice's mesh with its points shifted: rounding moves them
    // off their circles by an ulp or so, in either direction, so many
    // diagonals become illegal by margins the floating-point determinants
    // cannot see.
    SCOPED_TRACE("rotated lattice shifted after the build");
    std::vector<Vec2> pts;
    for (const Vec2& p : testing::Lattice(40, 0.1)) {
      pts.push_back({0.8 * p.x - 0.6 * p.y, 0.6 * p.x + 0.8 * p.y});
    }
    Mesh mesh = BuildDelaunayWithCgal(pts, AllSites(pts.size()));
    const std::vector<Vec2> shifted = Shifted(pts, 0.5);
    ExpectScanMatchesRules(mesh, shifted);
  }
  // Free slots are skipped.
  const auto pts = testing::UniformPoints(500, 10);
  Mesh mesh = BuildDelaunayWithCgal(pts, AllSites(pts.size()));
  std::vector<uint32_t> touched;
  ASSERT_TRUE(VertexOps::Remove(mesh, pts, 17, &touched, nullptr));
  ASSERT_TRUE(mesh.has_free_triangles());
  ExpectScanMatchesRules(mesh, pts);
}

class VertexOpsTest : public ::testing::TestWithParam<int> {};

TEST_P(VertexOpsTest, RemoveAndInsertMatchCgal) {
  const auto pts = GetParam() == 0 ? testing::UniformPoints(500, 4)
                                   : testing::ClusteredPoints(500, 5);
  Mesh mesh = BuildDelaunayWithCgal(pts, AllSites(pts.size()));
  uint32_t hint_ghost = 0;
  ASSERT_TRUE(HullWindsOnceFrom(mesh, pts, &hint_ghost));
  // Remove interior and hull vertices, legalize, compare with CGAL.
  std::vector<uint32_t> removed;
  for (uint32_t v = 0; v < pts.size(); v += 37) removed.push_back(v);
  const MeshView m = mesh.view();
  for (uint32_t t = 0; t < mesh.num_triangles() && removed.size() < 20; ++t) {
    if (m.IsGhost(t)) {  // a hull vertex too
      const uint32_t s = rules::SpokeOf(m, t);
      if (std::find(removed.begin(), removed.end(), m.origin[s]) ==
          removed.end()) {
        removed.push_back(m.origin[s]);
      }
    }
  }
  for (uint32_t v : removed) {
    std::vector<uint32_t> touched;
    ASSERT_TRUE(VertexOps::Remove(mesh, pts, v, &touched, nullptr)) << v;
    RegionExecutor::LegalizeSerial(mesh, pts, touched, nullptr);
  }
  std::vector<uint32_t> kept;
  for (uint32_t v = 0; v < pts.size(); ++v) {
    if (std::find(removed.begin(), removed.end(), v) == removed.end()) {
      kept.push_back(v);
    }
  }
  EXPECT_EQ(FiniteEdges(mesh), FiniteEdges(BuildDelaunayWithCgal(pts, kept)));
  ExpectConsistent(mesh);
  // Insert them again: locate, split, fix, legalize.
  for (uint32_t v : removed) {
    uint32_t start = 0;
    while (mesh.view().IsFree(start)) ++start;
    const auto loc = VertexOps::Locate(mesh, pts, pts[v], start);
    ASSERT_NE(loc.triangle, kNoEdge);
    ASSERT_EQ(loc.coincident, kNoVertex);
    const auto tris = VertexOps::Split(mesh, loc.triangle, v);
    std::vector<uint32_t> touched(tris.begin(), tris.end());
    const std::vector<uint32_t> just = {v};
    const std::vector<uint32_t> bad =
        KineticExecutor::FindInvalidTriangles(mesh, pts, &just);
    ASSERT_TRUE(RegionExecutor::FixSerial(mesh, pts, bad, nullptr, &touched,
                                          nullptr, nullptr));
    for (uint32_t t : KineticExecutor::TrianglesAround(mesh, {v})) {
      touched.push_back(t);
    }
    RegionExecutor::LegalizeSerial(mesh, pts, touched, nullptr);
  }
  EXPECT_EQ(FiniteEdges(mesh),
            FiniteEdges(BuildDelaunayWithCgal(pts, AllSites(pts.size()))));
  ExpectConsistent(mesh);
  EXPECT_TRUE(HullWindsOnceFrom(mesh, pts, &hint_ghost));
}

INSTANTIATE_TEST_SUITE_P(UniformAndClustered, VertexOpsTest,
                         ::testing::Values(0, 1));

}  // namespace
}  // namespace kinetri::core
