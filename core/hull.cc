// Hull checks shared by the CPU executors.
#include "core/hull.h"

#include "core/flip_rules.h"

namespace kinetri::core {

bool HullWindsOnceFrom(const Mesh& mesh, const std::vector<Vec2>& pos,
                       uint32_t* ghost_hint) {
  const MeshView m = mesh.view();
  const uint32_t nt = mesh.num_triangles();
  uint32_t g0 = *ghost_hint;
  if (g0 >= nt || m.IsFree(g0) || !m.IsGhost(g0)) {
    g0 = 0;
    while (g0 < nt && (m.IsFree(g0) || !m.IsGhost(g0))) ++g0;
    if (g0 == nt) return false;
    *ghost_hint = g0;
  }
  auto above = [&](uint32_t u, uint32_t v) {  // (y, x) lexicographic u > v
    const Vec2 &a = pos[u], &b = pos[v];
    return a.y > b.y || (a.y == b.y && a.x > b.x);
  };
  uint32_t g = g0;
  size_t steps = 0, tops = 0;
  do {
    const uint32_t s = rules::SpokeOf(m, g);
    if (s == kNoEdge) return false;
    const uint32_t a = m.origin[s];
    const uint32_t pv = rules::SpokePrev(m, s), nx = rules::SpokeNext(m, s);
    if (pv == kInfiniteVertex || nx == kInfiniteVertex) return false;
    if (above(a, pv) && above(a, nx)) ++tops;
    g = TriangleOf(m.twin[Next(s)]);
    if (++steps > nt) return false;
  } while (g != g0);
  return steps >= 3 && tops == 1;
}

}  // namespace kinetri::core
