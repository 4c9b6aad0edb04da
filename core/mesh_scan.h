// The dense scan of a kinetic step: which triangles are invalid and which
// edges are not locally Delaunay for new positions, over a range of
// triangle slots.
//
// It answers exactly what rules::TriangleOk and rules::IsIllegal answer
// (the same exact predicates behind the same floating-point filters), but
// laid out for the CPU: each triangle is translated once and the filters
// of its three edges run in the lanes of one vector, from both sides of
// each edge, so the loop has no branch that the data make unpredictable.
// Only what the filters cannot decide goes to the exact predicates.
#ifndef KINETRI_CORE_MESH_SCAN_H_
#define KINETRI_CORE_MESH_SCAN_H_

#include <cstdint>
#include <vector>

#include "core/mesh.h"
#include "core/vec2.h"

namespace kinetri::core {

// Appends to *invalid the triangles t in [lo, hi) with !rules::TriangleOk
// and to *illegal the canonical half-edges e (e < twin(e)) of those
// triangles with rules::IsIllegal, both in increasing order. Free slots
// are skipped; edges of ghost triangles are never illegal.
void ScanTriangles(const MeshView& m, const Vec2* pos, uint32_t lo, uint32_t hi,
                   std::vector<uint32_t>* invalid,
                   std::vector<uint32_t>* illegal);

// The same scan, with the apex across each half-edge e read from
// across[e] (== m.Across(e), as FillAcross writes it) instead of from
// origin[Prev(twin[e])]: the loads of a triangle's apexes then lie next to
// its own vertices instead of in its neighbours' slots, which a dense scan
// waits for (kinetri-scan-probe, docs/BENCHMARKS.md). For finite
// triangles, twin is read only for edges the floating-point filter cannot
// decide (ghosts are decided by rules::TriangleOk on the mesh, as before).
void ScanTriangles(const MeshView& m, const Vec2* pos, const uint32_t* across,
                   uint32_t lo, uint32_t hi, std::vector<uint32_t>* invalid,
                   std::vector<uint32_t>* illegal);

// across[e] = m.Across(e) for the half-edges of triangle slots [lo, hi)
// (kNoVertex for free slots).
void FillAcross(const MeshView& m, uint32_t lo, uint32_t hi, uint32_t* across);

// Keeps such an array valid where triangle t changed (a flip or unflip of
// one of its edges, a split, a removal that rewrote or freed it): t's
// entries, and those of the half-edges on the other side of its edges
// (they read t's apexes). Writes only entries of t and of its neighbours.
inline void RefreshAcross(const MeshView& m, uint32_t t, uint32_t* across) {
  if (m.IsFree(t)) {
    for (uint32_t e = 3 * t; e < 3 * t + 3; ++e) across[e] = kNoVertex;
    return;
  }
  for (uint32_t e = 3 * t; e < 3 * t + 3; ++e) {
    const uint32_t f = m.twin[e];
    across[e] = m.origin[Prev(f)];
    across[f] = m.origin[Prev(e)];
  }
}

}  // namespace kinetri::core

#endif  // KINETRI_CORE_MESH_SCAN_H_
