// Shared test helpers: point generators and the CGAL / brute-force oracles.
#include "tests/core/test_util.h"

#include <CGAL/Delaunay_triangulation_2.h>
#include <CGAL/Exact_predicates_inexact_constructions_kernel.h>

#include <algorithm>
#include <cmath>

#include "core/predicates.h"

namespace kinetri::testing {
namespace {
using Kernel = CGAL::Exact_predicates_inexact_constructions_kernel;
using Delaunay = CGAL::Delaunay_triangulation_2<Kernel>;

std::pair<Vec2, Vec2> Normal(Vec2 a, Vec2 b) {
  if (core::LexLess(b, a)) std::swap(a, b);
  return {a, b};
}
bool PairLess(const std::pair<Vec2, Vec2>& x, const std::pair<Vec2, Vec2>& y) {
  if (x.first != y.first) return core::LexLess(x.first, y.first);
  return core::LexLess(x.second, y.second);
}
}  // namespace

bool operator<(const Vec2& a, const Vec2& b) { return core::LexLess(a, b); }

std::vector<Vec2> UniformPoints(size_t n, uint64_t seed, double scale,
                                double offset) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  std::vector<Vec2> out(n);
  for (auto& p : out) p = {offset + scale * u(rng), offset + scale * u(rng)};
  return out;
}

std::vector<Vec2> ClusteredPoints(size_t n, uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  std::normal_distribution<double> g(0.0, 0.01);
  std::vector<Vec2> centers(8);
  for (auto& c : centers) c = {u(rng), u(rng)};
  std::vector<Vec2> out(n);
  for (size_t i = 0; i < n; ++i) {
    const Vec2& c = centers[i % centers.size()];
    out[i] = {c.x + g(rng), c.y + g(rng)};
  }
  return out;
}

std::vector<Vec2> Lattice(int side, double spacing) {
  std::vector<Vec2> out;
  for (int i = 0; i < side; ++i) {
    for (int j = 0; j < side; ++j) out.push_back({i * spacing, j * spacing});
  }
  return out;
}

std::vector<Vec2> Collinear(size_t n, uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::uniform_int_distribution<int> u(-1000, 1000);
  std::vector<Vec2> out(n);
  for (auto& p : out) {
    const int t = u(rng);
    p = {3.0 * t + 1.0, -2.0 * t + 5.0};
  }
  return out;
}

std::vector<Vec2> WithDuplicates(size_t n, int copies, uint64_t seed) {
  std::vector<Vec2> base = UniformPoints(n, seed);
  std::vector<Vec2> out;
  for (int c = 0; c < copies; ++c)
    out.insert(out.end(), base.begin(), base.end());
  std::mt19937_64 rng(seed + 1);
  std::shuffle(out.begin(), out.end(), rng);
  return out;
}

EdgeList CgalDelaunayEdges(const std::vector<Vec2>& points) {
  std::vector<Kernel::Point_2> pts;
  for (const Vec2& p : points) pts.emplace_back(p.x, p.y);
  Delaunay dt(pts.begin(), pts.end());
  EdgeList out;
  for (auto e = dt.finite_edges_begin(); e != dt.finite_edges_end(); ++e) {
    const auto& f = e->first;
    const int i = e->second;
    const auto& a = f->vertex(f->cw(i))->point();
    const auto& b = f->vertex(f->ccw(i))->point();
    out.push_back(Normal({a.x(), a.y()}, {b.x(), b.y()}));
  }
  std::sort(out.begin(), out.end(), PairLess);
  return out;
}

EdgeList EdgesAsPositions(const core::Triangulation& t) {
  EdgeList out;
  for (const auto& [a, b] : t.Edges()) {
    out.push_back(Normal(t.Position(a), t.Position(b)));
  }
  std::sort(out.begin(), out.end(), PairLess);
  return out;
}

EdgeList EdgesOfTriangles(const std::vector<Vec2>& points,
                          const std::vector<uint32_t>& triangles) {
  EdgeList out;
  for (size_t t = 0; t + 2 < triangles.size(); t += 3) {
    for (int k = 0; k < 3; ++k) {
      out.push_back(
          Normal(points[triangles[t + k]], points[triangles[t + (k + 1) % 3]]));
    }
  }
  std::sort(out.begin(), out.end(), PairLess);
  out.erase(std::unique(out.begin(), out.end()), out.end());
  return out;
}

std::vector<uint32_t> BruteRank(const std::vector<Vec2>& pts, const Vec2& q,
                                uint32_t self) {
  std::vector<uint32_t> ids;
  for (uint32_t i = 0; i < pts.size(); ++i) {
    if (i != self) ids.push_back(i);
  }
  std::sort(ids.begin(), ids.end(), [&](uint32_t a, uint32_t b) {
    const int c = core::CompareCloser(q, pts[a], pts[b]);
    return c != 0 ? c < 0 : a < b;
  });
  return ids;
}

std::vector<Vec2> QueryPoints(const std::vector<Vec2>& pts, size_t m,
                              uint64_t seed) {
  std::mt19937_64 rng(seed);
  Vec2 lo{1e300, 1e300}, hi{-1e300, -1e300};
  for (const Vec2& p : pts) {
    lo = {std::min(lo.x, p.x), std::min(lo.y, p.y)};
    hi = {std::max(hi.x, p.x), std::max(hi.y, p.y)};
  }
  if (pts.empty()) lo = {0, 0}, hi = {1, 1};
  std::uniform_real_distribution<double> u(-0.2, 1.2);
  std::uniform_int_distribution<size_t> pick(0,
                                             pts.empty() ? 0 : pts.size() - 1);
  std::vector<Vec2> q(m);
  for (size_t i = 0; i < m; ++i) {
    if (i % 3 == 0 && !pts.empty()) {
      q[i] = pts[pick(rng)];  // exactly on a point
    } else {
      q[i] = {lo.x + u(rng) * (hi.x - lo.x + 1e-9),
              lo.y + u(rng) * (hi.y - lo.y + 1e-9)};
    }
  }
  return q;
}

core::DisplacementBatch Brownian(size_t n, double sigma, std::mt19937_64& rng) {
  std::normal_distribution<double> g(0.0, sigma);
  std::vector<Vec2> d(n);
  for (auto& v : d) v = {g(rng), g(rng)};
  return core::DisplacementBatch::Dense(std::move(d));
}

}  // namespace kinetri::testing
