#include "core/hint_grid.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace kinetri::core {
namespace {

// Cells holding more sites than this get a sub-grid of about four sites
// per cell (at most kMaxSubSide cells a side).
constexpr uint32_t kRefineAbove = 16;
constexpr uint32_t kMaxSubSide = 1024;

// Fills the empty entries of a side x side row-major block: from the
// nearest non-empty entry of the row, and rows without any from the
// nearest row with one (a walk from there is short, where one from the
// first site would cross the whole mesh). Entries stay empty only when the
// whole block is.
void FillEmpty(uint32_t* cells, size_t side) {
  std::vector<uint8_t> row_has(side, 0);
  for (size_t y = 0; y < side; ++y) {
    uint32_t* row = cells + y * side;
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
      std::copy_n(cells + from * side, side, cells + y * side);
      row_has[y] = 1;
    }
  }
}

}  // namespace

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
  const size_t side = view_.side, num_cells = side * side;
  view_.scale = {hi.x > lo.x ? side / (hi.x - lo.x) : 0.0,
                 hi.y > lo.y ? side / (hi.y - lo.y) : 0.0};
  cells_.assign(num_cells, kNoVertex);
  // The first site (in internal, i.e. Hilbert, order) found in each cell,
  // how many each cell holds, and where each site lies in its cell.
  std::vector<uint32_t> cell_of(v.num_sites), within(v.num_sites),
      count(num_cells, 0);
  for (uint32_t i = 0; i < v.num_sites; ++i) {
    const uint32_t s = v.sites[i];
    uint32_t ix, iy, fx, fy;
    view_.Locate(v.pos[s], &ix, &iy, &fx, &fy);
    const size_t c = size_t{iy} * side + ix;
    cell_of[i] = static_cast<uint32_t>(c);
    within[i] = fy << 16 | fx;
    if (cells_[c] == kNoVertex) cells_[c] = s;
    ++count[c];
  }
  FillEmpty(cells_.data(), side);
  // Sub-grids of the crowded cells, after the cells (their offsets reuse
  // `count`: 0 for a cell that is not refined).
  for (size_t c = 0; c < num_cells; ++c) {
    const uint32_t k = count[c];
    count[c] = 0;
    if (k <= kRefineAbove) continue;
    const size_t off = cells_.size();
    const uint32_t n = std::min<uint32_t>(
        kMaxSubSide, static_cast<uint32_t>(std::ceil(std::sqrt(k / 4.0))));
    if (off + 1 + size_t{n} * n >= HintGridView::kRefined) break;
    cells_.push_back(n);
    cells_.resize(off + 1 + size_t{n} * n, kNoVertex);
    count[c] = static_cast<uint32_t>(off);
  }
  view_.cells = cells_.data();
  // The first site of each sub-cell: backwards, the last write wins (no
  // load, no branch on the entry).
  for (uint32_t i = v.num_sites; i-- > 0;) {
    const uint32_t off = count[cell_of[i]];
    if (off == 0) continue;
    cells_[view_.SubCell(HintGridView::kRefined | off, within[i] & 0xFFFFu,
                         within[i] >> 16)] = v.sites[i];
  }
  for (size_t c = 0; c < num_cells; ++c) {
    const uint32_t off = count[c];
    if (off == 0) continue;
    const uint32_t n = cells_[off];
    uint32_t* sub = cells_.data() + off + 1;
    FillEmpty(sub, n);  // every sub-grid holds a site: none stays empty
    cells_[c] = HintGridView::kRefined | off;
  }
}

HintGridView HintGrid::view() const {
  HintGridView v = view_;
  v.cells = cells_.data();
  return v;
}

}  // namespace kinetri::core
