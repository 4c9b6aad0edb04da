// Local re-insertion: removing a vertex from, and inserting one into, a valid
// triangulation (the fallback for vertices whose motion fixing cannot repair).
#include "core/vertex_ops.h"

#include <cstddef>

#include "core/flip_rules.h"
#include "core/predicates.h"

namespace kinetri::core {

namespace {

// Ear-clips the counter-clockwise simple polygon `poly` (exact predicates);
// appends triangles to `out`. False if no ear can be found.
bool EarClip(const std::vector<Vec2>& pos, std::vector<uint32_t> poly,
             std::vector<std::array<uint32_t, 3>>* out) {
  while (poly.size() > 3) {
    const size_t m = poly.size();
    bool clipped = false;
    for (size_t i = 0; i < m && !clipped; ++i) {
      const uint32_t a = poly[(i + m - 1) % m], b = poly[i],
                     c = poly[(i + 1) % m];
      if (Orient2d(pos[a], pos[b], pos[c]) <= 0) continue;
      bool empty = true;
      for (size_t j = 0; j < m && empty; ++j) {
        const uint32_t x = poly[j];
        if (x == a || x == b || x == c) continue;
        if (Orient2d(pos[a], pos[b], pos[x]) >= 0 &&
            Orient2d(pos[b], pos[c], pos[x]) >= 0 &&
            Orient2d(pos[c], pos[a], pos[x]) >= 0) {
          empty = false;
        }
      }
      if (!empty) continue;
      out->push_back({a, b, c});
      poly.erase(poly.begin() + static_cast<std::ptrdiff_t>(i));
      clipped = true;
    }
    if (!clipped) return false;
  }
  if (Orient2d(pos[poly[0]], pos[poly[1]], pos[poly[2]]) <= 0) return false;
  out->push_back({poly[0], poly[1], poly[2]});
  return true;
}

}  // namespace

bool VertexOps::Remove(Mesh& mesh, const std::vector<Vec2>& pos, uint32_t v,
                       std::vector<uint32_t>* touched, uint64_t* flips) {
  (void)flips;
  const MeshView m = mesh.view();
  const uint32_t e0 = mesh.vertex_edge()[v];
  if (e0 == kNoEdge) return false;
  // Star of v, counter-clockwise: triangle k = (v, x_k, x_{k+1}).
  std::vector<uint32_t> ring, x, outer_twin, tris;
  uint32_t e = e0;
  do {
    ring.push_back(e);
    if (ring.size() > (1u << 16)) return false;
    e = m.twin[Prev(e)];
  } while (e != e0);
  const size_t deg = ring.size();
  size_t inf_at = deg;
  for (size_t k = 0; k < deg; ++k) {
    x.push_back(m.Dest(ring[k]));
    outer_twin.push_back(m.twin[Next(ring[k])]);
    tris.push_back(TriangleOf(ring[k]));
    if (x.back() == kInfiniteVertex) inf_at = k;
  }
  // New triangles covering the star without v.
  std::vector<std::array<uint32_t, 3>> fresh;
  if (inf_at == deg) {
    if (!EarClip(pos, x, &fresh)) return false;
  } else {
    // Hull vertex: chain q = c_0 .. c_m = p (ring order after inf).
    std::vector<uint32_t> chain;
    for (size_t k = 1; k < deg; ++k) chain.push_back(x[(inf_at + k) % deg]);
    const size_t mm = chain.size();
    if (mm < 2) return false;
    // Convex chain facing v, from p back to q (Graham scan around v).
    std::vector<size_t> hull;  // indices into chain, descending
    for (size_t k = mm; k-- > 0;) {
      while (hull.size() >= 2 &&
             Orient2d(pos[chain[hull[hull.size() - 2]]],
                      pos[chain[hull.back()]], pos[chain[k]]) < 0) {
        hull.pop_back();
      }
      hull.push_back(k);
    }
    for (size_t j = 0; j + 1 < hull.size(); ++j) {
      const size_t a = hull[j], b = hull[j + 1];  // a > b
      // Ghost on the outer side of the new hull edge chain[a] -> chain[b].
      fresh.push_back({chain[b], chain[a], kInfiniteVertex});
      if (a - b >= 2) {
        std::vector<uint32_t> pocket = {chain[a]};
        for (size_t k = b; k < a; ++k) pocket.push_back(chain[k]);
        if (!EarClip(pos, pocket, &fresh)) return false;
      }
    }
  }
  if (fresh.size() + 2 != deg) return false;
  // Write the new triangles into the first deg-2 slots of the star and link
  // twins: boundary edges to the outside, inner edges to each other.
  std::vector<uint32_t> slots(tris.begin(), tris.begin() + (deg - 2));
  for (size_t i = 0; i < fresh.size(); ++i) {
    for (int k = 0; k < 3; ++k) m.origin[3 * slots[i] + k] = fresh[i][k];
  }
  for (size_t i = 0; i < fresh.size(); ++i) {
    for (int k = 0; k < 3; ++k) {
      const uint32_t h = 3 * slots[i] + k;
      const uint32_t u = fresh[i][k], w = fresh[i][(k + 1) % 3];
      uint32_t tw = kNoEdge;
      for (size_t j = 0; j < deg && tw == kNoEdge; ++j) {
        if (x[j] == u && x[(j + 1) % deg] == w) tw = outer_twin[j];
      }
      for (size_t i2 = 0; i2 < fresh.size() && tw == kNoEdge; ++i2) {
        for (int k2 = 0; k2 < 3; ++k2) {
          if (fresh[i2][k2] == w && fresh[i2][(k2 + 1) % 3] == u) {
            tw = 3 * slots[i2] + static_cast<uint32_t>(k2);
            break;
          }
        }
      }
      if (tw == kNoEdge) return false;  // cannot happen for a valid star
      m.twin[h] = tw;
      m.twin[tw] = h;
    }
  }
  mesh.FreeTriangle(tris[deg - 2]);
  mesh.FreeTriangle(tris[deg - 1]);
  auto& ve = mesh.mutable_vertex_edge();
  for (size_t i = 0; i < fresh.size(); ++i) {
    for (int k = 0; k < 3; ++k) {
      if (fresh[i][k] != kInfiniteVertex) ve[fresh[i][k]] = 3 * slots[i] + k;
    }
    if (touched) touched->push_back(slots[i]);
  }
  ve[v] = kNoEdge;
  // Every new triangle and the hull turns next to it must be valid.
  for (uint32_t t : slots) {
    if (!rules::TriangleOk(m, pos.data(), t)) return false;
    for (uint32_t h = 3 * t; h < 3 * t + 3; ++h) {
      if (!rules::TriangleOk(m, pos.data(), TriangleOf(m.twin[h]))) {
        return false;
      }
    }
  }
  return true;
}

VertexOps::Location VertexOps::Locate(const Mesh& mesh,
                                      const std::vector<Vec2>& pos,
                                      const Vec2& p, uint32_t start_triangle) {
  const MeshView m = mesh.view();
  uint32_t t = start_triangle;
  const uint64_t max_steps = uint64_t{4} * mesh.num_triangles() + 16;
  uint32_t rotate = 0;
  for (uint64_t step = 0; step < max_steps; ++step) {
    if (m.IsGhost(t)) {
      const uint32_t s = rules::SpokeOf(m, t);
      // Finite edge of the ghost: Prev(s) = x -> a, hull edge a -> x.
      const uint32_t fe = Prev(s);
      const uint32_t x = m.origin[fe], a = m.Dest(fe);
      if (Orient2d(pos[a], pos[x], p) < 0) return {t, kNoVertex};
      t = TriangleOf(m.twin[fe]);
      continue;
    }
    bool moved = false;
    for (uint32_t k = 0; k < 3; ++k) {
      const uint32_t e = 3 * t + (k + rotate) % 3;
      if (Orient2d(pos[m.origin[e]], pos[m.Dest(e)], p) < 0) {
        t = TriangleOf(m.twin[e]);
        moved = true;
        break;
      }
    }
    ++rotate;
    if (moved) continue;
    for (uint32_t e = 3 * t; e < 3 * t + 3; ++e) {
      if (pos[m.origin[e]] == p) return {t, m.origin[e]};
    }
    return {t, kNoVertex};
  }
  return {kNoEdge, kNoVertex};
}

std::array<uint32_t, 3> VertexOps::Split(Mesh& mesh, uint32_t t, uint32_t v) {
  const uint32_t t1 = mesh.AllocateTriangle();
  const uint32_t t2 = mesh.AllocateTriangle();
  const MeshView m = mesh.view();
  const uint32_t tri[3] = {t, t1, t2};
  uint32_t org[3], tw[3];
  for (int k = 0; k < 3; ++k) {
    org[k] = m.origin[3 * t + k];
    tw[k] = m.twin[3 * t + k];
  }
  // Triangle k = (org[k], org[k+1], v): slot 0 keeps the outer edge.
  for (int k = 0; k < 3; ++k) {
    const uint32_t base = 3 * tri[k];
    const int k1 = (k + 1) % 3, k2 = (k + 2) % 3;
    m.origin[base] = org[k];
    m.origin[base + 1] = org[k1];
    m.origin[base + 2] = v;
    m.twin[base] = tw[k];
    m.twin[tw[k]] = base;
    // org[k1] -> v pairs with v -> org[k1], slot 2 of triangle k1.
    m.twin[base + 1] = 3 * tri[k1] + 2;
    m.twin[3 * tri[k1] + 2] = base + 1;
    (void)k2;
  }
  auto& ve = mesh.mutable_vertex_edge();
  for (int k = 0; k < 3; ++k) {
    if (org[k] != kInfiniteVertex) ve[org[k]] = 3 * tri[k];
  }
  ve[v] = 3 * t + 2;
  return {t, t1, t2};
}

}  // namespace kinetri::core
