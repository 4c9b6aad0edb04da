#include "core/hint_grid.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <memory>
#include <vector>

#include "core/parallel.h"

namespace kinetri::core {
namespace {

// Cells estimated to hold more sites than this get a sub-grid of about
// four sites per cell (at most kMaxSubSide cells a side).
constexpr uint32_t kRefineAbove = 32;
// Sites are counted per cell from a sample: those whose index in the site
// list is a multiple of this (sites follow a Hilbert curve, so a cell's
// sites come in runs: a cell needs about 40 sites to be refined). Enough to
// tell a crowded cell (a cluster's hundreds or thousands) from an ordinary
// one (about four), and the sub-grids are then known before the pass that
// finds every cell's first site, which fills them in the same pass.
constexpr uint32_t kCountEvery = 16;
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

// Fills the empty cells of the main grid with about the site nearest to
// each cell's centre, by propagation along rows (both ways, rows in
// parallel), then along columns (both ways, blocks of columns in
// parallel): an empty cell takes its neighbour's site when that site lies
// closer to its own centre. Clustered points leave most cells empty; a
// query there then starts next to its nearest site instead of deep inside
// whatever cluster its row meets first (the walk out of a cluster crosses
// it site by site).
void FillNearest(uint32_t* cells, const HintGridView& g, const Vec2* pos) {
  const size_t side = g.side;
  std::vector<uint8_t> empty(side * side);
  std::atomic<bool> any{false};
  ParallelFor(0, side, [&](size_t y) {
    bool row_any = false;
    for (size_t c = y * side; c < (y + 1) * side; ++c) {
      empty[c] = cells[c] == kNoVertex;
      row_any |= empty[c] != 0;
    }
    if (row_any) any.store(true, std::memory_order_relaxed);
  });
  if (!any.load()) return;
  // Cell sides (0 along an axis of no extent); multiplied, not divided.
  const Vec2 width{g.scale.x > 0 ? 1.0 / g.scale.x : 0.0,
                   g.scale.y > 0 ? 1.0 / g.scale.y : 0.0};
  // Cell c (at x, y) takes site s when s lies closer to its centre.
  auto offer = [&](size_t c, size_t x, size_t y, uint32_t s) {
    if (s == kNoVertex || s == cells[c]) return;
    const double cx = g.lo.x + (x + 0.5) * width.x;
    const double cy = g.lo.y + (y + 0.5) * width.y;
    auto d2 = [&](uint32_t t) {
      const double ex = pos[t].x - cx, ey = pos[t].y - cy;
      return ex * ex + ey * ey;
    };
    if (cells[c] == kNoVertex || d2(s) < d2(cells[c])) cells[c] = s;
  };
  ParallelFor(
      0, side,
      [&](size_t y) {
        const size_t row = y * side;
        for (size_t x = 1; x < side; ++x) {
          if (empty[row + x]) offer(row + x, x, y, cells[row + x - 1]);
        }
        for (size_t x = side - 1; x-- > 0;) {
          if (empty[row + x]) offer(row + x, x, y, cells[row + x + 1]);
        }
      },
      8);
  constexpr size_t kColumns = 16;  // a cache line of each row at a time
  ParallelFor(
      0, (side + kColumns - 1) / kColumns,
      [&](size_t b) {
        const size_t x0 = b * kColumns, x1 = std::min(side, x0 + kColumns);
        for (size_t y = 1; y < side; ++y) {
          for (size_t x = x0; x < x1; ++x) {
            const size_t c = y * side + x;
            if (empty[c]) offer(c, x, y, cells[c - side]);
          }
        }
        for (size_t y = side - 1; y-- > 0;) {
          for (size_t x = x0; x < x1; ++x) {
            const size_t c = y * side + x;
            if (empty[c]) offer(c, x, y, cells[c + side]);
          }
        }
      },
      1);
}

}  // namespace

HintGrid::HintGrid(const TriangulationView& v) {
  if (v.num_sites == 0) return;
  view_.fallback = v.sites[0];
  // The bounding box, by blocks on all threads.
  constexpr size_t kBlock = 16384;
  const size_t num_blocks = (size_t{v.num_sites} + kBlock - 1) / kBlock;
  std::vector<Vec2> block_lo(num_blocks), block_hi(num_blocks);
  ParallelFor(
      0, num_blocks,
      [&](size_t b) {
        const size_t end = std::min<size_t>(v.num_sites, (b + 1) * kBlock);
        Vec2 lo = v.pos[v.sites[b * kBlock]], hi = lo;
        for (size_t i = b * kBlock; i < end; ++i) {
          const Vec2& p = v.pos[v.sites[i]];
          lo = {std::min(lo.x, p.x), std::min(lo.y, p.y)};
          hi = {std::max(hi.x, p.x), std::max(hi.y, p.y)};
        }
        block_lo[b] = lo;
        block_hi[b] = hi;
      },
      1);
  Vec2 lo = block_lo[0], hi = block_hi[0];
  for (size_t b = 1; b < num_blocks; ++b) {
    lo = {std::min(lo.x, block_lo[b].x), std::min(lo.y, block_lo[b].y)};
    hi = {std::max(hi.x, block_hi[b].x), std::max(hi.y, block_hi[b].y)};
  }
  view_.lo = lo;
  view_.hi = hi;
  view_.side = std::max<uint32_t>(
      1, static_cast<uint32_t>(std::sqrt(v.num_sites / 4.0)));
  const size_t side = view_.side, num_cells = side * side;
  view_.scale = {hi.x > lo.x ? side / (hi.x - lo.x) : 0.0,
                 hi.y > lo.y ? side / (hi.y - lo.y) : 0.0};
  // How many sites each cell holds, estimated from every kCountEvery-th
  // site (a pass over a sixteenth of them).
  std::vector<uint32_t> count(num_cells, 0);
  const size_t num_sampled = (v.num_sites + kCountEvery - 1) / kCountEvery;
  ParallelFor(0, num_sampled, [&](size_t j) {
    uint32_t ix, iy, fx, fy;
    view_.Locate(v.pos[v.sites[j * kCountEvery]], &ix, &iy, &fx, &fy);
    std::atomic_ref<uint32_t>(count[size_t{iy} * side + ix])
        .fetch_add(1, std::memory_order_relaxed);
  });
  // Sub-grids of the crowded cells, after the cells (their offsets reuse
  // `count`: 0 for a cell that is not refined).
  cells_.assign(num_cells, kNoVertex);
  std::vector<uint32_t> refined;
  for (size_t c = 0; c < num_cells; ++c) {
    const uint32_t k = count[c] * kCountEvery;
    count[c] = 0;
    if (k <= kRefineAbove) continue;
    const size_t off = cells_.size();
    const uint32_t n = std::min<uint32_t>(
        kMaxSubSide, static_cast<uint32_t>(std::ceil(std::sqrt(k / 4.0))));
    if (off + 1 + size_t{n} * n >= HintGridView::kRefined) break;
    cells_.push_back(n);
    cells_.resize(off + 1 + size_t{n} * n, kNoVertex);
    count[c] = static_cast<uint32_t>(off);
    refined.push_back(static_cast<uint32_t>(c));
  }
  view_.cells = cells_.data();
  // The first site (in internal, i.e. Hilbert, order: the smallest id) of
  // each cell and sub-cell, in one pass, in parallel, the same for any
  // thread count. Sites come in ascending order, so an atomic minimum is a
  // load once its cell has a site.
  const HintGridView grid = view_;  // (a copy the loop keeps in registers)
  ParallelFor(
      0, num_blocks,
      [&](size_t b) {
        const size_t end = std::min<size_t>(v.num_sites, (b + 1) * kBlock);
        for (size_t i = b * kBlock; i < end; ++i) {
          const uint32_t s = v.sites[i];
          uint32_t ix, iy, fx, fy;
          grid.Locate(v.pos[s], &ix, &iy, &fx, &fy);
          const size_t c = size_t{iy} * side + ix;
          AtomicMin(&cells_[c], s);
          if (const uint32_t off = count[c]; off != 0) {
            AtomicMin(
                &cells_[grid.SubCell(HintGridView::kRefined | off, fx, fy)], s);
          }
        }
      },
      1);
  // (Refined cells still hold their first site here, as a neighbour for
  // the empty cells.)
  FillNearest(cells_.data(), grid, v.pos);
  ParallelFor(
      0, refined.size(),
      [&](size_t j) {
        const uint32_t c = refined[j], off = count[c];
        // Every sub-grid holds a site: no entry stays empty.
        FillEmpty(cells_.data() + off + 1, cells_[off]);
        cells_[c] = HintGridView::kRefined | off;
      },
      16);
}

std::shared_ptr<const HintGrid> HintGrid::Renumbered(
    absl::FunctionRef<uint32_t(uint32_t)> new_of_old) const {
  auto out = std::make_shared<HintGrid>(*this);
  std::vector<uint32_t>& cells = out->cells_;
  auto map = [&](uint32_t& s) {
    if (s != kNoVertex) s = new_of_old(s);
  };
  map(out->view_.fallback);
  const size_t main = size_t{view_.side} * view_.side;
  ParallelFor(0, main, [&](size_t c) {
    if (!HintGridView::IsRefined(cells[c])) {
      map(cells[c]);
      return;
    }
    const size_t off = cells[c] & ~HintGridView::kRefined;
    const size_t n = cells[off];
    for (size_t k = off + 1; k < off + 1 + n * n; ++k) map(cells[k]);
  });
  out->view_.cells = cells.data();
  return out;
}

HintGridView HintGrid::view() const {
  HintGridView v = view_;
  v.cells = cells_.data();
  return v;
}

}  // namespace kinetri::core
