#include "core/hint_grid.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

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
  // An empty cell (about 2 % of them for uniform points, most of a sparse
  // region) starts from a site of the nearest non-empty cell of its row,
  // or of the nearest row with sites: a walk from there is short, where
  // one from the first site would cross the whole mesh.
  const size_t side = view_.side;
  std::vector<uint8_t> row_has(side, 0);
  for (size_t y = 0; y < side; ++y) {
    uint32_t* row = cells_.data() + y * side;
    uint32_t last = kNoVertex;
    for (size_t x = 0; x < side; ++x) {
      if (row[x] != kNoVertex) {
        last = row[x];
      } else {
        row[x] = last;  // from the left (may stay empty)
      }
    }
    last = kNoVertex;
    for (size_t x = side; x-- > 0;) {
      if (row[x] != kNoVertex) {
        last = row[x];
      } else {
        row[x] = last;  // from the right, for the cells left of the first
      }
    }
    row_has[y] = row[0] != kNoVertex;
  }
  for (int pass = 0; pass < 2; ++pass) {  // rows without sites: up, down
    for (size_t k = 1; k < side; ++k) {
      const size_t y = pass == 0 ? k : side - 1 - k;
      const size_t from = pass == 0 ? y - 1 : y + 1;
      if (row_has[y] || !row_has[from]) continue;
      std::copy_n(cells_.data() + from * side, side, cells_.data() + y * side);
      row_has[y] = 1;
    }
  }
}

HintGridView HintGrid::view() const {
  HintGridView v = view_;
  v.cells = cells_.data();
  return v;
}

}  // namespace kinetri::core
