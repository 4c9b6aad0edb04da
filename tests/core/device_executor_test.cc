// The device executor (core/device/): its emulated backend runs the same
// CCCL source on CPU threads. It follows the round executor's schedule, so
// the two must build the same mesh down to the numbering of half-edges; it
// keeps the mesh resident across steps (only positions go up once it is in
// sync); and the CUDA backend is refused cleanly where there is no GPU.
#include "core/device/device_executor.h"

#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <random>
#include <vector>

#include "core/queries.h"
#include "core/triangulation.h"
#include "tests/core/test_util.h"

namespace kinetri::core {
namespace {

using device::DeviceBackend;
using testing::Brownian;

TriangulationOptions DeviceOptions(int threads = 0) {
  TriangulationOptions o;
  o.executor = Executor::kDevice;
  o.device_backend = DeviceBackend::kEmulated;
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
      ExpectSameMesh(*rounds, *dev, where);
      ASSERT_TRUE(dev->Validate().ok()) << where << dev->Validate();
      EXPECT_EQ(testing::EdgesAsPositions(*dev),
                testing::CgalDelaunayEdges(dev->Positions()))
          << where;
    }
  }
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

// The device copy of the mesh lives across steps: the first step uploads
// the mesh, a later local step only the positions (and downloads the
// result); a rebuild or re-insertion makes the next step upload it again.
TEST(DeviceExecutor, MeshStaysResidentAcrossSteps) {
  const size_t n = 4000;
  auto t =
      Triangulation::Create(testing::UniformPoints(n, 11), DeviceOptions());
  ASSERT_TRUE(t.ok());
  EXPECT_EQ(t->device_bytes(), 0u);  // nothing goes up before a step
  std::mt19937_64 rng(12);
  const double spacing = 1.0 / std::sqrt(double(n));
  auto first = t->ApplyDisplacements(Brownian(n, 0.01 * spacing, rng));
  ASSERT_TRUE(first.ok()) << first.status();
  ASSERT_EQ(first->path, UpdatePath::kLocal);
  auto second = t->ApplyDisplacements(Brownian(n, 0.01 * spacing, rng));
  ASSERT_TRUE(second.ok()) << second.status();
  ASSERT_EQ(second->path, UpdatePath::kLocal);
  const uint64_t mesh_bytes = 8ull * t->view().mesh.num_half_edges;
  const uint64_t pos_bytes = sizeof(Vec2) * n;
  // Up: positions (+ origin, twin, vertex_edge the first time). Down:
  // origin, twin, vertex_edge.
  const uint64_t down = mesh_bytes + 4ull * n;
  EXPECT_EQ(first->transfer_bytes, down + pos_bytes + down);
  EXPECT_EQ(second->transfer_bytes, pos_bytes + down);
  EXPECT_GT(t->device_bytes(), mesh_bytes + pos_bytes);
  EXPECT_TRUE(t->Validate().ok());
  // The admission estimate holds after steps of every kind (a large step
  // legalizes every edge: the biggest worklists).
  for (double sigma : {0.01, 0.3, 1.0}) {
    ASSERT_TRUE(t->ApplyDisplacements(Brownian(n, sigma * spacing, rng)).ok());
    std::printf("sigma %.2f: %.1f device bytes per point\n", sigma,
                double(t->device_bytes()) / n);
    EXPECT_LE(t->device_bytes(), device::kDeviceBytesPerPoint * n);
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
  EXPECT_TRUE(device::DeviceBackendAvailable(DeviceBackend::kEmulated));
}

}  // namespace
}  // namespace kinetri::core
