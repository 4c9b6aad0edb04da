// Local re-insertion: removing a vertex from, and inserting one into, a valid
// triangulation (the fallback for vertices whose motion fixing cannot repair).
#ifndef KINETRI_CORE_VERTEX_OPS_H_
#define KINETRI_CORE_VERTEX_OPS_H_

#include <array>
#include <cstdint>
#include <vector>

#include "core/mesh.h"
#include "core/vec2.h"

namespace kinetri::core {

class VertexOps {
 public:
  // Removes vertex v from a valid triangulation of pos and re-triangulates
  // its star: an interior vertex's star polygon by ear clipping; a hull
  // vertex's by the convex chain of its neighbours that becomes the new hull
  // (Graham scan around v) plus ear-clipped pockets behind it. Two triangle
  // slots are freed. The result is valid, not necessarily Delaunay; `touched`
  // receives the new triangles. Returns false if the result would be invalid
  // (the caller then rebuilds).
  static bool Remove(Mesh& mesh, const std::vector<Vec2>& pos, uint32_t v,
                     std::vector<uint32_t>* touched, uint64_t* flips);

  struct Location {
    uint32_t triangle = kNoEdge;      // triangle containing p (closed)
    uint32_t coincident = kNoVertex;  // vertex exactly at p, if any
  };
  // Visibility walk from start_triangle to p (valid Delaunay mesh).
  static Location Locate(const Mesh& mesh, const std::vector<Vec2>& pos,
                         const Vec2& p, uint32_t start_triangle);

  // Splits triangle t (finite or ghost) into three around new vertex v;
  // returns the three triangles. Degenerate pieces (v on an edge) are left
  // for the fixing step.
  static std::array<uint32_t, 3> Split(Mesh& mesh, uint32_t t, uint32_t v);
};

}  // namespace kinetri::core

#endif  // KINETRI_CORE_VERTEX_OPS_H_
