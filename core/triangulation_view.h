// Trivially copyable read-only view of a Triangulation for per-element code.
#ifndef KINETRI_CORE_TRIANGULATION_VIEW_H_
#define KINETRI_CORE_TRIANGULATION_VIEW_H_

#include <cstdint>

#include "core/hd.h"
#include "core/mesh.h"
#include "core/vec2.h"

namespace kinetri::core {

struct TriangulationView {
  const Vec2* pos = nullptr;  // by internal id
  const uint32_t* ext_of_int = nullptr;
  const uint32_t* int_of_ext = nullptr;
  const uint32_t* rep = nullptr;       // site representative of each point
  const uint32_t* dup_next = nullptr;  // next point of the same site
  const uint32_t* sites = nullptr;     // representatives, ascending
  uint32_t num_points = 0;
  uint32_t num_sites = 0;
  // Planar mode (mesh.num_half_edges > 0):
  MeshView mesh;
  const uint32_t* vertex_edge = nullptr;
  // Line mode:
  const uint32_t* line = nullptr;
  const uint32_t* line_rank = nullptr;
  // Optional contiguous neighbour rows (SiteAdjacency); when set,
  // ForEachNeighbor reads them instead of walking the mesh.
  const uint32_t* adj_offsets = nullptr;
  const uint32_t* adj = nullptr;
  // Optional (query views of point sets with coincident points): the
  // external ids of the points of site v, ascending, are
  // site_members[site_member_offsets[v] .. site_member_offsets[v + 1]).
  const uint32_t* site_member_offsets = nullptr;
  const uint32_t* site_members = nullptr;

  KINETRI_HD bool planar() const { return mesh.num_half_edges > 0; }

  // The neighbour row of site v; only with adjacency (query views).
  KINETRI_HD const uint32_t* RowBegin(uint32_t v) const {
    return adj + adj_offsets[v];
  }
  KINETRI_HD const uint32_t* RowEnd(uint32_t v) const {
    return adj + adj_offsets[v + 1];
  }

  // Calls fn(w) for every Delaunay neighbour site w of site v.
  template <typename Fn>
  KINETRI_HD void ForEachNeighbor(uint32_t v, Fn&& fn) const {
    if (adj_offsets != nullptr) {
      const uint32_t end = adj_offsets[v + 1];
      for (uint32_t k = adj_offsets[v]; k < end; ++k) fn(adj[k]);
      return;
    }
    if (planar()) {
      const uint32_t e0 = vertex_edge[v];
      if (e0 == kNoEdge) return;
      uint32_t e = e0;
      do {
        const uint32_t w = mesh.Dest(e);
        if (w != kInfiniteVertex) fn(w);
        e = mesh.twin[Prev(e)];
      } while (e != e0);
      return;
    }
    const uint32_t r = line_rank[v];
    if (r > 0) fn(line[r - 1]);
    if (r + 1 < num_sites) fn(line[r + 1]);
  }
};

}  // namespace kinetri::core

#endif  // KINETRI_CORE_TRIANGULATION_VIEW_H_
