// The executor a motion test runs on. The motion tests are built four
// times: for the region executor (default), with KINETRI_TEST_FILTER for the
// region executor with vertex tolerances forced on every step, with
// KINETRI_TEST_ROUNDS for the round executor, and with KINETRI_TEST_DEVICE for
// the device executor on its emulated backend (the CCCL source on CPU threads),
// so every sequence checks all of them against CGAL. With KINETRI_TEST_CUDA
// (CUDA builds) the same suites run on the CUDA backend, skipped where there is
// no GPU.
#ifndef KINETRI_TESTS_CORE_EXECUTOR_UNDER_TEST_H_
#define KINETRI_TESTS_CORE_EXECUTOR_UNDER_TEST_H_

#include "core/triangulation.h"

namespace kinetri::testing {

#if defined(KINETRI_TEST_ROUNDS) || defined(KINETRI_TEST_DEVICE) || \
    defined(KINETRI_TEST_CUDA)
inline constexpr bool kRegionExecutor = false;
#else
inline constexpr bool kRegionExecutor = true;
#endif

inline core::TriangulationOptions ExecutorOptions() {
  core::TriangulationOptions o;
#if defined(KINETRI_TEST_ROUNDS)
  o.executor = core::Executor::kRounds;
#elif defined(KINETRI_TEST_DEVICE)
  o.executor = core::Executor::kDevice;
  o.device_backend = core::device::DeviceBackend::kEmulated;
#elif defined(KINETRI_TEST_CUDA)
  o.executor = core::Executor::kDevice;
  o.device_backend = core::device::DeviceBackend::kCuda;
#else
  o.executor = core::Executor::kRegions;
  // Test meshes are small: small regions make most of them parallel and
  // send many elements across boundaries to the serial pass.
  o.region.region_triangles = 256;
#if defined(KINETRI_TEST_FILTER)
  // Vertex tolerances on every step, whatever the motion, and the sparse
  // scan around the loud vertices however many there are.
  o.region.filter_estimate = 1.0;
  o.region.filter_fraction = 1.0;
  o.region.sparse_fraction = 1.0;
#endif
#endif
  return o;
}

}  // namespace kinetri::testing

#endif  // KINETRI_TESTS_CORE_EXECUTOR_UNDER_TEST_H_
