// Delaunay construction on all cores: the sites split into vertical strips,
// each strip triangulated by CGAL on its own thread, neighbouring strips
// stitched along the gap between their convex hulls, and the stitched
// triangulation made Delaunay by Lawson flips from the seams.
#ifndef KINETRI_CORE_STRIP_BUILDER_H_
#define KINETRI_CORE_STRIP_BUILDER_H_

#include <cstddef>
#include <cstdint>

#include "absl/types/span.h"
#include "core/cancel.h"
#include "core/mesh.h"
#include "core/vec2.h"

namespace kinetri::core {

// What a strip build did (for benchmarks and tests).
struct StripBuildStats {
  uint32_t strips = 0;           // strips built (1: a serial CGAL build)
  uint64_t seam_triangles = 0;   // triangles added between strip hulls
  uint64_t seam_flips = 0;       // Lawson flips that made the seams Delaunay
  bool serial_fallback = false;  // a strip spanned < 2 dimensions, or the
                                 // strips' hulls held too many vertices
};

// Strips BuildDelaunayInStrips should use for `num_sites` sites in the
// calling task arena: four per thread, each of at least 32K sites, at most
// 64; 1 (a serial build) for small sets or one thread.
uint32_t DefaultStripCount(size_t num_sites);

// The triangulation BuildDelaunayWithCgal builds (same arguments, same
// contract), built in `strips` vertical strips on the calling task arena.
// Strip boundaries are lexicographic (x, then y) quantiles of the sites, so
// the strips' convex hulls are disjoint; the gap between the union built so
// far and the next strip is filled by a constrained triangulation of their
// hull vertices, and Lawson flips with the exact predicates
// (rules::IsIllegal) then make every edge locally Delaunay. The Delaunay
// triangulation with the symbolic perturbation is unique, so the result has
// the same triangles as the serial build, whatever `strips` is, and both
// come in the canonical layout: the two meshes are equal slot for slot. A
// strip whose sites span fewer than two dimensions, or strips whose hulls
// hold more than max(4096, 1/64 of the sites) vertices in all (points in
// convex position: stitching would cost more than it saves), make the
// whole build serial. `cancel` is polled by every strip's CGAL build,
// before each stitch and every 64K flips.
Mesh BuildDelaunayInStrips(absl::Span<const Vec2> positions,
                           absl::Span<const uint32_t> sites, uint32_t strips,
                           const CancelToken* cancel = nullptr,
                           bool* cancelled = nullptr,
                           StripBuildStats* stats = nullptr);

}  // namespace kinetri::core

#endif  // KINETRI_CORE_STRIP_BUILDER_H_
