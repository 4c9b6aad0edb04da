// The exact predicates (core/predicates.h) on a GPU give the signs they give
// on the host, on inputs that take their exact paths: lattice points (exact
// ties everywhere), pairs rotated about a centre (near ties) and random
// points. Each predicate and each exact fallback is evaluated by a device
// functor over all inputs, the way the device executor calls them.
//
// On an H200 (CUDA 13.0, NVVM -O3, the fallbacks out of line) the exact
// distance-to-radius comparison read outside the thread's stack and crashed
// the kernel, and with the previous expansion code Orient2d gave the wrong
// sign for 52 of 102 collinear lattice triples; inlined, built with -G or
// with NVVM at -O1 the signs were right (docs/DEVICE.md). The tests print
// the stack limit before and after each launch and the plain kernel's frame,
// and KINETRI_CUDA_STACK_BYTES raises the limit first, so one run tells a
// stack the driver sized too small from a miscompilation. Built only with
// CUDA; skipped where no GPU is present.
#include <cuda_runtime.h>
#include <gtest/gtest.h>
#include <thrust/device_vector.h>
#include <thrust/execution_policy.h>
#include <thrust/for_each.h>
#include <thrust/iterator/counting_iterator.h>

#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <random>
#include <vector>

#include "core/predicates.h"

