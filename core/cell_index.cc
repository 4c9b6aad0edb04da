#include "core/cell_index.h"

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/parallel_reduce.h>

#include <algorithm>
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

// The bounding box of v's sites (in parallel).
Box SitesBox(const TriangulationView& v) {
  return tbb::parallel_reduce(
      tbb::blocked_range<uint32_t>(0, v.num_sites, 4096), Box{},
      [&](const tbb::blocked_range<uint32_t>& r, Box b) {
        for (uint32_t i = r.begin(); i != r.end(); ++i)
          b.Add(v.pos[v.sites[i]]);
        return b;
      },
      [](Box a, const Box& b) {
        a.Add(b);
        return a;
      });
}

}  // namespace

double CellIndex::SideForOccupancy(const TriangulationView& v,
                                   double sites_per_cell) {
  if (v.num_sites == 0 || !(sites_per_cell > 0.0)) return 0.0;
  const Box box = SitesBox(v);
  const double area = (box.hi_x - box.lo_x) * (box.hi_y - box.lo_y);
  const double side = std::sqrt(area * sites_per_cell / v.num_sites);
  return std::isfinite(side) && std::isfinite(1.0 / side) ? side : 0.0;
}

double CellIndex::EstimateOccupancy(const TriangulationView& v, double cell,
                                    uint32_t every, size_t max_cells) {
  if (v.num_sites == 0 || every == 0 || !(cell > 0.0) ||
      !std::isfinite(1.0 / cell)) {
    return INFINITY;
  }
  const Box box = SitesBox(v);
  const double inv = 1.0 / cell;
  const double cx = std::floor((box.hi_x - box.lo_x) * inv) + 1.0;
  const double cy = std::floor((box.hi_y - box.lo_y) * inv) + 1.0;
  if (!(cx * cy <= static_cast<double>(max_cells))) return INFINITY;
  const uint32_t nx = static_cast<uint32_t>(cx), ny = static_cast<uint32_t>(cy);
  // A site's sampled cell-mates m (itself included): over the samples, the
  // mean of m is about 1 + (occupancy - 1) / every.
  std::vector<uint32_t> count(size_t{nx} * ny, 0);
  uint64_t samples = 0, sum = 0;
  std::vector<uint32_t> cell_of;
  cell_of.reserve(v.num_sites / every + 1);
  for (uint32_t i = 0; i < v.num_sites; i += every) {
    const Vec2& p = v.pos[v.sites[i]];
    const uint32_t c =
        CellOf(p.y, box.lo_y, inv, ny) * nx + CellOf(p.x, box.lo_x, inv, nx);
    ++count[c];
    cell_of.push_back(c);
    ++samples;
  }
  for (const uint32_t c : cell_of) sum += count[c];
  const double mates = static_cast<double>(sum) / samples;
  return std::max(1.0, 1.0 + (mates - 1.0) * every);
}

