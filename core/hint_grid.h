// Coarse uniform grid of start sites for greedy walks of position queries:
// each cell holds one site that lies in it (or the first site), so a walk
// from a query's cell takes a few steps. Built on the host; HintGridView is
// trivially copyable and answers on the host and on the device.
#ifndef KINETRI_CORE_HINT_GRID_H_
#define KINETRI_CORE_HINT_GRID_H_

#include <cstddef>
#include <cstdint>
#include <vector>

#include "core/hd.h"
#include "core/triangulation_view.h"
#include "core/vec2.h"

namespace kinetri::core {

struct HintGridView {
  Vec2 lo{0, 0}, hi{0, 0};
  uint32_t side = 0;  // side x side cells; 0: no cells
  const uint32_t* cells = nullptr;
  uint32_t fallback = kNoVertex;  // first site (kNoVertex: no sites)

  KINETRI_HD uint32_t Hint(const Vec2& q) const {
    if (side == 0) return fallback;
    const uint32_t c = cells[Cell(q)];
    return c != kNoVertex ? c : fallback;
  }

  // Row-major cell of q (clamped to the grid).
  KINETRI_HD size_t Cell(const Vec2& q) const {
    return size_t{Index(q.y, lo.y, hi.y)} * side + Index(q.x, lo.x, hi.x);
  }

 private:
  KINETRI_HD uint32_t Index(double x, double l, double h) const {
    if (!(h > l)) return 0;
    const double t = (x - l) / (h - l) * side;
    if (!(t > 0)) return 0;
    return t >= side ? side - 1 : static_cast<uint32_t>(t);
  }
};

class HintGrid {
 public:
  // About four sites per cell.
  explicit HintGrid(const TriangulationView& v);
  // Valid while this grid lives; `cells` points into host memory.
  HintGridView view() const;
  const std::vector<uint32_t>& cells() const { return cells_; }

 private:
  HintGridView view_;
  std::vector<uint32_t> cells_;
};

}  // namespace kinetri::core

#endif  // KINETRI_CORE_HINT_GRID_H_
