// The exact predicates' fallbacks as true device functions, compiled on
// their own as relocatable device code (CMake option
// KINETRI_CUDA_EXACT_EXTERN; core/predicates.h calls them from device code
// built with KINETRI_EXACT_EXTERN). NVVM sees no caller here, so it cannot
// specialize or clone them per call site: compiled per caller at -O3 they
// came out wrong on an H200 (docs/DEVICE.md).
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
