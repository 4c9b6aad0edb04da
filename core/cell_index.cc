#include "core/cell_index.h"

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/parallel_reduce.h>

#include <cmath>

#include "core/parallel.h"

namespace kinetri::core {
namespace {

struct Box {
  double lo_x = INFINITY, lo_y = INFINITY, hi_x = -INFINITY, hi_y = -INFINITY;
  void Add(const Vec2& p) {
    lo_x = std::min(lo_x, p.x);
    lo_y = std::min(lo_y, p.y);
    hi_x = std::max(hi_x, p.x);
    hi_y = std::max(hi_y, p.y);
  }
  void Add(const Box& b) {
    lo_x = std::min(lo_x, b.lo_x);
    lo_y = std::min(lo_y, b.lo_y);
    hi_x = std::max(hi_x, b.hi_x);
    hi_y = std::max(hi_y, b.hi_y);
  }
};

}  // namespace

std::optional<CellIndex> CellIndex::Build(const TriangulationView& v,
                                          double cell, size_t max_cells) {
  const uint32_t ns = v.num_sites;
  if (ns == 0 || !(cell > 0.0) || !std::isfinite(1.0 / cell)) {
    return std::nullopt;
  }
  const Box box = tbb::parallel_reduce(
      tbb::blocked_range<uint32_t>(0, ns, 4096), Box{},
      [&](const tbb::blocked_range<uint32_t>& r, Box b) {
        for (uint32_t i = r.begin(); i != r.end(); ++i)
          b.Add(v.pos[v.sites[i]]);
        return b;
      },
      [](Box a, const Box& b) {
        a.Add(b);
        return a;
      });
  CellIndex g;
  g.inv_ = 1.0 / cell;
  const double cx = std::floor((box.hi_x - box.lo_x) * g.inv_) + 1.0;
  const double cy = std::floor((box.hi_y - box.lo_y) * g.inv_) + 1.0;
  if (!(cx * cy <= static_cast<double>(max_cells))) return std::nullopt;
  g.x0_ = box.lo_x;
  g.y0_ = box.lo_y;
  g.nx_ = static_cast<uint32_t>(cx);
  g.ny_ = static_cast<uint32_t>(cy);
  const size_t cells = g.num_cells();
  // Counting sort of the sites (in their internal, Hilbert order, which
  // each cell keeps) by cell.
  std::vector<uint32_t> key(ns);
  ParallelFor(0, ns, [&](size_t i) {
    const Vec2& p = v.pos[v.sites[i]];
    key[i] = static_cast<uint32_t>(size_t{g.Cell(p.y, g.y0_, g.ny_)} * g.nx_ +
                                   g.Cell(p.x, g.x0_, g.nx_));
  });
  g.start_.assign(cells + 1, 0);
  for (uint32_t k : key) ++g.start_[k + 1];
  for (size_t c = 0; c < cells; ++c) g.start_[c + 1] += g.start_[c];
  g.site_.resize(ns);
  g.pos_.resize(ns);
  g.ext_.resize(ns);
  std::vector<uint32_t> next(g.start_.begin(), g.start_.end() - 1);
  for (uint32_t i = 0; i < ns; ++i) {
    const uint32_t s = next[key[i]]++;
    g.site_[s] = v.sites[i];
    g.pos_[s] = v.pos[v.sites[i]];
    g.ext_[s] = v.dup_next[v.sites[i]] == kNoVertex ? v.ext_of_int[v.sites[i]]
                                                    : kNoVertex;
  }
  return g;
}

}  // namespace kinetri::core
