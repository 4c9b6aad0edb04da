// Delaunay neighbours of every site in compressed rows (CSR), built from the
// half-edge mesh after a step. Queries walk these contiguous rows instead of
// chasing twin pointers around each vertex's fan: the loads of one row are
// independent, which is what makes graph searches (k-NN, radius) cheap.
#ifndef KINETRI_CORE_SITE_ADJACENCY_H_
#define KINETRI_CORE_SITE_ADJACENCY_H_

#include <cstddef>
#include <cstdint>
#include <vector>

#include "core/triangulation_view.h"

namespace kinetri::core {

struct SiteAdjacency {
  // Row of internal vertex v: neighbours[offsets[v] .. offsets[v + 1]).
  // Points that are not site representatives have empty rows. The sum of
  // degrees is below 6 * 2^29 < 2^32, so 32-bit offsets suffice.
  std::vector<uint32_t> offsets;
  std::vector<uint32_t> neighbours;
  // Only when some site holds several points: the external ids of each
  // site's points, ascending (queries emit the first few of a large site
  // without walking and sorting all of them).
  std::vector<uint32_t> member_offsets;
  std::vector<uint32_t> members;

  size_t bytes() const {
    return (offsets.capacity() + neighbours.capacity() +
            member_offsets.capacity() + members.capacity()) *
           sizeof(uint32_t);
  }
};

// Builds the rows of `v` (which must not carry adjacency itself) in
// parallel; call inside the triangulation's thread arena.
void BuildSiteAdjacency(const TriangulationView& v, SiteAdjacency* out);

}  // namespace kinetri::core

#endif  // KINETRI_CORE_SITE_ADJACENCY_H_
