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

}  // namespace kinetri::core

#endif  // KINETRI_CORE_MESH_SCAN_H_
