#include "core/motion_filter.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <limits>

#include "core/parallel.h"
#include "core/predicates.h"

namespace kinetri::core {
namespace {

// Relative margin taken off every certified distance: far above the
// rounding error of the few operations behind each (a handful of ulps,
// about 1e-15), so a certificate is a lower bound of the true distance.
constexpr double kMargin = 1e-12;
constexpr double kUnbounded = std::numeric_limits<double>::infinity();

double Dist2(Vec2 a, Vec2 b) {
  const double dx = a.x - b.x, dy = a.y - b.y;
  return dx * dx + dy * dy;
}

double Dist(Vec2 a, Vec2 b) { return std::sqrt(Dist2(a, b)); }

// |to - ref| < tol, certainly.
bool Within(Vec2 to, Vec2 ref, double tol) {
  return Dist2(to, ref) * (1.0 + kMargin) < tol * tol * (1.0 - kMargin);
}

void AtomicMinDouble(double* slot, double value) {
  std::atomic_ref<double> ref(*slot);
  double cur = ref.load(std::memory_order_relaxed);
  while (value < cur &&
         !ref.compare_exchange_weak(cur, value, std::memory_order_relaxed)) {
  }
}

double Finite(double h) { return h > 0.0 && std::isfinite(h) ? h : 0.0; }

// The tolerance of vertex v from every certificate it belongs to, at pos:
// the certificates of the triangles around it and of the ghosts next to
// its ghosts (the hull corners of its hull neighbours).
double VertexTolerance(const MeshView& m, const Vec2* pos, uint32_t e0) {
  const uint32_t v = m.origin[e0];
  double tol = kUnbounded;
  auto take = [&](uint32_t u, double h) {
    if (u == v) tol = std::min(tol, h);
  };
  auto every_side = [](uint32_t, uint32_t) { return false; };
  uint32_t x = e0;
  do {
    const uint32_t t = TriangleOf(x);
    ForEachCertificate(m, pos, t, take, every_side);
    if (m.IsGhost(t)) {
      for (uint32_t e = 3 * t; e < 3 * t + 3; ++e) {
        ForEachCertificate(m, pos, TriangleOf(m.twin[e]), take, every_side);
      }
    }
    x = m.twin[Prev(x)];
  } while (x != e0);
  return tol;
}

}  // namespace

double OrientTolerance(Vec2 a, Vec2 b, Vec2 c) {
  // Twice the area, with Shewchuk's bound on its rounding error: `lower`
  // is certainly at most the exact determinant.
  const double detleft = (a.x - c.x) * (b.y - c.y);
  const double detright = (a.y - c.y) * (b.x - c.x);
  const double det = detleft - detright;
  const double lower = det - internal::kCcwErrBoundA *
                                 (std::fabs(detleft) + std::fabs(detright));
  if (!(lower > 0.0)) return 0.0;
  const double ab = (b.x - a.x) * (b.x - a.x) + (b.y - a.y) * (b.y - a.y);
  const double bc = (c.x - b.x) * (c.x - b.x) + (c.y - b.y) * (c.y - b.y);
  const double ca = (a.x - c.x) * (a.x - c.x) + (a.y - c.y) * (a.y - c.y);
  const double longest = std::sqrt(std::max({ab, bc, ca})) * (1.0 + kMargin);
  // Half the smallest altitude: area / longest side.
  return Finite(lower / (2.0 * longest) * (1.0 - kMargin));
}

double EdgeTolerance(Vec2 p, Vec2 q, Vec2 r, Vec2 s) {
  // Centre o where the bisectors of pq and rs meet, relative to p. Any
  // centre gives a valid annulus (the distances below are what must be
  // right); this one is the widest along pq's bisector.
  const double ux = q.x - p.x, uy = q.y - p.y;
  const double vx = s.x - r.x, vy = s.y - r.y;
  const double mx = 0.5 * (r.x + s.x) - p.x, my = 0.5 * (r.y + s.y) - p.y;
  const double c1 = 0.5 * (ux * ux + uy * uy);  // o.u = |u|^2 / 2
  const double c2 = vx * mx + vy * my;          // o.v = m.v
  const double det = ux * vy - uy * vx;
  if (det == 0.0) return 0.0;
  const double inv = 1.0 / det;
  const Vec2 o{p.x + (c1 * vy - uy * c2) * inv,
               p.y + (ux * c2 - c1 * vx) * inv};
  // Squared distances (each within a few ulps), then one square root:
  // (R2 - R1) / 2 = (R2^2 - R1^2) / (2 (R1 + R2)) >= (R2^2 - R1^2) / (4 R2).
  const double inner2 = std::max(Dist2(o, p), Dist2(o, q)) * (1.0 + kMargin);
  const double outer2 = std::min(Dist2(o, r), Dist2(o, s)) * (1.0 - kMargin);
  return Finite((outer2 - inner2) / (4.0 * std::sqrt(outer2)) *
                (1.0 - kMargin));
}

void MotionFilter::Certify(const Mesh& mesh, const std::vector<Vec2>& pos) {
  const MeshView m = mesh.view();
  const size_t n = pos.size();
  ref_ = pos;
  tol_.assign(n, kUnbounded);
  reset_.assign(n, 0);
  double* tol = tol_.data();
  ParallelFor(
      0, mesh.num_triangles(),
      [&](size_t t) {
        ForEachCertificate(
            m, pos.data(), static_cast<uint32_t>(t),
            [&](uint32_t u, double h) { AtomicMinDouble(&tol[u], h); },
            [](uint32_t e, uint32_t f) { return f < e; });
      },
      4096);
  valid_ = true;
}

std::vector<uint32_t> MotionFilter::Loud(const std::vector<uint32_t>& moved,
                                         const std::vector<Vec2>& to) const {
  std::vector<uint32_t> out = FilterIndices(moved.size(), [&](size_t k) {
    const uint32_t v = moved[k];
    return !Within(to[v], ref_[v], tol_[v]);
  });
  for (uint32_t& k : out) k = moved[k];
  return out;
}

void MotionFilter::Recertify(const Mesh& mesh, const std::vector<Vec2>& pos,
                             const std::vector<uint32_t>& loud,
                             const std::vector<uint8_t>& changed) {
  const MeshView m = mesh.view();
  ParallelFor(0, loud.size(), [&](size_t i) {
    const uint32_t v = loud[i];
    ref_[v] = pos[v];
    tol_[v] = kUnbounded;
    reset_[v] = 1;
  });
  const std::vector<uint32_t> touched =
      FilterIndices(changed.size(), [&](size_t t) { return changed[t] != 0; });
  double* tol = tol_.data();
  ParallelFor(
      0, touched.size(),
      [&](size_t i) {
        ForEachCertificate(
            m, pos.data(), touched[i],
            [&](uint32_t u, double h) {
              if (reset_[u]) {
                AtomicMinDouble(&tol[u], h);
              } else {
                // |ref - c_E| + tol <= h, with c_E = pos now.
                const double d = Dist(pos[u], ref_[u]) * (1.0 + kMargin);
                AtomicMinDouble(&tol[u], std::max(0.0, h - d));
              }
            },
            [&](uint32_t e, uint32_t f) {
              return f < e && changed[TriangleOf(f)] != 0;
            });
      },
      256);
  ParallelFor(0, loud.size(), [&](size_t i) { reset_[loud[i]] = 0; });
}

double MotionFilter::EstimateLoudFraction(const Mesh& mesh,
                                          const std::vector<Vec2>& from,
                                          const std::vector<Vec2>& to,
                                          const std::vector<uint32_t>& moved,
                                          uint32_t samples) {
  if (moved.empty() || samples == 0) return 0.0;
  const MeshView m = mesh.view();
  const auto& ve = mesh.vertex_edge();
  const size_t stride = std::max<size_t>(1, moved.size() / samples);
  size_t seen = 0, loud = 0;
  for (size_t k = 0; k < moved.size(); k += stride) {
    const uint32_t v = moved[k];
    if (ve[v] == kNoEdge) continue;
    ++seen;
    if (!Within(to[v], from[v], VertexTolerance(m, from.data(), ve[v]))) {
      ++loud;
    }
  }
  return seen ? static_cast<double>(loud) / static_cast<double>(seen) : 0.0;
}

}  // namespace kinetri::core
