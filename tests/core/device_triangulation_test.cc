// CUDA executor vs the CPU executor: identical answers (skips without a GPU).
#include "core/device/device_triangulation.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <random>
#include <string>
#include <vector>

#include "core/queries.h"
#include "tests/core/test_util.h"

namespace kinetri::core::cuda {
namespace {

class CudaExecutorTest : public ::testing::Test {
 protected:
  void SetUp() override {
    if (!DeviceAvailable()) GTEST_SKIP() << "no CUDA device present";
  }
  void ExpectSame(const Triangulation& t) {
    auto dev = DeviceTriangulation::Upload(t);
    ASSERT_TRUE(dev.ok()) << dev.status();
    auto gpu = dev->AllNearestNeighbors();
    auto cpu = core::AllNearestNeighbors(t);
    ASSERT_TRUE(gpu.ok() && cpu.ok());
    EXPECT_EQ(gpu->offsets, cpu->offsets);
    EXPECT_EQ(gpu->ids, cpu->ids);
    EXPECT_EQ(gpu->distances, cpu->distances);
    EXPECT_EQ(*dev->CountInvalidTriangles(), 0u);
    EXPECT_EQ(*dev->CountIllegalEdges(), 0u);
  }
};

void ExpectSameRows(const absl::StatusOr<NeighborLists>& gpu,
                    const absl::StatusOr<NeighborLists>& cpu,
                    const std::string& what) {
  ASSERT_EQ(gpu.ok(), cpu.ok())
      << what << ": " << gpu.status() << " vs " << cpu.status();
  if (!cpu.ok()) {
    EXPECT_EQ(gpu.status().code(), cpu.status().code()) << what;
    return;
  }
  EXPECT_EQ(gpu->offsets, cpu->offsets) << what;
  EXPECT_EQ(gpu->ids, cpu->ids) << what;
  EXPECT_EQ(gpu->distances, cpu->distances) << what;
  EXPECT_EQ(gpu->truncated, cpu->truncated) << what;
}

// k-NN and radius queries of points and positions: same rows as the CPU.
void ExpectSameQueries(const Triangulation& t, uint64_t seed) {
  auto dev = DeviceTriangulation::Upload(t);
  ASSERT_TRUE(dev.ok()) << dev.status();
  const auto pts = t.Positions();
  const auto qs = testing::QueryPoints(pts, 3000, seed);
  std::vector<uint32_t> ids(std::min<size_t>(pts.size(), 3000));
  for (uint32_t i = 0; i < ids.size(); ++i) ids[i] = i;
  double typical = 0.0;
  for (size_t i = 1; i < std::min<size_t>(pts.size(), 50); ++i) {
    typical =
        std::max(typical, std::hypot(pts[i].x - pts[0].x, pts[i].y - pts[0].y));
  }
  for (int k : {1, 8, 33}) {
    ExpectSameRows(dev->KNearest(qs, k), core::KNearest(t, qs, k), "knn");
    for (bool ex : {true, false}) {
      ExpectSameRows(dev->KNearestOfPoints(ids, k, ex),
                     core::KNearestOfPoints(t, ids, k, ex), "knn of points");
    }
  }
  for (double r : {0.0, typical * 0.05, typical * 0.3}) {
    for (uint32_t cap : {0u, 5u}) {
      ExpectSameRows(dev->WithinRadius(qs, r, cap),
                     core::WithinRadius(t, qs, r, cap), "radius");
      ExpectSameRows(dev->WithinRadiusOfPoints(ids, r, true, cap),
                     core::WithinRadiusOfPoints(t, ids, r, true, cap),
                     "radius of points");
    }
  }
  // Bad arguments: the same status codes.
  const std::vector<Vec2> nan = {{0.5, std::nan("")}};
  ExpectSameRows(dev->KNearest(nan, 3), core::KNearest(t, nan, 3), "NaN");
  ExpectSameRows(dev->KNearest(qs, 0), core::KNearest(t, qs, 0), "k = 0");
  ExpectSameRows(dev->WithinRadius(qs, -1.0, 0),
                 core::WithinRadius(t, qs, -1.0, 0), "r < 0");
  const std::vector<uint32_t> unknown = {static_cast<uint32_t>(pts.size())};
  ExpectSameRows(dev->KNearestOfPoints(unknown, 3, true),
                 core::KNearestOfPoints(t, unknown, 3, true), "unknown id");
  QueryLimits tight;
  tight.max_total_results = 10;
  ExpectSameRows(dev->KNearest(qs, 8, tight), core::KNearest(t, qs, 8, tight),
                 "limit");
}

TEST_F(CudaExecutorTest, SameQueriesAsCpu) {
  uint64_t seed = 10;
  for (const auto& pts :
       {testing::UniformPoints(20000, 11), testing::ClusteredPoints(20000, 12),
        testing::Lattice(60), testing::WithDuplicates(3000, 3, 13),
        testing::Collinear(500, 14),
        testing::UniformPoints(5000, 15, 1e-12, 3e-12)}) {
    auto t = Triangulation::Create(pts);
    ASSERT_TRUE(t.ok());
    ExpectSameQueries(*t, ++seed);
  }
}

TEST_F(CudaExecutorTest, MemoryPerPoint) {
  auto t = Triangulation::Create(testing::UniformPoints(100000, 16));
  ASSERT_TRUE(t.ok());
  auto dev = DeviceTriangulation::Upload(*t);
  ASSERT_TRUE(dev.ok());
  // 100M points must fit in 80 GB with room for query output.
  std::printf("device bytes per point: %.1f\n", dev->bytes_per_point());
  EXPECT_LT(dev->bytes_per_point() * 100e6, 40e9);
}

TEST_F(CudaExecutorTest, SameAllNearestAndScansAsCpu) {
  for (const auto& pts :
       {testing::UniformPoints(20000, 1), testing::ClusteredPoints(20000, 2),
        testing::Lattice(100), testing::WithDuplicates(5000, 3, 3),
        testing::Collinear(500, 4)}) {
    auto t = Triangulation::Create(pts);
    ASSERT_TRUE(t.ok());
    ExpectSame(*t);
  }
}

TEST_F(CudaExecutorTest, SameAfterMotion) {
  const size_t n = 50000;
  auto t = Triangulation::Create(testing::UniformPoints(n, 5));
  ASSERT_TRUE(t.ok());
  std::mt19937_64 rng(6);
  std::normal_distribution<double> g(0.0, 0.1 / std::sqrt(double(n)));
  for (int s = 0; s < 5; ++s) {
    std::vector<Vec2> d(n);
    for (auto& v : d) v = {g(rng), g(rng)};
    ASSERT_TRUE(t->ApplyDisplacements(DisplacementBatch::Dense(d)).ok());
    ExpectSame(*t);
  }
}

}  // namespace
}  // namespace kinetri::core::cuda