namespace kinetri::core {
namespace {

struct Input {
  Vec2 a, b, c, d;
  double r;
};

enum Predicate : int {
  kOrient2d,
  kOrient2dExact,
  kInCircle,
  kInCircleExact,
  kCompareDistance,
  kCompareDistanceExact,
  kCompareDistanceToRadius,
  kCompareDistanceToRadiusExact,
  kCompareCloser,
  kNumPredicates
};
const char* const kNames[kNumPredicates] = {"Orient2d",
                                            "Orient2dExact",
                                            "InCircle",
                                            "InCircleExact",
                                            "CompareDistance",
                                            "CompareDistanceExact",
                                            "CompareDistanceToRadius",
                                            "CompareDistanceToRadiusExact",
                                            "CompareCloser"};

__host__ __device__ int Evaluate(int predicate, const Input& x) {
  switch (predicate) {
    case kOrient2d:
      return Orient2d(x.a, x.b, x.c);
    case kOrient2dExact:
      return internal::Orient2dExact(x.a, x.b, x.c);
    case kInCircle:
      return InCircle(x.a, x.b, x.c, x.d);
    case kInCircleExact:
      return internal::InCircleExact(x.a, x.b, x.c, x.d);
    case kCompareDistance:
      return CompareDistance(x.a, x.b, x.c);
    case kCompareDistanceExact:
      return internal::CompareDistanceExact(x.a, x.b, x.c);
    case kCompareDistanceToRadius:
      return CompareDistanceToRadius(x.a, x.b, x.r);
    case kCompareDistanceToRadiusExact:
      return internal::CompareDistanceToRadiusExact(x.a, x.b, x.r);
    default:
      return CompareCloser(x.a, x.b, x.c);
  }
}

struct EvaluateAll {
  const Input* in;
  int* out;
  __host__ __device__ void operator()(unsigned i) const {
    for (int p = 0; p < kNumPredicates; ++p) {
      out[i * kNumPredicates + p] = Evaluate(p, in[i]);
    }
  }
};

std::vector<Input> Inputs() {
  std::mt19937_64 rng(7);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  std::uniform_int_distribution<int> lattice(-20, 20);
  auto lattice_point = [&] {
    return Vec2{double(lattice(rng)), double(lattice(rng))};
  };
  std::vector<Input> in;
  for (int i = 0; i < 20000; ++i) {  // exact ties everywhere
    Input x{lattice_point(), lattice_point(), lattice_point(), lattice_point(),
            0.0};
    x.r = std::hypot(x.a.x - x.c.x, x.a.y - x.c.y);
    in.push_back(x);
  }
  for (int i = 0; i < 20000; ++i) {  // b, c, d: a + v rotated (near ties)
    Input x;
    x.a = {u(rng), u(rng)};
    const Vec2 v{u(rng), u(rng)};
    x.b = {x.a.x + v.x, x.a.y + v.y};
    x.c = {x.a.x - v.y, x.a.y + v.x};
    x.d = {x.a.x - v.x, x.a.y - v.y};
    x.r = std::hypot(v.x, v.y);
    in.push_back(x);
  }
  for (int i = 0; i < 20000; ++i) {
    in.push_back({{u(rng), u(rng)},
                  {u(rng), u(rng)},
                  {u(rng), u(rng)},
                  {u(rng), u(rng)},
                  u(rng) + 1.0});
  }
  return in;
}

__global__ void EvaluateKernel(const Input* in, unsigned n, int* out) {
  const unsigned i = blockIdx.x * blockDim.x + threadIdx.x;
  if (i < n) EvaluateAll{in, out}(i);
}

// Skips the test where no GPU is present; sets the stack limit to
// KINETRI_CUDA_STACK_BYTES when that is given (as the CUDA backend does).
bool NeedDevice() {
  int devices = 0;
  if (cudaGetDeviceCount(&devices) != cudaSuccess || devices == 0) {
    return false;
  }
  if (const char* env = std::getenv("KINETRI_CUDA_STACK_BYTES")) {
    const size_t bytes = std::strtoull(env, nullptr, 10);
    if (bytes != 0) {
      EXPECT_EQ(cudaDeviceSetLimit(cudaLimitStackSize, bytes), cudaSuccess);
    }
  }
  return true;
}

size_t StackLimit() {
  size_t bytes = 0;
  cudaDeviceGetLimit(&bytes, cudaLimitStackSize);
  return bytes;
}

// Compares the device's signs with the host's, predicate by predicate.
void ExpectSameSigns(const std::vector<Input>& in,
                     const std::vector<int>& device) {
  const unsigned n = in.size();
  for (int p = 0; p < kNumPredicates; ++p) {
    int disagree = 0, zeros = 0;
    for (unsigned i = 0; i < n; ++i) {
      const int host = Evaluate(p, in[i]);
      zeros += host == 0;
      const int dev = device[size_t{i} * kNumPredicates + p];
      if (host != dev && ++disagree <= 3) {
        const Input& x = in[i];
        ADD_FAILURE() << kNames[p] << " input " << i << ": host " << host
                      << ", device " << dev << "; a=(" << x.a.x << "," << x.a.y
                      << ") b=(" << x.b.x << "," << x.b.y << ") c=(" << x.c.x
                      << "," << x.c.y << ") d=(" << x.d.x << "," << x.d.y
                      << ") r=" << x.r;
      }
    }
    EXPECT_EQ(disagree, 0) << kNames[p];
    // The inputs reach the exact paths (ties are decided there).
    if (p == kOrient2d || p == kCompareDistance) EXPECT_GT(zeros, 100);
  }
}

// Through thrust::for_each, as the device executor calls them.
TEST(DevicePredicates, SameSignsAsTheHost) {
  if (!NeedDevice()) GTEST_SKIP() << "no CUDA device present";
  const std::vector<Input> in = Inputs();
  const unsigned n = in.size();
  thrust::device_vector<Input> d_in(in.begin(), in.end());
  thrust::device_vector<int> d_out(size_t{n} * kNumPredicates, 99);
  const size_t limit_before = StackLimit();
  thrust::for_each(thrust::device, thrust::counting_iterator<unsigned>(0),
                   thrust::counting_iterator<unsigned>(n),
                   EvaluateAll{thrust::raw_pointer_cast(d_in.data()),
                               thrust::raw_pointer_cast(d_out.data())});
  ASSERT_EQ(cudaDeviceSynchronize(), cudaSuccess);
  std::printf("stack limit %zu bytes before the launch, %zu after\n",
              limit_before, StackLimit());
  ExpectSameSigns(in, std::vector<int>(d_out.begin(), d_out.end()));
}

// In a plain kernel, with its frame size printed: what the driver sizes
// the per-thread stack by (the limit before and after the launch).
TEST(DevicePredicates, SameSignsInAPlainKernel) {
  if (!NeedDevice()) GTEST_SKIP() << "no CUDA device present";
  cudaFuncAttributes attributes{};
  ASSERT_EQ(cudaFuncGetAttributes(&attributes, EvaluateKernel), cudaSuccess);
  const std::vector<Input> in = Inputs();
  const unsigned n = in.size();
  thrust::device_vector<Input> d_in(in.begin(), in.end());
  thrust::device_vector<int> d_out(size_t{n} * kNumPredicates, 99);
  const size_t limit_before = StackLimit();
  EvaluateKernel<<<(n + 127) / 128, 128>>>(
      thrust::raw_pointer_cast(d_in.data()), n,
      thrust::raw_pointer_cast(d_out.data()));
  ASSERT_EQ(cudaGetLastError(), cudaSuccess);
  ASSERT_EQ(cudaDeviceSynchronize(), cudaSuccess);
  std::printf(
      "kernel: %zu bytes of local memory per thread, %d registers; stack "
      "limit %zu bytes before the launch, %zu after\n",
      attributes.localSizeBytes, attributes.numRegs, limit_before,
      StackLimit());
  ExpectSameSigns(in, std::vector<int>(d_out.begin(), d_out.end()));
}

}  // namespace
}  // namespace kinetri::core
