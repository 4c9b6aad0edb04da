#include "core/hint_grid.h"

#include <algorithm>
#include <cmath>

namespace kinetri::core {

HintGrid::HintGrid(const TriangulationView& v) {
  if (v.num_sites == 0) return;
  view_.fallback = v.sites[0];
  Vec2 lo = v.pos[v.sites[0]], hi = lo;
  for (uint32_t i = 0; i < v.num_sites; ++i) {
    const Vec2& p = v.pos[v.sites[i]];
    lo = {std::min(lo.x, p.x), std::min(lo.y, p.y)};
    hi = {std::max(hi.x, p.x), std::max(hi.y, p.y)};
  }
  view_.lo = lo;
  view_.hi = hi;
  view_.side = std::max<uint32_t>(
      1, static_cast<uint32_t>(std::sqrt(v.num_sites / 4.0)));
  cells_.assign(size_t{view_.side} * view_.side, kNoVertex);
  view_.cells = cells_.data();
  // The first site (in internal, i.e. Hilbert, order) found in each cell.
  for (uint32_t i = 0; i < v.num_sites; ++i) {
    const uint32_t s = v.sites[i];
    uint32_t& c = cells_[view_.Cell(v.pos[s])];
    if (c == kNoVertex) c = s;
  }
}

HintGridView HintGrid::view() const {
  HintGridView v = view_;
  v.cells = cells_.data();
  return v;
}

}  // namespace kinetri::core
