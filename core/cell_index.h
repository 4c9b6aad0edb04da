// A uniform grid of square cells over the sites of a triangulation view,
// built for one batch of radius queries (cell side = the radius): the sites
// in cell order with their positions copied next to each other, so the
// candidates of a disk are a few contiguous runs of memory instead of a
// walk over neighbour rows. Used by the radius queries of core/queries.h
// when disks hold more than a few sites (RowOptions::Plan).
//
// Where every cell of the bounding box fits the budget, the cells are
// dense (a cell's slots found by its number). Where they do not (clustered
// points: most of the box is empty at the scale of a cluster's radius),
// only the occupied cells are kept, row by row and sorted by column, and a
// row's run is found by binary search among its occupied cells.
#ifndef KINETRI_CORE_CELL_INDEX_H_
#define KINETRI_CORE_CELL_INDEX_H_

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <optional>
#include <vector>

#include "core/triangulation_view.h"
#include "core/vec2.h"

namespace kinetri::core {

class CellIndex {
 public:
  // When each form may be built.
  struct Limits {
    // Dense when the box needs at most this many cells.
    size_t max_dense_cells = 0;
    // Otherwise sparse when the box needs more than this many cells (so a
    // box that fits neither form is refused before any sorting) and has at
    // most max_rows rows (0: never sparse).
    size_t min_sparse_cells = 0;
    size_t max_rows = 0;
    // The sparse form also keeps a bitmap of each row's occupied columns
    // with counts per 64 columns (where that takes at most 4 words per site
    // and a few more), so that a row's run is two population counts
    // instead of two binary searches. false: binary searches only (tests).
    bool rank_rows = true;
  };
  // The index of v's sites with cells of side `cell` (> 0), or nullopt when
  // `limits` allow neither form (decided before sorting). Sorts in
  // parallel: call inside the triangulation's thread arena.
  static std::optional<CellIndex> Build(const TriangulationView& v, double cell,
                                        const Limits& limits);
  // The cell side at which cells over the bounding box of v's sites would
  // hold `sites_per_cell` sites on average, or 0 when there is none (no
  // sites, or a box of no area: the sites on a line).
  static double SideForOccupancy(const TriangulationView& v,
                                 double sites_per_cell);
  // About the occupancy() of an index of v's sites with cells of side
  // `cell`, from every `every`-th site (in internal order) alone: a pass
  // over a fraction of the sites instead of a build. Infinity when more
  // than max_cells cells would be needed.
  static double EstimateOccupancy(const TriangulationView& v, double cell,
                                  uint32_t every, size_t max_cells);
  // The cell side.
  double side() const { return side_; }
  // Whether the sparse form finds runs by rank (Limits::rank_rows).
  bool ranked() const { return !rank_.empty(); }

  // Sites per occupied cell, as a site sees it (the mean over sites of the
  // count of their own cell).
  double occupancy() const { return occupancy_; }
  bool sparse() const { return sparse_; }

  // Calls fn(begin, end) for runs of slots [begin, end) that together hold
  // every site within r of q (a superset, whatever the rounding): per row
  // of cells meeting the square [q - r, q + r]^2, its cells in that square,
  // which are one contiguous run. (Clipping each row to the disk's chord
  // skipped about 9 % of the candidates at cell side r and cost more in
  // square roots.) fn returns false to stop. The sites of a slot are
  // site(s), position(s) and ext(s).
  template <typename Fn>
  void ForEachRun(const Vec2& q, double r, Fn&& fn) const {
    // Bounds moved outwards by more than their rounding error, so that no
    // site of the disk falls outside them.
    const double slack_x = (std::fabs(q.x) + r) * 0x1p-50;
    const double slack_y = (std::fabs(q.y) + r) * 0x1p-50;
    const uint32_t x0 = Cell(q.x - r - slack_x, x0_, nx_);
    const uint32_t x1 = Cell(q.x + r + slack_x, x0_, nx_);
    const uint32_t y0 = Cell(q.y - r - slack_y, y0_, ny_);
    const uint32_t y1 = Cell(q.y + r + slack_y, y0_, ny_);
    for (uint32_t y = y0; y <= y1; ++y) {
      // The cells x0..x1 of a row are one contiguous run of slots.
      uint32_t b, e;
      if (!sparse_) {
        b = start_[size_t{y} * nx_ + x0];
        e = start_[size_t{y} * nx_ + x1 + 1];
      } else if (!rank_.empty()) {
        // Most rows a wide square crosses in a sparse index are empty
        // there (a point between clusters, in cells sized for them): a
        // look at the bitmap skips them without counting ranks.
        if (RowEmpty(y, x0, x1)) continue;
        b = start_[Rank(y, x0)];
        e = start_[Rank(y, x1 + 1)];
      } else {
        const uint32_t* first = cell_x_.data() + row_[y];
        const uint32_t* last = cell_x_.data() + row_[y + 1];
        if (first == last) continue;
        const uint32_t* k0 = std::lower_bound(first, last, x0);
        const uint32_t* k1 = std::upper_bound(k0, last, x1);
        b = start_[k0 - cell_x_.data()];
        e = start_[k1 - cell_x_.data()];
      }
      if (b != e && !fn(b, e)) return;
    }
  }

