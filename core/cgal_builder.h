// Initial / fallback Delaunay construction with CGAL, converted to our Mesh.
#ifndef KINETRI_CORE_CGAL_BUILDER_H_
#define KINETRI_CORE_CGAL_BUILDER_H_

#include <cstdint>
#include <vector>

#include "absl/types/span.h"
#include "core/cancel.h"
#include "core/mesh.h"
#include "core/vec2.h"

namespace kinetri::core {

// Builds the Delaunay triangulation of positions[s] for s in `sites` (which
// must be pairwise distinct). Vertex ids in the returned mesh are the site
// ids; the mesh has positions.size() vertex slots and the canonical layout
// of Mesh::SortTrianglesByVertex. Returns an empty mesh when
// the sites span fewer than two dimensions (fewer than 3, or all collinear).
// Sites are inserted in the order given, each located from the one before:
// in spatial order (as the triangulation's internal ids are) that takes
// linear time; any order is correct. `cancel` (optional) is polled every
// 8K insertions (a few milliseconds) and 1M converted faces; when
// it fires the result is an empty mesh and *cancelled is set.
Mesh BuildDelaunayWithCgal(absl::Span<const Vec2> positions,
                           absl::Span<const uint32_t> sites,
                           const CancelToken* cancel = nullptr,
                           bool* cancelled = nullptr);

// The same triangulation as half-edge arrays (Mesh's layout: three
// half-edges per triangle, ghosts included) without a Mesh around them, for
// builders that assemble several: false (arrays untouched) when the sites
// span fewer than two dimensions or `cancel` fired (*cancelled set).
bool TriangulateWithCgal(absl::Span<const Vec2> positions,
                         absl::Span<const uint32_t> sites,
                         const CancelToken* cancel, bool* cancelled,
                         std::vector<uint32_t>* origin,
                         std::vector<uint32_t>* twin);

}  // namespace kinetri::core

#endif  // KINETRI_CORE_CGAL_BUILDER_H_
