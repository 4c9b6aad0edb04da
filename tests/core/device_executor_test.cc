// The device executor (core/device/): its emulated backend runs the same
// CCCL source on CPU threads (built with KINETRI_TEST_CUDA, the same tests
// run on the CUDA backend: device_executor_cuda_test, on a machine with a
// GPU). It follows the round executor's schedule, so
// the two must build the same mesh down to the numbering of half-edges; it
// keeps the mesh resident across steps (only positions go up once it is in
// sync); and the CUDA backend is refused cleanly where there is no GPU.
#include "core/device/device_executor.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdio>
#include <functional>
#include <optional>
#include <random>
#include <string>
#include <utility>
#include <vector>

#if defined(KINETRI_TEST_CUDA)
#include <cuda_runtime.h>

#include <chrono>
#include <thread>
#endif

#include "core/cancel.h"
#include "core/cgal_builder.h"
#include "core/device/checks.h"
#include "core/mesh.h"
#include "core/predicates.h"
#include "core/queries.h"
#include "core/triangulation.h"
#include "tests/core/test_util.h"

namespace kinetri::core {
namespace {

using device::DeviceBackend;
using testing::Brownian;

#if defined(KINETRI_TEST_CUDA)
constexpr DeviceBackend kBackend = DeviceBackend::kCuda;
#else
constexpr DeviceBackend kBackend = DeviceBackend::kEmulated;
#endif

TriangulationOptions DeviceOptions(int threads = 0) {
  TriangulationOptions o;
  o.executor = Executor::kDevice;
  o.device_backend = kBackend;
  o.num_threads = threads;
  return o;
}

void ExpectSameMesh(const Triangulation& a, const Triangulation& b,
                    const std::string& where) {
  const TriangulationView va = a.view(), vb = b.view();
  ASSERT_EQ(va.mesh.num_half_edges, vb.mesh.num_half_edges) << where;
  for (uint32_t e = 0; e < va.mesh.num_half_edges; ++e) {
    ASSERT_EQ(va.mesh.origin[e], vb.mesh.origin[e]) << where << " e " << e;
    ASSERT_EQ(va.mesh.twin[e], vb.mesh.twin[e]) << where << " e " << e;
  }
  ASSERT_EQ(va.num_points, vb.num_points) << where;
  for (uint32_t v = 0; v < va.num_points; ++v) {
    ASSERT_EQ(va.vertex_edge[v], vb.vertex_edge[v]) << where << " v " << v;
  }
}

// Same input, same schedule: the emulated device executor and the round
// executor (core/kinetic.cc) produce identical meshes and flip counts, on
// uniform, clustered and duplicated points, small and large motion.
TEST(DeviceExecutor, EqualsTheRoundExecutorHalfEdgeForHalfEdge) {
  struct Case {
    const char* name;
    std::vector<Vec2> pts;
    double sigma;  // in mean spacings
  };
  const std::vector<Case> cases = {
      {"uniform small", testing::UniformPoints(3000, 1), 0.05},
      {"uniform large", testing::UniformPoints(3000, 2), 0.5},
      {"clustered", testing::ClusteredPoints(3000, 3), 0.3},
      {"duplicates", testing::WithDuplicates(1500, 3, 4), 0.2},
  };
  uint64_t held = 0;
  for (const Case& c : cases) {
    TriangulationOptions rounds_opt;
    rounds_opt.executor = Executor::kRounds;
    auto rounds = Triangulation::Create(c.pts, rounds_opt);
    auto dev = Triangulation::Create(c.pts, DeviceOptions());
    ASSERT_TRUE(rounds.ok() && dev.ok());
    std::mt19937_64 rng(7);
    const double spacing = 1.0 / std::sqrt(double(c.pts.size()));
    for (int s = 0; s < 6; ++s) {
      const DisplacementBatch b =
          Brownian(c.pts.size(), c.sigma * spacing, rng);
      auto rr = rounds->ApplyDisplacements(b);
      auto rd = dev->ApplyDisplacements(b);
      ASSERT_TRUE(rr.ok() && rd.ok()) << rr.status() << rd.status();
      const std::string where =
          std::string(c.name) + " step " + std::to_string(s);
      EXPECT_EQ(rr->path, rd->path) << where << ": " << rd->fallback_reason;
      EXPECT_EQ(rr->flips.interior_fix, rd->flips.interior_fix) << where;
      EXPECT_EQ(rr->flips.hull_absorb, rd->flips.hull_absorb) << where;
      EXPECT_EQ(rr->flips.hull_release, rd->flips.hull_release) << where;
      EXPECT_EQ(rr->flips.delaunay, rd->flips.delaunay) << where;
      EXPECT_EQ(rr->flips.fix_rounds, rd->flips.fix_rounds) << where;
      EXPECT_EQ(rr->flips.legalize_rounds, rd->flips.legalize_rounds) << where;
      EXPECT_EQ(rr->failed_attempts, rd->failed_attempts) << where;
      // The same vertices held back inside fixing (hold_culprits).
      EXPECT_EQ(rr->held_vertices, rd->held_vertices) << where;
      held += rd->held_vertices;
      EXPECT_EQ(rd->device_resyncs, 0u) << where;
      ExpectSameMesh(*rounds, *dev, where);
      ASSERT_TRUE(dev->Validate().ok()) << where << dev->Validate();
      EXPECT_EQ(testing::EdgesAsPositions(*dev),
                testing::CgalDelaunayEdges(dev->Positions()))
          << where;
    }
  }
  EXPECT_GT(held, 0u);  // the hold-back ran, on both
}

// The host waits for the device only where it reads a result: twice per
// legalizing round (the candidates' count, the next worklist's), five
// times per fixing round, and a few times per attempt (first worklists,
// hull check, flip counts); every other algorithm returns without waiting
// on the CUDA backend. (The emulated backend counts the same calls.)
TEST(DeviceExecutor, HostWaitsTwicePerLegalizingRound) {
  const size_t n = 3000;
  auto t =
      Triangulation::Create(testing::UniformPoints(n, 21), DeviceOptions());
  ASSERT_TRUE(t.ok()) << t.status();
  std::mt19937_64 rng(22);
  const double spacing = 1.0 / std::sqrt(double(n));
  int checked = 0;
  for (double sigma : {0.01, 0.02, 0.03, 0.05, 0.1}) {
    auto r = t->ApplyDisplacements(Brownian(n, sigma * spacing, rng));
    ASSERT_TRUE(r.ok()) << r.status();
    if (r->path != UpdatePath::kLocal || r->failed_attempts != 0) continue;
    ++checked;
    const uint64_t rounds = r->flips.legalize_rounds;
    ASSERT_GT(rounds, 0u);
    EXPECT_LE(r->device_waits, 2 * rounds + 5 * r->flips.fix_rounds + 12)
        << "sigma " << sigma;
    // Most calls of a round do not wait.
    EXPECT_GE(r->device_calls, 3 * r->device_waits) << "sigma " << sigma;
    std::printf(
        "sigma %.2f: %u fixing and %u legalizing rounds, %llu device calls, "
        "%llu waited for\n",
        sigma, r->flips.fix_rounds, r->flips.legalize_rounds,
        static_cast<unsigned long long>(r->device_calls),
        static_cast<unsigned long long>(r->device_waits));
  }
  EXPECT_GT(checked, 0);
}

// The tail of legalizing runs in device loops (device::LoopControl): the
// host reads one word per `rounds_per_check` rounds instead of waiting
// twice per round, and the mesh is the same whatever the settings: the
// host driving every round (capacity 0), the defaults, a capacity so small
// that worklists keep outgrowing the loop and go back to the host, and a
// loop that takes every worklist. Each is compared with the round executor
// half-edge for half-edge, with its flip and round counts.
TEST(DeviceExecutor, DeviceLoopsLeaveTheMeshAsTheHostRoundsDo) {
  struct Setting {
    const char* name;
    device::LoopControl control;
  };
  const std::vector<Setting> settings = {
      {"host rounds", {0, 8}},
      {"defaults", device::DefaultLoopControl(kBackend)},
      {"capacity 7, check every 2", {7, 2}},
      {"every worklist, check every round", {1u << 22, 1}},
      {"every worklist, check every 16", {1u << 22, 16}},
  };
  const size_t n = 3000;
  const auto pts = testing::UniformPoints(n, 61);
  // Without hold-back inside fixing (RoundStepPolicy::hold_culprits): with
  // it, no legalizing worklist of these steps outgrows the small capacity
  // below, and handing a loop back is what that setting tests.
  TriangulationOptions rounds_opt;
  rounds_opt.executor = Executor::kRounds;
  rounds_opt.round.hold_culprits = false;
  auto rounds = Triangulation::Create(pts, rounds_opt);
  ASSERT_TRUE(rounds.ok());
  std::vector<Triangulation> devs;
  for (const Setting& s : settings) {
    TriangulationOptions device_opt = DeviceOptions();
    device_opt.round.hold_culprits = false;
    auto t = Triangulation::Create(pts, device_opt);
    ASSERT_TRUE(t.ok()) << t.status();
    t->device_executor()->set_loop_control(s.control);
    EXPECT_EQ(t->device_executor()->loop_control().capacity,
              s.control.capacity);
    devs.push_back(*std::move(t));
  }
  std::vector<uint64_t> loop_rounds(settings.size(), 0);
  std::vector<uint64_t> returns(settings.size(), 0);
  std::vector<uint64_t> waits(settings.size(), 0);
  std::mt19937_64 rng(62);
  const double spacing = 1.0 / std::sqrt(double(n));
  int s = 0;
  for (double sigma : {0.02, 0.1, 0.3, 0.05, 0.5, 0.2}) {
    const DisplacementBatch b = Brownian(n, sigma * spacing, rng);
    auto rr = rounds->ApplyDisplacements(b);
    ASSERT_TRUE(rr.ok()) << rr.status();
    for (size_t k = 0; k < settings.size(); ++k) {
      const std::string where = std::string(settings[k].name) + ", step " +
                                std::to_string(s) + ", sigma " +
                                std::to_string(sigma);
      auto rd = devs[k].ApplyDisplacements(b);
      ASSERT_TRUE(rd.ok()) << rd.status();
      EXPECT_EQ(rr->path, rd->path) << where;
      EXPECT_EQ(rr->flips.delaunay, rd->flips.delaunay) << where;
      EXPECT_EQ(rr->flips.legalize_rounds, rd->flips.legalize_rounds) << where;
      EXPECT_EQ(rr->failed_attempts, rd->failed_attempts) << where;
      ExpectSameMesh(*rounds, devs[k], where);
      EXPECT_LE(rd->device_loop_rounds, rd->flips.legalize_rounds) << where;
      loop_rounds[k] += rd->device_loop_rounds;
      returns[k] += rd->device_loop_returns;
      waits[k] += rd->device_waits;
      if (settings[k].control.capacity >= (1u << 22) &&
          rd->path == UpdatePath::kLocal && rd->failed_attempts == 0) {
        // Every legalizing round ran in the loop: one wait per check (and
        // one more for the check that found it done), besides the fixing
        // rounds' and the attempt's own.
        EXPECT_EQ(rd->device_loop_rounds, rd->flips.legalize_rounds) << where;
        const uint64_t per = settings[k].control.rounds_per_check;
        EXPECT_LE(rd->device_waits, rd->device_loop_rounds / per + 2 +
                                        5 * rd->flips.fix_rounds + 12)
            << where;
      }
    }
    EXPECT_EQ(testing::EdgesAsPositions(*rounds),
              testing::CgalDelaunayEdges(rounds->Positions()));
    ++s;
  }
  for (size_t k = 0; k < settings.size(); ++k) {
    std::printf(
        "%s: %llu rounds in device loops, %llu handed back, %llu "
        "waits\n",
        settings[k].name, static_cast<unsigned long long>(loop_rounds[k]),
        static_cast<unsigned long long>(returns[k]),
        static_cast<unsigned long long>(waits[k]));
  }
  EXPECT_EQ(loop_rounds[0], 0u);  // capacity 0: the host drives every round
  for (size_t k = 1; k < settings.size(); ++k) {
    EXPECT_GT(loop_rounds[k], 0u) << settings[k].name;
    EXPECT_LT(waits[k], waits[0]) << settings[k].name;
  }
  EXPECT_GT(returns[2], 0u);  // the small capacity went back to the host
  EXPECT_EQ(returns[3], 0u);  // the large ones never did
  EXPECT_EQ(returns[4], 0u);
  EXPECT_LT(waits[4], waits[3]);
}

// A step stopped while a device loop runs (the token is polled between
// checks) hands the loop's worklist back and forgets its marks: the step
// returns CANCELLED with the triangulation as it was, and the same step
// taken again afterwards ends at CGAL's triangulation (a mark left behind
// would drop an edge from a later worklist or flip a legal one).
TEST(DeviceExecutor, DeviceLoopStoppedAtAnyCheckLeavesNothingBehind) {
  const size_t n = 3000;
  auto t =
      Triangulation::Create(testing::UniformPoints(n, 71), DeviceOptions());
  ASSERT_TRUE(t.ok());
  t->device_executor()->set_loop_control({1u << 22, 1});
  std::mt19937_64 rng(72);
  const double spacing = 1.0 / std::sqrt(double(n));
  int stopped = 0, in_loop = 0;
  for (int k = 0; k < 60; k += 3) {
    const DisplacementBatch b = Brownian(n, 0.05 * spacing, rng);
    const std::vector<Vec2> before = t->Positions();
    std::atomic<int> polls{0};
    CancelToken cancel([&] { return polls.fetch_add(1) >= k; },
                       CancelToken::Clock::time_point::max(),
                       CancelToken::Clock::duration::zero());
    auto r = t->ApplyDisplacements(b, &cancel);
    if (!r.ok()) {
      ASSERT_EQ(r.status().code(), absl::StatusCode::kCancelled) << r.status();
      ++stopped;
      EXPECT_EQ(t->Positions(), before) << "poll " << k;
      ASSERT_TRUE(t->Validate().ok()) << "poll " << k;
      EXPECT_EQ(testing::EdgesAsPositions(*t),
                testing::CgalDelaunayEdges(t->Positions()))
          << "poll " << k;
      auto again = t->ApplyDisplacements(b);
      ASSERT_TRUE(again.ok()) << again.status();
      in_loop += again->device_loop_rounds > 0 ? 1 : 0;
    }
    ASSERT_TRUE(t->Validate().ok()) << "poll " << k;
    EXPECT_EQ(testing::EdgesAsPositions(*t),
              testing::CgalDelaunayEdges(t->Positions()))
        << "poll " << k;
  }
  EXPECT_GT(stopped, 5);
  EXPECT_GT(in_loop, 0);
}

// Sites 0..n-1 (every point its own site), for BuildDelaunayWithCgal.
std::vector<uint32_t> AllSites(size_t n) {
  std::vector<uint32_t> sites(n);
  for (uint32_t i = 0; i < n; ++i) sites[i] = i;
  return sites;
}

// The finite edges of a mesh as sorted vertex pairs.
std::vector<std::pair<uint32_t, uint32_t>> EdgeSet(const Mesh& m) {
  std::vector<std::pair<uint32_t, uint32_t>> out;
  const MeshView v = m.view();
  for (uint32_t e = 0; e < v.num_half_edges; ++e) {
    if (v.twin[e] == kNoEdge || e > v.twin[e]) continue;
    const uint32_t a = v.origin[e], b = v.origin[v.twin[e]];
    if (a == kInfiniteVertex || b == kInfiniteVertex || a == kNoVertex ||
        b == kNoVertex) {
      continue;
    }
    out.emplace_back(std::min(a, b), std::max(a, b));
  }
  std::sort(out.begin(), out.end());
  return out;
}

// The 8 nearest of each of the points `ids` (by id, itself excluded).
device::DeviceQuery KnnOfPoints(absl::Span<const uint32_t> ids) {
  device::DeviceQuery q;
  q.kind = device::DeviceQuery::Kind::kKNearest;
  q.by_ids = true;
  q.ids = ids;
  q.k = 8;
  q.exclude_self = true;
  return q;
}

// Takes the attempt to `to` again with `a`, and with a fresh executor from
// a copy of `m`: both must succeed and leave the same mesh, half-edge for
// half-edge. Returns `a`'s result (nullopt after a failure, reported).
// CGAL's Delaunay mesh of n uniform points, and an executor whose first
// attempt (for the same positions) made it the device's copy (an error
// status in `executor` when that failed).
struct ResidentMesh {
  ResidentMesh(size_t n, uint64_t seed)
      : pts(testing::UniformPoints(n, seed)),
        sites(AllSites(n)),
        mesh(BuildDelaunayWithCgal(pts, sites)),
        executor(device::MakeDeviceExecutor(kBackend)) {
    if (!executor.ok()) return;
    auto r =
        (*executor)->Attempt(mesh, pts, {}, nullptr, nullptr, 0.5, nullptr);
    if (!r.ok() || !r->fixed || r->resyncs != 0) {
      executor = absl::InternalError("the first attempt failed");
    }
  }
  std::vector<Vec2> pts;
  std::vector<uint32_t> sites;
  Mesh mesh;
  absl::StatusOr<std::unique_ptr<device::DeviceExecutor>> executor;
};

// Flips, on the host, the first interior edge at or after half-edge `from`
// whose quad is convex: still a triangulation of `pts`, no longer Delaunay
// (legalizing flips it back), and not the device's copy. Returns the edge,
// or kNoEdge when there is none (vertex_edge is left to the caller).
uint32_t FlipAConvexQuad(Mesh& m, const std::vector<Vec2>& pts, uint32_t from) {
  const MeshView v = m.view();
  for (uint32_t e = from; e < v.num_half_edges; ++e) {
    const uint32_t f = v.twin[e];
    if (e > f || v.IsGhost(e / 3) || v.IsGhost(f / 3)) continue;
    const Vec2 &pa = pts[v.origin[e]], &pb = pts[v.Dest(e)],
               &pc = pts[v.Apex(e)], &pd = pts[v.Across(e)];
    if (Orient2d(pc, pd, pa) < 0 && Orient2d(pd, pc, pb) < 0) {
      v.Flip(e);
      return e;
    }
  }
  return kNoEdge;
}

std::optional<device::DeviceAttempt> AgainAsAFreshExecutor(
    device::DeviceExecutor& a, Mesh& m, absl::Span<const Vec2> to,
    const std::string& where) {
  Mesh fresh_mesh = m;
  auto fresh = device::MakeDeviceExecutor(kBackend);
  if (!fresh.ok()) {
    ADD_FAILURE() << where << ": " << fresh.status();
    return std::nullopt;
  }
  auto again = a.Attempt(m, to, {}, nullptr, nullptr, 0.5, nullptr);
  auto other =
      (*fresh)->Attempt(fresh_mesh, to, {}, nullptr, nullptr, 0.5, nullptr);
  if (!again.ok() || !other.ok()) {
    ADD_FAILURE() << where << ": " << again.status() << other.status();
    return std::nullopt;
  }
  EXPECT_EQ(again->fixed, other->fixed) << where;
  EXPECT_EQ(again->counts.delaunay, other->counts.delaunay) << where;
  EXPECT_EQ(m.origin(), fresh_mesh.origin()) << where;
  EXPECT_EQ(m.twin(), fresh_mesh.twin()) << where;
  EXPECT_EQ(m.vertex_edge(), fresh_mesh.vertex_edge()) << where;
  return *std::move(again);
}

// The host names what it changed (ChangedOnHost): only those entries go
// up, and the result is what a fresh executor gives from the changed mesh.
// The names are a promise, trusted without a pass over the host mesh;
// with KINETRI_DEVICE_CHECK=1 (ctest sets it for the device suites, and
// runs this test without it too) each is checked by the fingerprint, and a
// change left out is caught (the whole mesh goes up: a resync). More
// changes than a patch holds send the whole mesh.
TEST(DeviceExecutor, ChangesNamedByTheHostGoUpAlone) {
  ResidentMesh res(2000, 52);
  ASSERT_TRUE(res.executor.ok()) << res.executor.status();
  auto& [pts, sites, m, a] = res;
  const uint64_t whole_mesh =
      8ull * m.num_half_edges() + 4ull * m.num_vertices();
  uint32_t from = 0;
  // 0: named with their neighbours and corners; 1: one triangle left out;
  // 2: every triangle named (more than a patch holds).
  const bool checked = device::DeviceChecksOn();
  for (int round = 0; round < 6; ++round) {
    const int how = round % 3;
    // (Trusted, a broken promise gives a wrong mesh: not tried.)
    if (how == 1 && !checked) continue;
    // Flip an interior edge whose quad is convex, on the host (legalizing
    // flips it back).
    const uint32_t flipped = FlipAConvexQuad(m, pts, from);
    ASSERT_NE(flipped, kNoEdge);
    from = flipped + 991;
    m.UpdateVertexEdgesAfterFlip(flipped);
    const MeshView v = std::as_const(m).view();
    std::vector<uint32_t> tris, verts;
    for (uint32_t t : {flipped / 3, v.twin[flipped] / 3}) {
      tris.push_back(t);
      for (uint32_t e = 3 * t; e < 3 * t + 3; ++e) {
        tris.push_back(v.twin[e] / 3);
        verts.push_back(v.origin[e]);
      }
    }
    if (how == 1) {
      tris.erase(std::remove(tris.begin(), tris.end(), flipped / 3),
                 tris.end());
    } else if (how == 2) {
      tris.clear();
      for (uint32_t t = 0; t < m.num_triangles(); ++t) tris.push_back(t);
    }
    // (Named in two calls: they add up.)
    (*a)->ChangedOnHost(absl::MakeConstSpan(tris).subspan(0, 2), {});
    (*a)->ChangedOnHost(absl::MakeConstSpan(tris).subspan(2), verts);
    const std::string where = "round " + std::to_string(round);
    const auto again = AgainAsAFreshExecutor(**a, m, pts, where);
    ASSERT_TRUE(again.has_value());
    ASSERT_TRUE(again->fixed) << where;
    EXPECT_GE(again->counts.delaunay, 1u) << where;
    // A pass where the names are checked or the whole mesh goes up.
    EXPECT_EQ(again->fingerprint_passes, checked || how == 2 ? 1u : 0u)
        << where;
    EXPECT_EQ(again->resyncs, how == 1 ? 1u : 0u) << where;
    EXPECT_EQ(again->patched_uploads, how == 0 ? 1u : 0u) << where;
    if (how == 0) {
      EXPECT_LT(again->bytes_uploaded, whole_mesh / 20) << where;
    } else {
      EXPECT_GE(again->bytes_uploaded, whole_mesh) << where;
    }
    EXPECT_EQ(EdgeSet(m), EdgeSet(BuildDelaunayWithCgal(pts, sites))) << where;
    // The device's copy is the host mesh: nothing to send, no pass.
    auto still = (*a)->Attempt(m, pts, {}, nullptr, nullptr, 0.5, nullptr);
    ASSERT_TRUE(still.ok() && still->fixed) << still.status();
    EXPECT_EQ(still->resyncs, 0u) << where;
    EXPECT_EQ(still->fingerprint_passes, 0u) << where;
    EXPECT_EQ(still->bytes_uploaded, 0u) << where;
  }
  // After Invalidate() named changes are ignored: the whole mesh goes up.
  (*a)->Invalidate();
  const uint32_t one = 0;
  (*a)->ChangedOnHost(absl::MakeConstSpan(&one, 1), {});
  (void)m.view();
  auto whole = (*a)->Attempt(m, pts, {}, nullptr, nullptr, 0.5, nullptr);
  ASSERT_TRUE(whole.ok() && whole->fixed) << whole.status();
  EXPECT_EQ(whole->patched_uploads, 0u);
  EXPECT_EQ(whole->resyncs, 0u);
  EXPECT_GE(whole->bytes_uploaded, whole_mesh);
}

// An attempt stopped inside a device loop (the token is polled between
// checks) leaves the mesh as it was and no mark behind: taken again, the
// attempt gives the mesh a fresh executor gives, half-edge for half-edge.
TEST(DeviceExecutor, AttemptStoppedInsideADeviceLoopLeavesNoMark) {
  const size_t n = 3000;
  std::vector<Vec2> pts = testing::UniformPoints(n, 91);
  const std::vector<uint32_t> sites = AllSites(n);
  auto a = device::MakeDeviceExecutor(kBackend);
  ASSERT_TRUE(a.ok());
  (*a)->set_loop_control({1u << 22, 1});
  Mesh m = BuildDelaunayWithCgal(pts, sites);
  std::mt19937_64 rng(92);
  std::normal_distribution<double> g(0.0, 0.002 / std::sqrt(double(n)));
  int stopped_in_loop = 0;
  for (int k = 0; k < 40; ++k) {
    std::vector<Vec2> to = pts;
    for (Vec2& p : to) {
      p.x += g(rng);
      p.y += g(rng);
    }
    const auto before = EdgeSet(m);
    std::atomic<int> polls{0};
    CancelToken cancel([&] { return polls.fetch_add(1) >= k; },
                       CancelToken::Clock::time_point::max(),
                       CancelToken::Clock::duration::zero());
    auto r = (*a)->Attempt(m, to, {}, nullptr, nullptr, 0.5, &cancel);
    ASSERT_TRUE(r.ok()) << r.status();
    if (!r->cancelled) continue;  // fixed, or stuck before any poll fired
    stopped_in_loop += r->loop_rounds > 0 ? 1 : 0;
    EXPECT_EQ(EdgeSet(m), before) << "poll " << k;
    // Again without a token, and on a fresh executor from the same mesh.
    const auto again =
        AgainAsAFreshExecutor(**a, m, to, "poll " + std::to_string(k));
    ASSERT_TRUE(again.has_value());
    if (again->fixed) {
      EXPECT_EQ(EdgeSet(m), EdgeSet(BuildDelaunayWithCgal(to, sites)));
      pts = to;
    }
  }
  EXPECT_GE(stopped_in_loop, 3);
}

// A device call that fails (exhausted memory, or an error of the CUDA
// system; injected at calls spread over whole attempts: uploads, fixing
// and legalizing rounds, the hull check, the download) ends the attempt
// with RESOURCE_EXHAUSTED or INTERNAL and leaves the host mesh exactly as
// it was; the same executor then takes the step as a fresh one does, half-
// edge for half-edge.
TEST(DeviceExecutor, AFailedDeviceCallLeavesTheMeshAsItWas) {
  const size_t n = 2000;
  std::vector<Vec2> pts = testing::UniformPoints(n, 71);
  const std::vector<uint32_t> sites = AllSites(n);
  std::mt19937_64 rng(72);
  std::normal_distribution<double> g(0.0, 0.3 / std::sqrt(double(n)));
  auto moved = [&] {
    std::vector<Vec2> to = pts;
    for (Vec2& p : to) {
      p.x += g(rng);
      p.y += g(rng);
    }
    return to;
  };
  // How many device calls an attempt on a fresh executor makes.
  uint64_t calls = 0;
  {
    Mesh m = BuildDelaunayWithCgal(pts, sites);
    auto probe = device::MakeDeviceExecutor(kBackend);
    ASSERT_TRUE(probe.ok());
    auto r = (*probe)->Attempt(m, moved(), {}, nullptr, nullptr, 0.5, nullptr);
    ASSERT_TRUE(r.ok()) << r.status();
    calls = r->device_calls;
  }
  ASSERT_GT(calls, 20u);
  Mesh m = BuildDelaunayWithCgal(pts, sites);
  auto a = device::MakeDeviceExecutor(kBackend);
  ASSERT_TRUE(a.ok());
  using Kind = device::DeviceFault::Kind;
  int fired = 0;
  for (const Kind kind : {Kind::kOutOfMemory, Kind::kError}) {
    for (const double at : {0.0, 0.05, 0.2, 0.4, 0.6, 0.8, 0.95, 0.99}) {
      const std::string where =
          std::string(kind == Kind::kOutOfMemory ? "out of memory" : "error") +
          " at " + std::to_string(at);
      const std::vector<Vec2> to = moved();
      const std::vector<uint32_t> origin = m.origin(), twin = m.twin(),
                                  vertex_edge = m.vertex_edge();
      (*a)->InjectFault({kind, static_cast<uint64_t>(at * double(calls))});
      auto r = (*a)->Attempt(m, to, {}, nullptr, nullptr, 0.5, nullptr);
      if ((*a)->fault_armed()) {  // the attempt made fewer calls
        (*a)->InjectFault({});
        ASSERT_TRUE(r.ok()) << where << ": " << r.status();
      } else {
        ++fired;
        ASSERT_FALSE(r.ok()) << where;
        EXPECT_EQ(r.status().code(), kind == Kind::kOutOfMemory
                                         ? absl::StatusCode::kResourceExhausted
                                         : absl::StatusCode::kInternal)
            << where << ": " << r.status();
        EXPECT_EQ(m.origin(), origin) << where;
        EXPECT_EQ(m.twin(), twin) << where;
        EXPECT_EQ(m.vertex_edge(), vertex_edge) << where;
      }
      // Again on the same executor, and on a fresh one from the same mesh.
      const auto again = AgainAsAFreshExecutor(**a, m, to, where);
      ASSERT_TRUE(again.has_value());
      if (again->fixed) {
        EXPECT_EQ(EdgeSet(m), EdgeSet(BuildDelaunayWithCgal(to, sites)))
            << where;
        pts = to;
      } else {
        m = BuildDelaunayWithCgal(pts, sites);  // stuck: start over
        (*a)->Invalidate();
      }
    }
  }
  EXPECT_GE(fired, 12);
}

// The executor keeps the host mesh on the device between attempts and
// trusts the caller to Invalidate() after changing it; a caller that
// forgets is caught by the mesh's fingerprint: the attempt uploads the
// mesh again (resyncs 1) and gives what a fresh executor gives from the
// changed mesh. Told, it does not count a resync.
TEST(DeviceExecutor, AMeshChangedBehindItsBackIsUploadedAgain) {
  // The points stay where they are: each round's host change is one flip
  // to the other diagonal of a convex quad, which legalizing flips back.
  ResidentMesh res(2000, 51);
  ASSERT_TRUE(res.executor.ok()) << res.executor.status();
  auto& [pts, sites, m, a] = res;
  uint32_t from = 0;
  for (int round = 0; round < 4; ++round) {
    // Flip an interior edge whose quad is convex, on the host: still a
    // triangulation of the points, no longer Delaunay, and not the
    // device's copy.
    const uint32_t flipped = FlipAConvexQuad(m, pts, from);
    ASSERT_NE(flipped, kNoEdge);
    from = flipped + 997;
    m.RebuildVertexEdges();
    const bool tell = round % 2 == 1;
    if (tell) (*a)->Invalidate();
    const std::string where = "round " + std::to_string(round);
    const auto again = AgainAsAFreshExecutor(**a, m, pts, where);
    ASSERT_TRUE(again.has_value());
    EXPECT_EQ(again->resyncs, tell ? 0u : 1u) << where;
    // The host wrote: the attempt checked the mesh by a pass over it.
    EXPECT_EQ(again->fingerprint_passes, 1u) << where;
    ASSERT_TRUE(again->fixed) << where;
    EXPECT_GE(again->counts.delaunay, 1u) << where;
    EXPECT_EQ(EdgeSet(m), EdgeSet(BuildDelaunayWithCgal(pts, sites))) << round;
    // Nothing changed since: no resync.
    auto still = (*a)->Attempt(m, pts, {}, nullptr, nullptr, 0.5, nullptr);
    ASSERT_TRUE(still.ok() && still->fixed) << still.status();
    EXPECT_EQ(still->resyncs, 0u) << round;
    // ... and it knows so without a pass over the host mesh.
    EXPECT_EQ(still->fingerprint_passes, 0u) << round;
  }
  // A writing view that writes nothing costs the pass, not an upload.
  (void)m.view();
  auto viewed = (*a)->Attempt(m, pts, {}, nullptr, nullptr, 0.5, nullptr);
  ASSERT_TRUE(viewed.ok() && viewed->fixed) << viewed.status();
  EXPECT_EQ(viewed->fingerprint_passes, 1u);
  EXPECT_EQ(viewed->resyncs, 0u);
  EXPECT_EQ(viewed->bytes_uploaded, 0u);
  // A copy of the mesh (equal contents, the same content_version()) is
  // the device's copy too; once it writes, it is checked and uploaded.
  Mesh copy = m;
  auto on_copy = (*a)->Attempt(copy, pts, {}, nullptr, nullptr, 0.5, nullptr);
  ASSERT_TRUE(on_copy.ok() && on_copy->fixed) << on_copy.status();
  EXPECT_EQ(on_copy->fingerprint_passes, 0u);
  ASSERT_NE(FlipAConvexQuad(copy, pts, 0), kNoEdge);
  copy.RebuildVertexEdges();
  auto changed = (*a)->Attempt(copy, pts, {}, nullptr, nullptr, 0.5, nullptr);
  ASSERT_TRUE(changed.ok() && changed->fixed) << changed.status();
  EXPECT_EQ(changed->fingerprint_passes, 1u);
  EXPECT_EQ(changed->resyncs, 1u);
  EXPECT_EQ(EdgeSet(copy), EdgeSet(BuildDelaunayWithCgal(pts, sites)));
}

// A session's steps check the host mesh by a pass over it only after the
// host changed it (its first step, re-insertions, rebuilds, renumbering,
// held vertices moved on the host): steps that stay on the device do not.
TEST(DeviceExecutor, StepsOnTheDeviceDoNotPassOverTheHostMesh) {
  const size_t n = 3000;
  std::mt19937_64 rng(61);
  TriangulationOptions o = DeviceOptions();
  auto t = Triangulation::Create(testing::UniformPoints(n, 61), o);
  ASSERT_TRUE(t.ok()) << t.status();
  const double sigma = 0.02 / std::sqrt(double(n));
  uint64_t steps_on_device = 0;
  bool host_changed = true;  // the first step uploads the mesh
  // ... which is checked by a pass unless it was only re-insertions,
  // named (ChangedOnHost) and trusted without KINETRI_DEVICE_CHECK=1.
  bool only_named = false;
  for (int s = 0; s < 12; ++s) {
    auto r = t->ApplyDisplacements(Brownian(n, sigma, rng));
    ASSERT_TRUE(r.ok()) << r.status();
    const std::string where = "step " + std::to_string(s);
    EXPECT_EQ(r->device_resyncs, 0u) << where;
    ASSERT_GT(r->device_calls, 0u) << where;
    if (!host_changed) {
      // Every attempt of the step (split ones and those that move held
      // vertices included) found the device's copy by the number.
      EXPECT_EQ(r->device_fingerprint_passes, 0u) << where;
      ++steps_on_device;
    } else if (!only_named || device::DeviceChecksOn()) {
      EXPECT_GE(r->device_fingerprint_passes, 1u) << where;
    }
    host_changed = r->path == UpdatePath::kReinserted ||
                   r->path == UpdatePath::kRebuilt || r->reinserted > 0 ||
                   r->renumbered;
    only_named = r->path != UpdatePath::kRebuilt && !r->renumbered;
    ASSERT_TRUE(t->Validate().ok()) << where << t->Validate();
    EXPECT_EQ(testing::EdgesAsPositions(*t),
              testing::CgalDelaunayEdges(t->Positions()))
        << where;
  }
  EXPECT_GE(steps_on_device, 6u);
}

// Re-insertions change a few hundred triangles on the host: the next
// attempt sends those (DeviceExecutor::ChangedOnHost), not the whole mesh,
// without a pass over the host mesh (with KINETRI_DEVICE_CHECK=1, finding
// by the fingerprint that nothing else changed: no resync).
TEST(DeviceExecutor, ReinsertionsGoUpAsTheirChangesAlone) {
  const size_t n = 6000;
  std::mt19937_64 rng(63);
  auto t =
      Triangulation::Create(testing::UniformPoints(n, 63), DeviceOptions());
  ASSERT_TRUE(t.ok()) << t.status();
  const double sigma = 0.1 / std::sqrt(double(n));
  int followed = 0;
  bool reinserted = false;
  for (int s = 0; s < 30 && followed < 3; ++s) {
    auto r = t->ApplyDisplacements(Brownian(n, sigma, rng));
    ASSERT_TRUE(r.ok()) << r.status();
    const std::string where = "step " + std::to_string(s);
    EXPECT_EQ(r->device_resyncs, 0u) << where;
    if (reinserted && r->path != UpdatePath::kRebuilt && !r->renumbered) {
      // The previous step ended with re-insertions on the host, and this
      // one may remove vertices: every attempt that found the host mesh
      // changed took the changes alone, checked by a pass over the host
      // mesh with KINETRI_DEVICE_CHECK=1, trusted without one otherwise.
      EXPECT_GE(r->device_patched_uploads, 1u) << where;
      EXPECT_EQ(r->device_fingerprint_passes,
                device::DeviceChecksOn() ? r->device_patched_uploads : 0u)
          << where;
      ++followed;
    }
    reinserted =
        r->reinserted > 0 && r->path != UpdatePath::kRebuilt && !r->renumbered;
    ASSERT_TRUE(t->Validate().ok()) << where << t->Validate();
    EXPECT_EQ(testing::EdgesAsPositions(*t),
              testing::CgalDelaunayEdges(t->Positions()))
        << where;
  }
  EXPECT_GE(followed, 3);
}

// Positions named by the caller (PositionsWrittenAt) are the only ones
// compared: the attempt sends the named entries that changed, nothing
// else, and gives CGAL's mesh. With KINETRI_DEVICE_CHECK=1 (ctest sets it
// for the device suites) a changed entry left out of the list is found by
// the whole comparison, sent, and counted as a resync.
TEST(DeviceExecutor, OnlyTheNamedPositionsAreCompared) {
  ResidentMesh res(3000, 53);
  ASSERT_TRUE(res.executor.ok()) << res.executor.status();
  auto& [pts, sites, m, a] = res;
  std::mt19937_64 rng(53);
  std::normal_distribution<double> step(0.0, 0.05 / std::sqrt(3000.0));
  std::vector<Vec2> to = pts;
  for (int round = 0; round < 4; ++round) {
    const bool leave_one_out = round % 2 == 1;
    // (Trusted, a broken promise gives a wrong mesh: not tried.)
    if (leave_one_out && !device::DeviceChecksOn()) continue;
    std::vector<uint32_t> written;
    for (int k = 0; k < 25; ++k) {
      const uint32_t v = static_cast<uint32_t>(rng() % to.size());
      to[v].x += step(rng);
      to[v].y += step(rng);
      written.push_back(v);
      // (Repeats and entries written with their old values are allowed.)
      written.push_back(static_cast<uint32_t>(rng() % to.size()));
    }
    uint32_t changed = 0;
    {
      std::vector<uint32_t> u = written;
      std::sort(u.begin(), u.end());
      u.erase(std::unique(u.begin(), u.end()), u.end());
      for (uint32_t v : u) changed += to[v] != pts[v] ? 1 : 0;
    }
    if (leave_one_out) {
      const uint32_t v = written.front();
      written.erase(std::remove(written.begin(), written.end(), v),
                    written.end());
    }
    // (In two calls: they add up.)
    const size_t half = written.size() / 2;
    (*a)->PositionsWrittenAt(absl::MakeConstSpan(written).subspan(0, half), {});
    (*a)->PositionsWrittenAt(absl::MakeConstSpan(written).subspan(half), {});
    auto r = (*a)->Attempt(m, to, {}, nullptr, nullptr, 0.5, nullptr);
    const std::string where = "round " + std::to_string(round);
    ASSERT_TRUE(r.ok()) << where << ": " << r.status();
    ASSERT_TRUE(r->fixed) << where;
    EXPECT_EQ(r->resyncs, leave_one_out ? 1u : 0u) << where;
    // Each changed entry went up once, as (index, position).
    EXPECT_EQ(r->bytes_uploaded, uint64_t{changed} * 20) << where;
    EXPECT_EQ(EdgeSet(m), EdgeSet(BuildDelaunayWithCgal(to, sites))) << where;
    pts = to;
  }
}

// A query whose device call fails is refused with RESOURCE_EXHAUSTED or
// INTERNAL; the next query (its view uploaded again where the failure hit
// the upload) gives the answer of a query that never failed, and no query
// holds its scratch after it returned. (Not device_bytes(): the blocks'
// sizes, and so the scratch kept, follow their timing.)
TEST(DeviceExecutor, AFailedQueryIsRefusedAndTheNextOneAnswers) {
  const size_t n = 3000;
  const std::vector<Vec2> pts = testing::ClusteredPoints(n, 81);
  auto t = Triangulation::Create(pts, DeviceOptions());
  ASSERT_TRUE(t.ok()) << t.status();
  std::mt19937_64 rng(82);
  ASSERT_TRUE(
      t->ApplyDisplacements(Brownian(n, 0.1 / std::sqrt(double(n)), rng)).ok());
  std::vector<uint32_t> ids(n);
  for (uint32_t i = 0; i < n; ++i) ids[i] = i;
  const double r = 2.0 / std::sqrt(double(n));
  auto knn = [&] { return KNearestOfPoints(*t, ids, 8, true); };
  auto radius = [&] { return WithinRadiusOfPoints(*t, ids, r, true, 0); };
  auto all_nn = [&] { return AllNearestNeighbors(*t); };
  struct Kind {
    const char* name;
    std::function<absl::StatusOr<NeighborLists>()> run;
  };
  const std::vector<Kind> kinds = {
      {"k nearest", knn}, {"radius", radius}, {"all nearest", all_nn}};
  device::DeviceExecutor* d = t->device_executor();
  ASSERT_NE(d, nullptr);
  std::vector<NeighborLists> want;
  for (const Kind& k : kinds) {
    auto a = k.run();
    ASSERT_TRUE(a.ok()) << k.name << ": " << a.status();
    want.push_back(*std::move(a));
  }
  int fired = 0;
  for (size_t i = 0; i < kinds.size(); ++i) {
    for (const auto fault_kind : {device::DeviceFault::Kind::kOutOfMemory,
                                  device::DeviceFault::Kind::kError}) {
      for (uint64_t after : {0, 1, 2, 3, 5}) {
        const std::string where = std::string(kinds[i].name) + " after " +
                                  std::to_string(after) + " calls";
        d->InjectFault({fault_kind, after});
        auto got = kinds[i].run();
        if (d->fault_armed()) {
          d->InjectFault({});
          ASSERT_TRUE(got.ok()) << where << ": " << got.status();
        } else {
          ++fired;
          ASSERT_FALSE(got.ok()) << where;
          EXPECT_EQ(got.status().code(),
                    fault_kind == device::DeviceFault::Kind::kOutOfMemory
                        ? absl::StatusCode::kResourceExhausted
                        : absl::StatusCode::kInternal)
              << where << ": " << got.status();
        }
        EXPECT_EQ(d->queries_in_flight(), 0u) << where;
        auto next = kinds[i].run();
        ASSERT_TRUE(next.ok()) << where << ": " << next.status();
        EXPECT_EQ(next->offsets, want[i].offsets) << where;
        EXPECT_EQ(next->ids, want[i].ids) << where;
        EXPECT_EQ(next->distances, want[i].distances) << where;
      }
    }
  }
  EXPECT_GE(fired, 10);
}

// A step whose device attempt fails is taken on the host (a rebuild, the
// reason naming the device), exact; the step after it runs on the device
// again.
TEST(DeviceExecutor, AStepWhoseDeviceFailsIsTakenOnTheHost) {
  const size_t n = 3000;
  const std::vector<Vec2> pts = testing::UniformPoints(n, 61);
  auto t = Triangulation::Create(pts, DeviceOptions());
  ASSERT_TRUE(t.ok()) << t.status();
  std::mt19937_64 rng(62);
  const double sigma = 0.05 / std::sqrt(double(n));
  ASSERT_TRUE(t->ApplyDisplacements(Brownian(n, sigma, rng)).ok());
  for (const auto kind : {device::DeviceFault::Kind::kOutOfMemory,
                          device::DeviceFault::Kind::kError}) {
    t->device_executor()->InjectFault({kind, 3});
    auto r = t->ApplyDisplacements(Brownian(n, sigma, rng));
    ASSERT_TRUE(r.ok()) << r.status();
    EXPECT_FALSE(t->device_executor()->fault_armed());
    EXPECT_EQ(r->path, UpdatePath::kRebuilt);
    EXPECT_NE(r->fallback_reason.find("device executor failed"),
              std::string::npos)
        << r->fallback_reason;
    ASSERT_TRUE(t->Validate().ok()) << t->Validate();
    EXPECT_EQ(testing::EdgesAsPositions(*t),
              testing::CgalDelaunayEdges(t->Positions()));
    auto next = t->ApplyDisplacements(Brownian(n, sigma, rng));
    ASSERT_TRUE(next.ok()) << next.status();
    EXPECT_EQ(next->device_resyncs, 0u);
    EXPECT_NE(next->path, UpdatePath::kRebuilt) << next->fallback_reason;
    EXPECT_GT(next->device_calls, 0u);
    EXPECT_EQ(testing::EdgesAsPositions(*t),
              testing::CgalDelaunayEdges(t->Positions()));
  }
}

// The _async forms give what the sync forms give: attempts on two
// executors, one called each way (and both at once), leave the same mesh,
// flip counts and stuck corners; queries asked twice at once on one
// executor, asynchronously, give the synchronous answer. A future dropped
// without get() waits for its work (std::async's), so nothing outlives its
// arguments.
TEST(DeviceExecutor, AsyncFormsGiveWhatTheSyncFormsGive) {
  const size_t n = 3000;
  std::vector<Vec2> pts = testing::UniformPoints(n, 81);
  const std::vector<uint32_t> sites = AllSites(n);
  auto a = device::MakeDeviceExecutor(kBackend);
  auto b = device::MakeDeviceExecutor(kBackend);
  ASSERT_TRUE(a.ok() && b.ok());
  Mesh ma = BuildDelaunayWithCgal(pts, sites);
  Mesh mb = ma;
  std::mt19937_64 rng(82);
  const double spacing = 1.0 / std::sqrt(double(n));
  std::normal_distribution<double> g(0.0, 1.0);
  int fixed = 0, stuck = 0;
  for (double sigma : {0.002, 0.3, 0.005, 0.5, 0.001}) {
    std::vector<Vec2> to = pts;
    for (Vec2& p : to) {
      p.x += sigma * spacing * g(rng);
      p.y += sigma * spacing * g(rng);
    }
    auto fb = (*b)->AttemptAsync(mb, to, {}, nullptr, nullptr, 0.5, nullptr,
                                 device::DeviceStream{});
    auto ra = (*a)->Attempt(ma, to, {}, nullptr, nullptr, 0.5, nullptr);
    auto rb = fb.get();
    ASSERT_TRUE(ra.ok() && rb.ok()) << ra.status() << rb.status();
    ASSERT_EQ(ra->fixed, rb->fixed) << "sigma " << sigma;
    EXPECT_EQ(ra->counts.delaunay, rb->counts.delaunay);
    EXPECT_EQ(ra->counts.legalize_rounds, rb->counts.legalize_rounds);
    EXPECT_EQ(ra->stuck_corners, rb->stuck_corners);
    EXPECT_EQ(ma.origin(), mb.origin()) << "sigma " << sigma;
    EXPECT_EQ(ma.twin(), mb.twin()) << "sigma " << sigma;
    if (ra->fixed) {
      ++fixed;
      EXPECT_EQ(EdgeSet(ma), EdgeSet(BuildDelaunayWithCgal(to, sites)))
          << "sigma " << sigma;
      pts = to;
    } else {
      ++stuck;  // both meshes are still those of pts
    }
  }
  EXPECT_GT(fixed, 0);
  EXPECT_GT(stuck, 0);
  // A dropped future: its attempt has ended when the statement that drops
  // it ends (the mesh is already the new one).
  {
    // The smallest move of point 0 (in steps of 0.02 spacings) that
    // changes the triangulation.
    std::vector<Vec2> to = pts;
    for (double d = 0.02; d < 1.0; d += 0.02) {
      to[0].x = pts[0].x + d * spacing;
      if (EdgeSet(BuildDelaunayWithCgal(to, sites)) != EdgeSet(ma)) break;
    }
    ASSERT_NE(EdgeSet(BuildDelaunayWithCgal(to, sites)), EdgeSet(ma));
    Mesh mc = ma;
    (*a)->Invalidate();  // another mesh for this executor
    (void)(*a)->AttemptAsync(mc, to, {}, nullptr, nullptr, 0.5, nullptr,
                             device::DeviceStream{});
    EXPECT_EQ(EdgeSet(mc), EdgeSet(BuildDelaunayWithCgal(to, sites)));
  }

  auto t =
      Triangulation::Create(testing::ClusteredPoints(n, 83), DeviceOptions());
  ASSERT_TRUE(t.ok());
  ASSERT_TRUE(t->ApplyDisplacements(Brownian(n, 0.05 * spacing, rng)).ok());
  const std::vector<uint32_t> ids = AllSites(n);
  device::DeviceQuery knn = KnnOfPoints(ids);
  device::DeviceQuery radius = knn;
  radius.kind = device::DeviceQuery::Kind::kRadius;
  radius.radius = 2 * spacing;
  for (const device::DeviceQuery* q : {&knn, &radius}) {
    device::DeviceExecutor* d = t->device_executor();
    auto sync = d->Query(t->query_view(), t->steps(), *q);
    ASSERT_TRUE(sync.ok()) << sync.status();
    auto f1 =
        d->QueryAsync(t->query_view(), t->steps(), *q, device::DeviceStream{});
    auto f2 =
        d->QueryAsync(t->query_view(), t->steps(), *q, device::DeviceStream{});
    for (auto* f : {&f1, &f2}) {
      auto r = f->get();
      ASSERT_TRUE(r.ok()) << r.status();
      EXPECT_EQ(r->offsets, sync->offsets);
      EXPECT_EQ(r->ids, sync->ids);
      EXPECT_EQ(r->distances, sync->distances);
    }
  }
}

#if defined(KINETRI_TEST_CUDA)
// The _async forms with a real caller's stream (CUDA only): the caller
// queues, on a non-blocking stream of its own, a host function that sleeps
// and then sets a flag; an attempt and a query asked with that stream must
// not end before it (their device work waits for an event recorded on the
// stream when they were called). Without that order the attempt would end
// within milliseconds, long before the flag.
std::atomic<int> caller_work_done{0};
void CUDART_CB SlowCallerWork(void*) {
  std::this_thread::sleep_for(std::chrono::milliseconds(300));
  caller_work_done.fetch_add(1);
}

TEST(DeviceExecutor, AsyncFormsWaitForTheCallersStream) {
  const size_t n = 3000;
  std::vector<Vec2> pts = testing::UniformPoints(n, 85);
  const std::vector<uint32_t> sites = AllSites(n);
  auto a = device::MakeDeviceExecutor(kBackend);
  ASSERT_TRUE(a.ok());
  Mesh m = BuildDelaunayWithCgal(pts, sites);
  std::vector<Vec2> to = pts;
  std::mt19937_64 rng(86);
  std::normal_distribution<double> g(0.0, 0.01 / std::sqrt(double(n)));
  for (Vec2& p : to) {
    p.x += g(rng);
    p.y += g(rng);
  }
  cudaStream_t caller;
  ASSERT_EQ(cudaStreamCreateWithFlags(&caller, cudaStreamNonBlocking),
            cudaSuccess);
  caller_work_done = 0;
  ASSERT_EQ(cudaLaunchHostFunc(caller, SlowCallerWork, nullptr), cudaSuccess);
  auto f = (*a)->AttemptAsync(m, to, {}, nullptr, nullptr, 0.5, nullptr,
                              device::DeviceStream{caller});
  auto r = f.get();
  EXPECT_EQ(caller_work_done.load(), 1) << "the attempt did not wait";
  ASSERT_TRUE(r.ok()) << r.status();
  ASSERT_TRUE(r->fixed);
  EXPECT_EQ(EdgeSet(m), EdgeSet(BuildDelaunayWithCgal(to, sites)));

  auto t = Triangulation::Create(to, DeviceOptions());
  ASSERT_TRUE(t.ok());
  const std::vector<uint32_t> ids = AllSites(n);
  const device::DeviceQuery knn = KnnOfPoints(ids);
  device::DeviceExecutor* d = t->device_executor();
  auto sync = d->Query(t->query_view(), t->steps(), knn);
  ASSERT_TRUE(sync.ok()) << sync.status();
  ASSERT_EQ(cudaLaunchHostFunc(caller, SlowCallerWork, nullptr), cudaSuccess);
  auto fq = d->QueryAsync(t->query_view(), t->steps(), knn,
                          device::DeviceStream{caller});
  auto q = fq.get();
  EXPECT_EQ(caller_work_done.load(), 2) << "the query did not wait";
  ASSERT_TRUE(q.ok()) << q.status();
  EXPECT_EQ(q->ids, sync->ids);
  EXPECT_EQ(q->distances, sync->distances);
  EXPECT_EQ(cudaStreamSynchronize(caller), cudaSuccess);
  EXPECT_EQ(cudaStreamDestroy(caller), cudaSuccess);
}
#endif  // KINETRI_TEST_CUDA

// The host mesh's arrays, to count what a step changed.
struct MeshArrays {
  std::vector<uint32_t> origin, twin, vertex_edge;
};
MeshArrays ArraysOf(const Triangulation& t) {
  const TriangulationView v = t.view();
  const uint32_t ne = v.mesh.num_half_edges, nv = v.num_points;
  return {{v.mesh.origin, v.mesh.origin + ne},
          {v.mesh.twin, v.mesh.twin + ne},
          {v.vertex_edge, v.vertex_edge + nv}};
}
// The bytes a fixed attempt downloads from `before` to `after`: the count,
// then the changed half-edges and vertex_edge entries (12 bytes each) when
// they are at most an eighth of all entries, the whole arrays otherwise.
uint64_t DownloadBytes(const MeshArrays& before, const MeshArrays& after) {
  const uint64_t ne = after.origin.size(), nv = after.vertex_edge.size();
  uint64_t changed = 0;
  for (size_t e = 0; e < ne; ++e) {
    changed +=
        before.origin[e] != after.origin[e] || before.twin[e] != after.twin[e];
  }
  for (size_t v = 0; v < nv; ++v) {
    changed += before.vertex_edge[v] != after.vertex_edge[v];
  }
  return 4 + (changed <= (ne + nv) / 8 ? 12 * changed : 8 * ne + 4 * nv);
}

// The device copy of the mesh lives across steps: the first step uploads
// the mesh, a later local step only the positions (only those that changed
// when they are few); a fixed attempt
// downloads what it changed (the whole arrays when that is much); a rebuild or
// re-insertion makes the next step upload the mesh again.
TEST(DeviceExecutor, MeshStaysResidentAcrossSteps) {
  const size_t n = 4000;
  auto t =
      Triangulation::Create(testing::UniformPoints(n, 11), DeviceOptions());
  ASSERT_TRUE(t.ok());
  EXPECT_EQ(t->device_bytes(), 0u);  // nothing goes up before a step
  EXPECT_EQ(t->device_host_bytes(), 0u);
  std::mt19937_64 rng(12);
  const double spacing = 1.0 / std::sqrt(double(n));
  const MeshArrays m0 = ArraysOf(*t);
  auto first = t->ApplyDisplacements(Brownian(n, 0.01 * spacing, rng));
  ASSERT_TRUE(first.ok()) << first.status();
  ASSERT_EQ(first->path, UpdatePath::kLocal);
  ASSERT_EQ(first->failed_attempts, 0u);
  const MeshArrays m1 = ArraysOf(*t);
  auto second = t->ApplyDisplacements(Brownian(n, 0.01 * spacing, rng));
  ASSERT_TRUE(second.ok()) << second.status();
  ASSERT_EQ(second->path, UpdatePath::kLocal);
  ASSERT_EQ(second->failed_attempts, 0u);
  const MeshArrays m2 = ArraysOf(*t);
  const uint64_t mesh_bytes = 8ull * t->view().mesh.num_half_edges;
  const uint64_t pos_bytes = sizeof(Vec2) * n;
  // Up: positions (+ origin, twin, vertex_edge the first time). Down: what
  // the attempt changed.
  const uint64_t whole = mesh_bytes + 4ull * n;
  const uint64_t down1 = DownloadBytes(m0, m1), down2 = DownloadBytes(m1, m2);
  EXPECT_LT(down2, whole / 4);  // a small step changes little
  EXPECT_EQ(first->transfer_bytes, whole + pos_bytes + down1);
  EXPECT_EQ(second->transfer_bytes, pos_bytes + down2);
  // A sparse step: 30 points move; their few changes come down.
  {
    std::vector<uint32_t> ids;
    std::vector<Vec2> d;
    for (uint32_t i = 0; i < 30; ++i) {
      ids.push_back(i * 97);
      d.push_back({0.05 * spacing, -0.03 * spacing});
    }
    auto sparse = t->ApplyDisplacements(
        DisplacementBatch::Sparse(std::move(ids), std::move(d)));
    ASSERT_TRUE(sparse.ok()) << sparse.status();
    ASSERT_EQ(sparse->path, UpdatePath::kLocal);
    ASSERT_EQ(sparse->failed_attempts, 0u);
    // Up: only the 30 positions that changed (index and value), not all
    // n; besides, the candidate and seed triangles around the moved points
    // (4 bytes each, a few dozen per point).
    const uint64_t down = DownloadBytes(m2, ArraysOf(*t));
    const uint64_t up = 30 * (sizeof(uint32_t) + sizeof(Vec2));
    EXPECT_LT(down, 30 * 12 * 40);
    EXPECT_GE(sparse->transfer_bytes, up + down);
    EXPECT_LE(sparse->transfer_bytes, up + down + 30 * 2 * 4 * 24);
    EXPECT_LT(sparse->transfer_bytes, pos_bytes);
    EXPECT_EQ(testing::EdgesAsPositions(*t),
              testing::CgalDelaunayEdges(t->Positions()));
  }
  EXPECT_GT(t->device_bytes(), mesh_bytes + pos_bytes);
  EXPECT_TRUE(t->Validate().ok());
  // The admission estimate holds after steps of every kind (a large step
  // legalizes every edge: the biggest worklists).
  for (double sigma : {0.01, 0.3, 1.0}) {
    ASSERT_TRUE(t->ApplyDisplacements(Brownian(n, sigma * spacing, rng)).ok());
    std::printf(
        "sigma %.2f: %.1f device bytes per point, %.1f host bytes per point "
        "beside the mesh\n",
        sigma, double(t->device_bytes()) / n,
        double(t->device_host_bytes()) / n);
    EXPECT_LE(t->device_bytes(), device::kDeviceBytesPerPoint * n);
    // The host side (mirrors, download arrays, patch and change lists,
    // staging), which the server admits beside the host session.
    EXPECT_GT(t->device_host_bytes(), 32 * n);
    EXPECT_LE(t->device_host_bytes(), device::kDeviceHostBytesPerPoint * n +
                                          device::DeviceHostFixedBytes(
                                              t->device_executor()->backend()));
  }
  // And with the query view on the device (after all-NN and an 8-NN query
  // of every point, whose scratch stays for the next queries).
  auto all = AllNearestNeighbors(*t);
  ASSERT_TRUE(all.ok()) << all.status();
  std::vector<uint32_t> ids(n);
  for (uint32_t i = 0; i < n; ++i) ids[i] = i;
  auto knn = KNearestOfPoints(*t, ids, 8, true);
  ASSERT_TRUE(knn.ok()) << knn.status();
  std::printf("with queries: %.1f device bytes per point\n",
              double(t->device_bytes()) / n);
  EXPECT_LE(t->device_bytes(), device::kDeviceBytesPerPoint * n +
                                   device::kDeviceQueryScratchBytes);
  // After points join (the mesh's arrays grow, and the download hands their
  // old ones to the executor) and then leave (the mirrors were sized for
  // more), the host side stays within the bound of the points there are.
  {
    DisplacementBatch join = Brownian(n, 0.01 * spacing, rng);
    std::uniform_real_distribution<double> u(0.0, 1.0);
    for (size_t i = 0; i < n / 2; ++i) join.add.push_back({u(rng), u(rng)});
    ASSERT_TRUE(t->ApplyDisplacements(join).ok());
    ASSERT_TRUE(
        t->ApplyDisplacements(Brownian(t->num_sites(), 0.01 * spacing, rng))
            .ok());
    DisplacementBatch leave = Brownian(t->num_sites(), 0.01 * spacing, rng);
    for (uint32_t i = 0; i < 3 * n / 4; ++i) leave.remove.push_back(2 * i);
    ASSERT_TRUE(t->ApplyDisplacements(leave).ok());
    for (int s = 0; s < 2; ++s) {
      ASSERT_TRUE(
          t->ApplyDisplacements(Brownian(t->num_sites(), 0.01 * spacing, rng))
              .ok());
      const uint64_t m = t->num_sites();
      std::printf(
          "%llu points after joins and leaves: %.1f host bytes per "
          "point beside the mesh\n",
          static_cast<unsigned long long>(m),
          double(t->device_host_bytes()) / m);
      EXPECT_LE(
          t->device_host_bytes(),
          device::kDeviceHostBytesPerPoint * m +
              device::DeviceHostFixedBytes(t->device_executor()->backend()));
    }
    EXPECT_TRUE(t->Validate().ok());
  }
}

// A fixed attempt brings down what it changed: the half-edges and
// vertex_edge entries that differ from the mesh it started from (12 bytes
// each, after a 4-byte count), or the whole arrays when those are over an
// eighth of the entries. Attempts from CGAL's mesh, small and large
// changes, each checked against the bytes counted on the host and against
// CGAL.
TEST(DeviceExecutor, FixedAttemptDownloadsWhatChanged) {
  const size_t n = 3000;
  const std::vector<Vec2> pts = testing::UniformPoints(n, 95);
  const std::vector<uint32_t> sites = AllSites(n);
  auto a = device::MakeDeviceExecutor(kBackend);
  ASSERT_TRUE(a.ok());
  std::mt19937_64 rng(96);
  const double spacing = 1.0 / std::sqrt(double(n));
  // Small Brownian motion, and shears (no triangle inverts; legalizing
  // flips more edges the stronger the shear).
  struct Case {
    double sigma, shear;
  };
  int patched = 0, whole = 0;
  for (const Case c : {Case{0.005, 0}, Case{0.002, 0}, Case{0, 0.05},
                       Case{0, 0.3}, Case{0, 1.5}}) {
    std::normal_distribution<double> g(0.0, c.sigma * spacing);
    std::vector<Vec2> to = pts;
    for (Vec2& p : to) {
      p.x += c.shear * p.y;
      if (c.sigma > 0) {
        p.x += g(rng);
        p.y += g(rng);
      }
    }
    const std::string where = "sigma " + std::to_string(c.sigma) + ", shear " +
                              std::to_string(c.shear);
    Mesh m = BuildDelaunayWithCgal(pts, sites);
    const Mesh before = m;
    (*a)->Invalidate();  // a mesh from elsewhere
    auto r = (*a)->Attempt(m, to, {}, nullptr, nullptr, 1.0, nullptr);
    ASSERT_TRUE(r.ok()) << r.status();
    ASSERT_TRUE(r->fixed) << where;
    const uint64_t ne = m.num_half_edges(), nv = m.num_vertices();
    uint64_t changed = 0;
    for (uint64_t e = 0; e < ne; ++e) {
      changed += m.origin()[e] != before.origin()[e] ||
                 m.twin()[e] != before.twin()[e];
    }
    for (uint64_t v = 0; v < nv; ++v) {
      changed += m.vertex_edge()[v] != before.vertex_edge()[v];
    }
    const bool as_patch = changed <= (ne + nv) / 8;
    EXPECT_EQ(r->bytes_downloaded,
              4 + (as_patch ? 12 * changed : 8 * ne + 4 * nv))
        << where;
    EXPECT_EQ(r->patched_downloads, as_patch ? 1u : 0u) << where;
    (as_patch ? patched : whole) += 1;
    EXPECT_EQ(EdgeSet(m), EdgeSet(BuildDelaunayWithCgal(to, sites))) << where;
    std::printf("%s: %llu of %llu entries changed\n", where.c_str(),
                static_cast<unsigned long long>(changed),
                static_cast<unsigned long long>(ne + nv));
  }
  EXPECT_GT(patched, 0);
  EXPECT_GT(whole, 0);
}

// Thrust's temporaries come from the executor's pool (counted in
// device_bytes) and go back to it: after a few steps of one kind the pool
// holds about all it needs, and further steps of that kind barely grow it
// (a pool that never reused a block would grow by its temporaries every
// step).
TEST(DeviceExecutor, TemporariesAreReusedAcrossSteps) {
  const size_t n = 3000;
  auto t =
      Triangulation::Create(testing::UniformPoints(n, 21), DeviceOptions());
  ASSERT_TRUE(t.ok());
  std::mt19937_64 rng(22);
  const double spacing = 1.0 / std::sqrt(double(n));
  for (int s = 0; s < 3; ++s) {
    ASSERT_TRUE(t->ApplyDisplacements(Brownian(n, 0.02 * spacing, rng)).ok());
  }
  const uint64_t settled = t->device_bytes();
  for (int s = 0; s < 8; ++s) {
    auto r = t->ApplyDisplacements(Brownian(n, 0.02 * spacing, rng));
    ASSERT_TRUE(r.ok()) << r.status();
    ASSERT_NE(r->path, UpdatePath::kRebuilt);
    EXPECT_LE(t->device_bytes(), settled + settled / 4) << "step " << s;
  }
  EXPECT_TRUE(t->Validate().ok());
}

// Sparse steps (few points move) go through the candidate list; the result
// is still CGAL's triangulation.
TEST(DeviceExecutor, SparseStepsAreExact) {
  const size_t n = 5000;
  auto pts = testing::ClusteredPoints(n, 21);
  auto t = Triangulation::Create(pts, DeviceOptions());
  ASSERT_TRUE(t.ok());
  std::mt19937_64 rng(22);
  std::uniform_int_distribution<uint32_t> pick(0, n - 1);
  std::normal_distribution<double> g(0.0, 2.0 / std::sqrt(double(n)));
  for (int s = 0; s < 8; ++s) {
    std::vector<uint32_t> ids;
    std::vector<Vec2> d;
    std::vector<uint8_t> used(n, 0);
    for (int k = 0; k < 40; ++k) {
      const uint32_t id = pick(rng);
      if (used[id]) continue;
      used[id] = 1;
      ids.push_back(id);
      d.push_back({g(rng), g(rng)});
    }
    auto r = t->ApplyDisplacements(
        DisplacementBatch::Sparse(std::move(ids), std::move(d)));
    ASSERT_TRUE(r.ok()) << r.status();
    ASSERT_TRUE(t->Validate().ok()) << "step " << s << t->Validate();
    EXPECT_EQ(testing::EdgesAsPositions(*t),
              testing::CgalDelaunayEdges(t->Positions()))
        << "step " << s;
  }
}

// One thread or all: the same mesh (claims are pure functions of the mesh).
TEST(DeviceExecutor, ResultIndependentOfThreadCount) {
  const size_t n = 4000;
  const auto pts = testing::ClusteredPoints(n, 31);
  auto a = Triangulation::Create(pts, DeviceOptions(1));
  auto b = Triangulation::Create(pts, DeviceOptions(0));
  ASSERT_TRUE(a.ok() && b.ok());
  std::mt19937_64 rng(32);
  for (int s = 0; s < 5; ++s) {
    const DisplacementBatch batch =
        Brownian(n, 0.4 / std::sqrt(double(n)), rng);
    ASSERT_TRUE(a->ApplyDisplacements(batch).ok());
    ASSERT_TRUE(b->ApplyDisplacements(batch).ok());
    ExpectSameMesh(*a, *b, "step " + std::to_string(s));
  }
}

// A clone has its own device copy; both go on independently and exactly.
TEST(DeviceExecutor, CloneHasItsOwnDeviceCopy) {
  const size_t n = 2000;
  auto t =
      Triangulation::Create(testing::UniformPoints(n, 41), DeviceOptions());
  ASSERT_TRUE(t.ok());
  std::mt19937_64 rng(42);
  const double sigma = 0.2 / std::sqrt(double(n));
  ASSERT_TRUE(t->ApplyDisplacements(Brownian(n, sigma, rng)).ok());
  Triangulation c = t->Clone();
  EXPECT_EQ(c.options().executor, Executor::kDevice);
  ASSERT_TRUE(c.ApplyDisplacements(Brownian(n, sigma, rng)).ok());
  ASSERT_TRUE(t->ApplyDisplacements(Brownian(n, sigma, rng)).ok());
  for (const Triangulation* x : {&*t, &c}) {
    ASSERT_TRUE(x->Validate().ok());
    EXPECT_EQ(testing::EdgesAsPositions(*x),
              testing::CgalDelaunayEdges(x->Positions()));
  }
}

// kCuda is refused before anything is built when this binary has no CUDA
// backend registered or the machine has no GPU; where both exist it works.
TEST(DeviceExecutor, CudaBackendIsRefusedWithoutAGpu) {
  TriangulationOptions o = DeviceOptions();
  o.device_backend = DeviceBackend::kCuda;
  auto t = Triangulation::Create(testing::UniformPoints(100, 51), o);
  if (device::DeviceBackendAvailable(DeviceBackend::kCuda)) {
    ASSERT_TRUE(t.ok()) << t.status();
  } else {
    ASSERT_EQ(t.status().code(), absl::StatusCode::kFailedPrecondition);
    EXPECT_NE(t.status().message().find("cuda"), std::string::npos);
  }
#if !defined(KINETRI_TEST_CUDA)
  EXPECT_TRUE(device::DeviceBackendAvailable(DeviceBackend::kEmulated));
#endif
}

}  // namespace
}  // namespace kinetri::core
