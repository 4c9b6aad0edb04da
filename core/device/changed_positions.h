// The host side of sending positions to the device as changes: which
// entries of the host's array differ, bit for bit, from the host's copy of
// what the device holds. A pass over both arrays, in parallel blocks.
#ifndef KINETRI_CORE_DEVICE_CHANGED_POSITIONS_H_
#define KINETRI_CORE_DEVICE_CHANGED_POSITIONS_H_

#include <cstddef>
#include <cstdint>
#include <vector>

#include "absl/types/span.h"
#include "core/vec2.h"

namespace kinetri::core::device {

// Fills `index` (ascending) and `value` with the entries of `now` whose
// bits differ from `mirror` (of the same size; 0.0 and -0.0 differ) and
// returns true when there are at most `most`; returns false (the vectors'
// contents unspecified) as soon as more are found. The result does not
// depend on the thread count.
bool ChangedPositions(absl::Span<const Vec2> now, absl::Span<const Vec2> mirror,
                      size_t most, std::vector<uint32_t>* index,
                      std::vector<Vec2>* value);

}  // namespace kinetri::core::device

#endif  // KINETRI_CORE_DEVICE_CHANGED_POSITIONS_H_
