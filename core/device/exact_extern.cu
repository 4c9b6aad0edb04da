// The exact predicates' fallbacks as true device functions, compiled on
// their own as relocatable device code at NVVM -O1 (core/CMakeLists.txt,
// KINETRI_CUDA_EXACT_OPTIONS); core/predicates.h calls them from device
// code built with KINETRI_EXACT_EXTERN. On an H200, CUDA 13.0's NVVM at -O3
// got them wrong wherever they were compiled: inlined, cloned per caller or
// alone in this unit (docs/DEVICE.md); at -O1 they agree with the host.
#include "core/predicates.h"

namespace kinetri::core::internal {

__device__ int Orient2dExactExtern(const Vec2& a, const Vec2& b,
                                   const Vec2& c) {
  return Orient2dExactBody(a, b, c);
}

__device__ int InCircleExactExtern(const Vec2& a, const Vec2& b, const Vec2& c,
                                   const Vec2& d) {
  return InCircleExactBody(a, b, c, d);
}

__device__ int CompareDistanceExactExtern(const Vec2& q, const Vec2& a,
                                          const Vec2& b) {
  return CompareDistanceExactBody(q, a, b);
}

__device__ int CompareDistanceToRadiusExactExtern(const Vec2& q, const Vec2& p,
                                                  double r) {
  return CompareDistanceToRadiusExactBody(q, p, r);
}

}  // namespace kinetri::core::internal