std::optional<CellIndex> CellIndex::Build(const TriangulationView& v,
                                          double cell, const Limits& limits) {
  const uint32_t ns = v.num_sites;
  if (ns == 0 || !(cell > 0.0) || !std::isfinite(1.0 / cell)) {
    return std::nullopt;
  }
  const Box box = SitesBox(v);
  CellIndex g;
  g.side_ = cell;
  g.inv_ = 1.0 / cell;
  const double cx = std::floor((box.hi_x - box.lo_x) * g.inv_) + 1.0;
  const double cy = std::floor((box.hi_y - box.lo_y) * g.inv_) + 1.0;
  const double cells = cx * cy;
  g.sparse_ = !(cells <= static_cast<double>(limits.max_dense_cells));
  // Columns and rows are 32-bit in either form.
  if (g.sparse_ && !(cells > static_cast<double>(limits.min_sparse_cells) &&
                     cy <= static_cast<double>(limits.max_rows) &&
                     cx < 0x1p31 && cy < 0x1p31)) {
    return std::nullopt;
  }
  g.x0_ = box.lo_x;
  g.y0_ = box.lo_y;
  g.nx_ = static_cast<uint32_t>(cx);
  g.ny_ = static_cast<uint32_t>(cy);
  g.site_.resize(ns);
  g.pos_.resize(ns);
  g.ext_.resize(ns);
  auto place = [&](uint32_t slot, uint32_t i) {
    const uint32_t w = v.sites[i];
    g.site_[slot] = w;
    g.pos_[slot] = v.pos[w];
    g.ext_[slot] = v.dup_next[w] == kNoVertex ? v.ext_of_int[w] : kNoVertex;
  };
  if (!g.sparse_) {
    const size_t num_cells = size_t{g.nx_} * g.ny_;
    // Counting sort of the sites (in their internal, Hilbert order, which
    // each cell keeps) by cell.
    std::vector<uint32_t> key(ns);
    ParallelFor(0, ns, [&](size_t i) {
      const Vec2& p = v.pos[v.sites[i]];
      key[i] = static_cast<uint32_t>(size_t{g.Cell(p.y, g.y0_, g.ny_)} * g.nx_ +
                                     g.Cell(p.x, g.x0_, g.nx_));
    });
    g.start_.assign(num_cells + 1, 0);
    for (uint32_t k : key) ++g.start_[k + 1];
    for (size_t c = 0; c < num_cells; ++c) g.start_[c + 1] += g.start_[c];
    std::vector<uint32_t> next(g.start_.begin(), g.start_.end() - 1);
    for (uint32_t i = 0; i < ns; ++i) place(next[key[i]]++, i);
    // (Counting and scattering on all threads, with atomic counts and each
    // cell put back in internal order, took 15.8 ms against 12.1 at 1M
    // sites on 2 threads.)
    uint64_t sum = 0;
    for (size_t c = 0; c < num_cells; ++c) {
      const uint64_t k = g.start_[c + 1] - g.start_[c];
      sum += k * k;
    }
    g.occupancy_ = static_cast<double>(sum) / ns;
    return g;
  }
  // Sparse: counting sort by row (internal order kept), then each row
  // sorted by (column, internal order); the occupied cells are the runs of
  // equal columns.
  std::vector<uint32_t> row(ns), col(ns);
  ParallelFor(0, ns, [&](size_t i) {
    const Vec2& p = v.pos[v.sites[i]];
    row[i] = g.Cell(p.y, g.y0_, g.ny_);
    col[i] = g.Cell(p.x, g.x0_, g.nx_);
  });
  std::vector<uint32_t> row_start(size_t{g.ny_} + 1, 0);
  for (uint32_t y : row) ++row_start[y + 1];
  for (uint32_t y = 0; y < g.ny_; ++y) row_start[y + 1] += row_start[y];
  std::vector<uint32_t> by_row(ns);
  // Where the columns are few enough to count (as many as 4 per site), two
  // stable counting sorts, by column and then by row, order the sites by
  // (row, column, internal order); otherwise each row is sorted by
  // (column, internal order) below. (100K clustered points: 2.3-3.3 ms for
  // the index with the sorts of rows.)
  const bool count_columns = g.nx_ <= 4 * size_t{ns} + 64;
  {
    std::vector<uint32_t> by_col;
    if (count_columns) {
      std::vector<uint32_t> col_start(size_t{g.nx_} + 1, 0);
      for (uint32_t x : col) ++col_start[x + 1];
      for (uint32_t x = 0; x < g.nx_; ++x) col_start[x + 1] += col_start[x];
      by_col.resize(ns);
      for (uint32_t i = 0; i < ns; ++i) by_col[col_start[col[i]]++] = i;
    }
    std::vector<uint32_t> next(row_start.begin(), row_start.end() - 1);
    if (count_columns) {
      for (uint32_t i : by_col) by_row[next[row[i]]++] = i;
    } else {
      for (uint32_t i = 0; i < ns; ++i) by_row[next[row[i]]++] = i;
    }
  }
  // Rows sorted (unless counted) and placed in parallel (64 rows per task);
  // each row's occupied cells counted, then numbered in row order.
  std::vector<uint32_t> row_cells(size_t{g.ny_} + 1, 0);
  ParallelFor(
      0, g.ny_,
      [&](size_t y) {
        const uint32_t b = row_start[y], e = row_start[y + 1];
        if (b == e) return;
        if (!count_columns) {
          std::sort(by_row.begin() + b, by_row.begin() + e,
                    [&](uint32_t i, uint32_t j) {
                      return col[i] != col[j] ? col[i] < col[j] : i < j;
                    });
        }
        uint32_t cells = 1;
        for (uint32_t s = b + 1; s < e; ++s) {
          cells += col[by_row[s]] != col[by_row[s - 1]];
        }
        row_cells[y + 1] = cells;
      },
      64);
  for (uint32_t y = 0; y < g.ny_; ++y) row_cells[y + 1] += row_cells[y];
  const uint32_t occupied = row_cells[g.ny_];
  g.row_ = std::move(row_cells);
  g.cell_x_.resize(occupied);
  g.start_.resize(size_t{occupied} + 1);
  g.start_[occupied] = ns;
  std::vector<uint64_t> sums(g.ny_, 0);
  ParallelFor(
      0, g.ny_,
      [&](size_t y) {
        const uint32_t b = row_start[y], e = row_start[y + 1];
        uint32_t c = g.row_[y];
        uint32_t first = b;
        uint64_t sum = 0;
        for (uint32_t s = b; s < e; ++s) {
          const uint32_t i = by_row[s];
          place(s, i);
          if (s == b || col[i] != col[by_row[s - 1]]) {
            if (s != b) sum += uint64_t{s - first} * (s - first);
            g.cell_x_[c] = col[i];
            g.start_[c] = s;
            first = s;
            ++c;
          }
        }
        if (e != b) sum += uint64_t{e - first} * (e - first);
        sums[y] = sum;
      },
      64);
  uint64_t sum = 0;
  for (uint64_t x : sums) sum += x;
  g.occupancy_ = static_cast<double>(sum) / ns;
  // Rows by rank where the bitmap stays small (clustered points at 100K:
  // all-points 8-NN spent about a third of its time in the binary
  // searches).
  const uint32_t words_per_row = g.nx_ / 64 + 1;
  const double words = double(g.ny_) * words_per_row;
  if (limits.rank_rows && words <= 4.0 * ns + 1024.0) {
    g.words_per_row_ = words_per_row;
    g.bits_.assign(static_cast<size_t>(words), 0);
    g.rank_.resize(static_cast<size_t>(words));
    ParallelFor(
        0, g.ny_,
        [&](size_t y) {
          uint64_t* bits = g.bits_.data() + y * words_per_row;
          for (uint32_t k = g.row_[y]; k < g.row_[y + 1]; ++k) {
            bits[g.cell_x_[k] / 64] |= uint64_t{1} << (g.cell_x_[k] % 64);
          }
          uint32_t* rank = g.rank_.data() + y * words_per_row;
          uint32_t before = g.row_[y];
          for (uint32_t w = 0; w < words_per_row; ++w) {
            rank[w] = before;
            before += Popcount(bits[w]);
          }
        },
        64);
  }
  return g;
}

}  // namespace kinetri::core
