// CUDA executor vs the CPU executor: identical answers (skips without a GPU).
#include "core/cuda/device_triangulation.h"

#include <gtest/gtest.h>

#include <random>

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
