// The device grid's source, compiled by device_grid_emulated.cc (host
// compiler, Thrust's TBB system) and device_grid_cuda.cu (nvcc), as the
// device executor is (core/device/round_executor.inl).
#ifndef KINETRI_DEVICE_NS
#error "define KINETRI_DEVICE_NS before including device_grid.inl"
#endif

#include <thrust/binary_search.h>
#include <thrust/device_vector.h>
#include <thrust/for_each.h>
#include <thrust/gather.h>
#include <thrust/iterator/counting_iterator.h>
#include <thrust/sequence.h>
#include <thrust/sort.h>
#include <thrust/transform.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <memory>
#include <type_traits>
#include <vector>

#include "bench/device_grid.h"
#include "core/hd.h"
#include "core/vec2.h"

namespace kinetri::bench {
namespace KINETRI_DEVICE_NS {
namespace {

namespace gthr = THRUST_NS_QUALIFIER;

struct GridView {
  double x0, y0, inv_cell, cell;
  int nx, ny;
  const uint32_t* start;  // cell c holds slots start[c] .. start[c + 1]
  const uint32_t* order;  // point id of each slot
  const core::Vec2* sorted;
  KINETRI_HD int CellX(double x) const {
    const int c = static_cast<int>((x - x0) * inv_cell);
    return c < 0 ? 0 : c >= nx ? nx - 1 : c;
  }
  KINETRI_HD int CellY(double y) const {
    const int c = static_cast<int>((y - y0) * inv_cell);
    return c < 0 ? 0 : c >= ny ? ny - 1 : c;
  }
};
static_assert(std::is_trivially_copyable_v<GridView>);

struct CellOf {
  GridView g;
  KINETRI_HD uint32_t operator()(const core::Vec2& p) const {
    return static_cast<uint32_t>(g.CellY(p.y)) * static_cast<uint32_t>(g.nx) +
           static_cast<uint32_t>(g.CellX(p.x));
  }
};

// Nearest other point of the point in slot s: rings of cells around its
// own until the ring cannot hold anything closer (squared distances; ties
// to the smaller id).
struct NearestOfSlot {
  GridView g;
  uint32_t* nn;
  KINETRI_HD void operator()(uint32_t s) const {
    const core::Vec2 q = g.sorted[s];
    const uint32_t self = g.order[s];
    const int cx = g.CellX(q.x), cy = g.CellY(q.y);
    double best_d2 = 0.0;
    uint32_t best = UINT32_MAX;
    const int rings = g.nx > g.ny ? g.nx : g.ny;
    for (int ring = 0; ring <= rings; ++ring) {
      // Everything in this ring and beyond is farther than (ring - 1) cells.
      if (best != UINT32_MAX && ring > 0) {
        const double reach = (ring - 1) * g.cell;
        if (best_d2 < reach * reach) break;
      }
      for (int y = cy - ring; y <= cy + ring; ++y) {
        if (y < 0 || y >= g.ny) continue;
        const bool edge_row = y == cy - ring || y == cy + ring;
        for (int x = cx - ring; x <= cx + ring;
             x += edge_row || ring == 0 ? 1 : 2 * ring) {
          if (x < 0 || x >= g.nx) continue;
          const uint32_t c = static_cast<uint32_t>(y) * g.nx + x;
          for (uint32_t t = g.start[c]; t < g.start[c + 1]; ++t) {
            const uint32_t j = g.order[t];
            if (j == self) continue;
            const double dx = g.sorted[t].x - q.x, dy = g.sorted[t].y - q.y;
            const double d2 = dx * dx + dy * dy;
            if (best == UINT32_MAX || d2 < best_d2 ||
                (d2 == best_d2 && j < best)) {
              best = j;
              best_d2 = d2;
            }
          }
        }
      }
    }
    nn[self] = best;
  }
};

class Grid final : public DeviceGrid {
 public:
  void Build(const std::vector<core::Vec2>& pts, double cell) override {
    n_ = static_cast<uint32_t>(pts.size());
    core::Vec2 lo{0, 0}, hi{0, 0};
    if (n_ > 0) lo = hi = pts[0];
    for (const core::Vec2& p : pts) {
      lo = {std::min(lo.x, p.x), std::min(lo.y, p.y)};
      hi = {std::max(hi.x, p.x), std::max(hi.y, p.y)};
    }
    if (!(cell > 0.0)) cell = 1.0;
    g_.x0 = lo.x;
    g_.y0 = lo.y;
    g_.cell = cell;
    g_.inv_cell = 1.0 / cell;
    g_.nx = std::max(
        1,
        std::min(1 << 14, static_cast<int>(std::ceil((hi.x - lo.x) / cell))));
    g_.ny = std::max(
        1,
        std::min(1 << 14, static_cast<int>(std::ceil((hi.y - lo.y) / cell))));
    // The cell side follows the clamped counts (every point in a cell).
    g_.cell = std::max((hi.x - lo.x) / g_.nx, (hi.y - lo.y) / g_.ny);
    if (!(g_.cell > 0.0)) g_.cell = 1.0;
    g_.inv_cell = 1.0 / g_.cell;
    const uint32_t cells = static_cast<uint32_t>(g_.nx) * g_.ny;
    pos_.assign(pts.begin(), pts.end());
    keys_.resize(n_);
    gthr::transform(pos_.begin(), pos_.end(), keys_.begin(), CellOf{g_});
    order_.resize(n_);
    gthr::sequence(order_.begin(), order_.end());
    gthr::sort_by_key(keys_.begin(), keys_.end(), order_.begin());
    sorted_.resize(n_);
    gthr::gather(order_.begin(), order_.end(), pos_.begin(), sorted_.begin());
    start_.resize(size_t{cells} + 1);
    gthr::lower_bound(
        keys_.begin(), keys_.end(), gthr::counting_iterator<uint32_t>(0),
        gthr::counting_iterator<uint32_t>(cells + 1), start_.begin());
    g_.start = gthr::raw_pointer_cast(start_.data());
    g_.order = gthr::raw_pointer_cast(order_.data());
    g_.sorted = gthr::raw_pointer_cast(sorted_.data());
  }

  std::vector<uint32_t> AllNearest() override {
    nn_.resize(n_);
    gthr::for_each(gthr::counting_iterator<uint32_t>(0),
                   gthr::counting_iterator<uint32_t>(n_),
                   NearestOfSlot{g_, gthr::raw_pointer_cast(nn_.data())});
    std::vector<uint32_t> out(n_);
    gthr::copy(nn_.begin(), nn_.end(), out.begin());
    return out;
  }

 private:
  uint32_t n_ = 0;
  GridView g_{};
  gthr::device_vector<core::Vec2> pos_, sorted_;
  gthr::device_vector<uint32_t> keys_, order_, start_, nn_;
};

}  // namespace

std::unique_ptr<DeviceGrid> MakeGrid() { return std::make_unique<Grid>(); }

}  // namespace KINETRI_DEVICE_NS
}  // namespace kinetri::bench
