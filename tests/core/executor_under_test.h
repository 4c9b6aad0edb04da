// The executor a motion test runs on. The motion tests are built twice: for
// the region executor (default) and, with KINETRI_TEST_ROUNDS, for the round
// executor, so every sequence checks both against CGAL.
#ifndef KINETRI_TESTS_CORE_EXECUTOR_UNDER_TEST_H_
#define KINETRI_TESTS_CORE_EXECUTOR_UNDER_TEST_H_

#include "core/triangulation.h"

namespace kinetri::testing {

#ifdef KINETRI_TEST_ROUNDS
inline constexpr bool kRegionExecutor = false;
#else
inline constexpr bool kRegionExecutor = true;
#endif

inline core::TriangulationOptions ExecutorOptions() {
  core::TriangulationOptions o;
#ifdef KINETRI_TEST_ROUNDS
  o.executor = core::Executor::kRounds;
#else
  o.executor = core::Executor::kRegions;
  // Test meshes are small: small regions make most of them parallel and
  // send many elements across boundaries to the serial pass.
  o.region.region_triangles = 256;
#endif
  return o;
}

}  // namespace kinetri::testing

#endif  // KINETRI_TESTS_CORE_EXECUTOR_UNDER_TEST_H_