  // Calls fn(site, position, ext) for every site of ForEachRun(q, r); ext
  // is the external id of the site's only point, or kNoVertex when the
  // site holds several. fn returns false to stop.
  template <typename Fn>
  void ForEachCandidate(const Vec2& q, double r, Fn&& fn) const {
    ForEachRun(q, r, [&](uint32_t b, uint32_t e) {
      for (uint32_t s = b; s < e; ++s) {
        if (!fn(site_[s], pos_[s], ext_[s])) return false;
      }
      return true;
    });
  }

  uint32_t site(uint32_t slot) const { return site_[slot]; }
  const Vec2* positions() const { return pos_.data(); }
  const uint32_t* exts() const { return ext_.data(); }

  // Cells of the box (dense) or occupied cells (sparse).
  size_t num_cells() const { return start_.size() - 1; }

 private:
  // The first occupied cell of row y at a column >= x (x <= nx_), as an
  // index into cell_x_ and start_ (sparse form, ranked).
  uint32_t Rank(uint32_t y, uint32_t x) const {
    const size_t w = size_t{y} * words_per_row_ + x / 64;
    return rank_[w] + Popcount(bits_[w] & ((uint64_t{1} << (x % 64)) - 1));
  }
  // Whether row y has no occupied cell in columns x0..x1 (x0 <= x1 < nx_;
  // ranked sparse form).
  bool RowEmpty(uint32_t y, uint32_t x0, uint32_t x1) const {
    const uint64_t* row = bits_.data() + size_t{y} * words_per_row_;
    const uint32_t w0 = x0 / 64, w1 = x1 / 64;
    const uint64_t from_x0 = ~uint64_t{0} << (x0 % 64);
    const uint64_t to_x1 = ~uint64_t{0} >> (63 - x1 % 64);
    if (w0 == w1) return (row[w0] & from_x0 & to_x1) == 0;
    if ((row[w0] & from_x0) != 0) return false;
    for (uint32_t w = w0 + 1; w < w1; ++w) {
      if (row[w] != 0) return false;
    }
    return (row[w1] & to_x1) == 0;
  }
  // Set bits of x, inline (std::popcount calls a library routine where the
  // target has no popcnt instruction, as the baseline x86-64 has not; a
  // build for a target with one, -mpopcnt or -march=native, uses it).
  static uint32_t Popcount(uint64_t x) {
#ifdef __POPCNT__
    return static_cast<uint32_t>(__builtin_popcountll(x));
#else
    x = x - ((x >> 1) & 0x5555555555555555u);
    x = (x & 0x3333333333333333u) + ((x >> 2) & 0x3333333333333333u);
    x = (x + (x >> 4)) & 0x0f0f0f0f0f0f0f0fu;
    return static_cast<uint32_t>((x * 0x0101010101010101u) >> 56);
#endif
  }
  uint32_t Cell(double c, double origin, uint32_t count) const {
    return CellOf(c, origin, inv_, count);
  }
  // The cell (of `count` along an axis from `origin`, 1 / side = inv) of
  // coordinate c, clamped to the grid.
  static uint32_t CellOf(double c, double origin, double inv, uint32_t count) {
    const double t = (c - origin) * inv;
    if (!(t > 0.0)) return 0;
    if (t >= static_cast<double>(count - 1)) return count - 1;
    return static_cast<uint32_t>(t);
  }

  double x0_ = 0.0, y0_ = 0.0, inv_ = 1.0, side_ = 1.0;
  uint32_t nx_ = 1, ny_ = 1;
  bool sparse_ = false;
  double occupancy_ = 0.0;
  // Cell c: slots start_[c] .. start_[c + 1]. Dense: c = y * nx_ + x.
  // Sparse: the occupied cells of row y are row_[y] .. row_[y + 1], in
  // increasing column cell_x_[c].
  std::vector<uint32_t> start_;
  std::vector<uint32_t> row_, cell_x_;
  // Ranked sparse form: bit x % 64 of word y * words_per_row_ + x / 64 is
  // set when cell (x, y) is occupied; rank_ of a word counts the occupied
  // cells before it (in cell_x_ order).
  uint32_t words_per_row_ = 0;
  std::vector<uint64_t> bits_;
  std::vector<uint32_t> rank_;
  std::vector<uint32_t> site_;  // site (internal id) of each slot
  std::vector<Vec2> pos_;       // its position
  std::vector<uint32_t> ext_;   // its only point's external id (or none)
};

}  // namespace kinetri::core

#endif  // KINETRI_CORE_CELL_INDEX_H_
