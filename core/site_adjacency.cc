#include "core/site_adjacency.h"

#include "core/parallel.h"

namespace kinetri::core {

void BuildSiteAdjacency(const TriangulationView& v, SiteAdjacency* out) {
  const uint32_t n = v.num_points;
  out->offsets.assign(size_t{n} + 1, 0);
  ParallelFor(0, n, [&](size_t i) {
    const uint32_t s = static_cast<uint32_t>(i);
    if (v.rep[s] != s) return;
    uint32_t degree = 0;
    v.ForEachNeighbor(s, [&](uint32_t) { ++degree; });
    out->offsets[i + 1] = degree;
  });
  for (uint32_t i = 0; i < n; ++i) out->offsets[i + 1] += out->offsets[i];
  out->neighbours.resize(out->offsets[n]);
  ParallelFor(0, n, [&](size_t i) {
    uint32_t k = out->offsets[i];
    if (k == out->offsets[i + 1]) return;
    v.ForEachNeighbor(static_cast<uint32_t>(i),
                      [&](uint32_t w) { out->neighbours[k++] = w; });
  });
}

}  // namespace kinetri::core
