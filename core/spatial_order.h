// Hilbert-curve ordering of points, used to number vertices for locality.
#ifndef KINETRI_CORE_SPATIAL_ORDER_H_
#define KINETRI_CORE_SPATIAL_ORDER_H_

#include <cstdint>
#include <vector>

#include "absl/types/span.h"
#include "core/vec2.h"

namespace kinetri::core {

// Index of (x, y) along a Hilbert curve of order 21 over [lo, hi]^2.
uint64_t HilbertKey(const Vec2& p, const Vec2& lo, const Vec2& hi);

// Point indices sorted along the Hilbert curve of their bounding box (ties
// by index, so the result is deterministic). `keys` (optional): the keys of
// the sorted points, in that order (equal positions have equal keys).
std::vector<uint32_t> HilbertOrder(absl::Span<const Vec2> points,
                                   std::vector<uint64_t>* keys = nullptr);

}  // namespace kinetri::core

#endif  // KINETRI_CORE_SPATIAL_ORDER_H_
