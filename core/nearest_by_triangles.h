// Every vertex's nearest Delaunay neighbour from one pass over the triangle
// slots (all-points nearest neighbour when every point is a site).
//
// The nearest other site of a vertex is one of its Delaunay neighbours, so
// the answer is the first of those in the CompareCloser order from the
// vertex. Walking each vertex's fan (core/query_walks.h, FirstNeighbor)
// finds it, but each step of a walk waits for the load before it. Here the
// half-edges are visited in slot order instead: half-edge a->b (in the
// triangle where it lies) offers b to a. Every ordered pair of neighbours is
// a half-edge of exactly one triangle (finite or ghost), so each vertex sees
// each of its neighbours once; the loads are independent, sequential in the
// slots, local in the positions. CompareCloser is a strict total order, so
// the minimum does not depend on the order of the offers: the answer is the
// walk's, for any thread count.
#ifndef KINETRI_CORE_NEAREST_BY_TRIANGLES_H_
#define KINETRI_CORE_NEAREST_BY_TRIANGLES_H_

#include <cstdint>

#include "core/mesh.h"
#include "core/vec2.h"

namespace kinetri::core {

struct NearestNeighbor {
  double d2 = 0.0;          // squared distance, rounded
  uint32_t id = kNoVertex;  // the neighbour; kNoVertex when none
};

// For each vertex v < num_vertices, out[v] = its neighbour that comes first
// in the CompareCloser order from pos[v] (kNoVertex for a vertex in no
// triangle). `vertex_edge` gives each vertex a half-edge leaving it (the
// vertex's slots decide which part of the pass owns it). Runs on the
// calling thread's task arena.
void NearestNeighborsByTriangles(const MeshView& m, const Vec2* pos,
                                 const uint32_t* vertex_edge,
                                 uint32_t num_vertices, NearestNeighbor* out);

}  // namespace kinetri::core

#endif  // KINETRI_CORE_NEAREST_BY_TRIANGLES_H_
