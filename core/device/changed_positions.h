// The host side of sending positions to the device as changes: which
// entries of the host's array differ, bit for bit, from the host's copy of
// what the device holds: a pass over both arrays, in parallel blocks, or
// over the entries the caller names.
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

// The same, looking only at the entries `written` (ascending, unique, each
// below now.size()) where the caller says it wrote since `mirror` was
// `now`'s copy: a pass over them alone, for an attempt that moves a few
// vertices of a large mesh. An entry written with its old value is not a
// change. The caller's list must hold every changed entry (a change left
// out is not found).
bool ChangedPositionsAt(absl::Span<const Vec2> now,
                        absl::Span<const Vec2> mirror,
                        absl::Span<const uint32_t> written, size_t most,
                        std::vector<uint32_t>* index, std::vector<Vec2>* value);

}  // namespace kinetri::core::device

#endif  // KINETRI_CORE_DEVICE_CHANGED_POSITIONS_H_
