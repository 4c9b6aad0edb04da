// Grid of start sites for greedy walks of position queries: each cell
// holds one site that lies in it (or a site of the nearest non-empty cell),
// so a walk from a query's cell takes a few steps. Cells holding many sites
// (clusters: a uniform grid over their bounding box would put thousands of
// sites in a cell) are refined by a grid of their own with about four
// sites per cell, stored in the same array, so walks stay short whatever
// the density contrast. Built on the host; HintGridView is trivially
// copyable and answers on the host and on the device.
#ifndef KINETRI_CORE_HINT_GRID_H_
#define KINETRI_CORE_HINT_GRID_H_

#include <cstddef>
#include <cstdint>
#include <memory>
#include <vector>

#include "absl/functional/function_ref.h"
#include "core/hd.h"
#include "core/triangulation_view.h"
#include "core/vec2.h"

namespace kinetri::core {

struct HintGridView {
  // A cell entry with this bit set (and not kNoVertex) is refined: the rest
  // is the offset in `cells` of its sub-grid (its side, then side x side
  // entries, row-major).
  static constexpr uint32_t kRefined = 0x80000000u;

  Vec2 lo{0, 0}, hi{0, 0};
  Vec2 scale{0, 0};   // cells per unit length (0 when the extent is 0)
  uint32_t side = 0;  // side x side cells; 0: no cells
  const uint32_t* cells = nullptr;
  uint32_t fallback = kNoVertex;  // first site (kNoVertex: no sites)

  KINETRI_HD uint32_t Hint(const Vec2& q) const {
    if (side == 0) return fallback;
    uint32_t ix, iy, fx, fy;
    Locate(q, &ix, &iy, &fx, &fy);
    uint32_t c = cells[size_t{iy} * side + ix];
    if (IsRefined(c)) c = cells[SubCell(c, fx, fy)];
    return c != kNoVertex ? c : fallback;
  }

  // Where q lies in its cell: the cell index and the position within it
  // in units of 2^-16 (what SubCell takes), per axis.
  KINETRI_HD void Locate(const Vec2& q, uint32_t* ix, uint32_t* iy,
                         uint32_t* fx, uint32_t* fy) const {
    const double tx = (q.x - lo.x) * scale.x, ty = (q.y - lo.y) * scale.y;
    *ix = Index(tx, side);
    *iy = Index(ty, side);
    *fx = Fraction(tx - *ix);
    *fy = Fraction(ty - *iy);
  }

  // Position in `cells` of the entry for (fx, fy) (see Locate) in the
  // sub-grid of refined entry c.
  KINETRI_HD size_t SubCell(uint32_t c, uint32_t fx, uint32_t fy) const {
    const size_t off = c & ~kRefined;
    const uint32_t n = cells[off];  // at most 2^16 (fy * n fits)
    return off + 1 + size_t{(fy * n) >> 16} * n + ((fx * n) >> 16);
  }

  KINETRI_HD static bool IsRefined(uint32_t c) {
    return c != kNoVertex && (c & kRefined) != 0;
  }

 private:
  KINETRI_HD static uint32_t Index(double t, uint32_t n) {
    if (!(t > 0)) return 0;
    return t >= n ? n - 1 : static_cast<uint32_t>(t);
  }
  // f (in [0, 1) but for rounding and clamping) in units of 2^-16.
  KINETRI_HD static uint32_t Fraction(double f) {
    if (!(f > 0)) return 0;
    return f >= 1 ? 0xFFFFu : static_cast<uint32_t>(f * 65536.0);
  }
};

class HintGrid {
 public:
  // About four sites per cell, and per cell of each sub-grid. Runs on all
  // threads: call inside the triangulation's thread arena.
  explicit HintGrid(const TriangulationView& v);
  // Valid while this grid lives; `cells` points into host memory.
  HintGridView view() const;
  // The same grid with every site s replaced by new_of_old(s): for the same
  // sites renumbered (hints only start walks, so the grid of the previous
  // numbering, or of positions a little older, still serves). Runs on all
  // threads.
  std::shared_ptr<const HintGrid> Renumbered(
      absl::FunctionRef<uint32_t(uint32_t)> new_of_old) const;
  const std::vector<uint32_t>& cells() const { return cells_; }

 private:
  HintGridView view_;
  std::vector<uint32_t> cells_;
};

}  // namespace kinetri::core

#endif  // KINETRI_CORE_HINT_GRID_H_
