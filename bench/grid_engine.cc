// Peer engine for the benchmarks: a uniform grid (cell list) rebuilt every
// step with a parallel counting sort; NN, k-NN and radius by ring search.
#include "bench/grid_engine.h"

#include <tbb/parallel_sort.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <utility>

#include "core/parallel.h"

namespace kinetri::bench {

int GridEngine::CellX(double x) const {
  return std::clamp(static_cast<int>((x - x0_) / cell_), 0, nx_ - 1);
}
int GridEngine::CellY(double y) const {
  return std::clamp(static_cast<int>((y - y0_) / cell_), 0, ny_ - 1);
}

void GridEngine::Build(const std::vector<core::Vec2>& pts, double cell) {
  pts_ = &pts;
  const size_t n = pts.size();
  double x1 = pts[0].x, y1 = pts[0].y;
  x0_ = x1;
  y0_ = y1;
  for (const auto& p : pts) {
    x0_ = std::min(x0_, p.x);
    y0_ = std::min(y0_, p.y);
    x1 = std::max(x1, p.x);
    y1 = std::max(y1, p.y);
  }
  cell_ = cell;
  nx_ = std::max(1, static_cast<int>((x1 - x0_) / cell) + 1);
  ny_ = std::max(1, static_cast<int>((y1 - y0_) / cell) + 1);
  const size_t cells = size_t{static_cast<size_t>(nx_)} * ny_;
  std::vector<uint32_t> cell_of(n);
  std::vector<std::atomic<uint32_t>> count(cells + 1);
  core::ParallelFor(0, n, [&](size_t i) {
    const uint32_t c = CellY(pts[i].y) * nx_ + CellX(pts[i].x);
    cell_of[i] = c;
    count[c + 1].fetch_add(1, std::memory_order_relaxed);
  });
  start_.assign(cells + 1, 0);
  for (size_t c = 0; c < cells; ++c) start_[c + 1] = start_[c] + count[c + 1];
  std::vector<std::atomic<uint32_t>> fill(cells);
  core::ParallelFor(0, cells, [&](size_t c) { fill[c] = start_[c]; });
  order_.resize(n);
  sorted_.resize(n);
  core::ParallelFor(0, n, [&](size_t i) {
    const uint32_t slot =
        fill[cell_of[i]].fetch_add(1, std::memory_order_relaxed);
    order_[slot] = static_cast<uint32_t>(i);
    sorted_[slot] = pts[i];
  });
}

std::vector<uint32_t> GridEngine::CellOrder(
    const std::vector<core::Vec2>& qs) const {
  std::vector<std::pair<uint32_t, uint32_t>> key(qs.size());
  core::ParallelFor(0, qs.size(), [&](size_t i) {
    key[i] = {static_cast<uint32_t>(CellY(qs[i].y) * nx_ + CellX(qs[i].x)),
              static_cast<uint32_t>(i)};
  });
  tbb::parallel_sort(key.begin(), key.end());
  std::vector<uint32_t> order(qs.size());
  for (size_t i = 0; i < qs.size(); ++i) order[i] = key[i].second;
  return order;
}

template <typename Visit>
void GridEngine::Ring(int cx, int cy, int ring, Visit&& visit) const {
  for (int y = cy - ring; y <= cy + ring; ++y) {
    if (y < 0 || y >= ny_) continue;
    const bool edge_row = (y == cy - ring || y == cy + ring);
    for (int x = cx - ring; x <= cx + ring; x += edge_row ? 1 : 2 * ring) {
      if (x >= 0 && x < nx_) {
        const size_t c = size_t(y) * nx_ + x;
        for (uint32_t k = start_[c]; k < start_[c + 1]; ++k) visit(k);
      }
      if (ring == 0) break;
    }
  }
}

void GridEngine::KNearestOne(const core::Vec2& q, uint32_t skip, int k,
                             uint32_t* out) const {
  const int cx = CellX(q.x), cy = CellY(q.y);
  // Max-heap of (d2, id) holding the k best so far, in a small array.
  thread_local std::vector<std::pair<double, uint32_t>> best;
  best.clear();
  for (int ring = 0; ring <= std::max(nx_, ny_); ++ring) {
    // Everything in rings > ring is farther than (ring - 1) * cell from q.
    if (static_cast<int>(best.size()) == k) {
      const double reach = ring > 0 ? (ring - 1) * cell_ : 0.0;
      if (best.front().first <= reach * reach) break;
    }
    Ring(cx, cy, ring, [&](uint32_t slot) {
      const uint32_t j = order_[slot];
      if (j == skip) return;
      const double dx = sorted_[slot].x - q.x, dy = sorted_[slot].y - q.y;
      const std::pair<double, uint32_t> e(dx * dx + dy * dy, j);
      if (static_cast<int>(best.size()) < k) {
        best.push_back(e);
        std::push_heap(best.begin(), best.end());
      } else if (e < best.front()) {
        std::pop_heap(best.begin(), best.end());
        best.back() = e;
        std::push_heap(best.begin(), best.end());
      }
    });
  }
  std::sort_heap(best.begin(), best.end());
  for (int r = 0; r < k; ++r) {
    out[r] = r < static_cast<int>(best.size()) ? best[r].second : UINT32_MAX;
  }
}

void GridEngine::RadiusOne(const core::Vec2& q, uint32_t skip, double r,
                           std::vector<uint32_t>& row) const {
  const int reach = static_cast<int>(std::ceil(r / cell_));
  const int cx = CellX(q.x), cy = CellY(q.y);
  for (int ring = 0; ring <= reach; ++ring) {
    Ring(cx, cy, ring, [&](uint32_t slot) {
      const uint32_t j = order_[slot];
      if (j == skip) return;
      const double dx = sorted_[slot].x - q.x, dy = sorted_[slot].y - q.y;
      if (dx * dx + dy * dy <= r * r) row.push_back(j);
    });
  }
}

std::vector<uint32_t> GridEngine::AllKNearest(int k) const {
  const size_t n = pts_->size();
  std::vector<uint32_t> out(n * k, UINT32_MAX);
  core::ParallelFor(
      0, n,
      [&](size_t slot) {
        const uint32_t i = order_[slot];
        KNearestOne(sorted_[slot], i, k, &out[size_t{i} * k]);
      },
      256);
  return out;
}

std::vector<uint32_t> GridEngine::AllNearest() const { return AllKNearest(1); }

std::vector<uint32_t> GridEngine::NearestOf(
    const std::vector<core::Vec2>& qs) const {
  return KNearestOf(qs, 1);
}

std::vector<uint32_t> GridEngine::KNearestOf(const std::vector<core::Vec2>& qs,
                                             int k) const {
  std::vector<uint32_t> out(qs.size() * k, UINT32_MAX);
  const std::vector<uint32_t> order = CellOrder(qs);
  core::ParallelFor(
      0, qs.size(),
      [&](size_t s) {
        const uint32_t i = order[s];
        KNearestOne(qs[i], UINT32_MAX, k, &out[size_t{i} * k]);
      },
      256);
  return out;
}

// Rows built in `order` per block of queries into block buffers, then one
// CSR in query order.
template <typename RowFn>
void GridEngine::Rows(const std::vector<uint32_t>& order, RowFn&& row_fn,
                      std::vector<uint64_t>* offsets,
                      std::vector<uint32_t>* ids) const {
  constexpr size_t kBlock = 256;
  const size_t nq = order.size();
  const size_t blocks = (nq + kBlock - 1) / kBlock;
  std::vector<std::vector<uint32_t>> hits(blocks);
  std::vector<uint32_t> start_in_block(nq);
  offsets->assign(nq + 1, 0);
  core::ParallelFor(
      0, blocks,
      [&](size_t b) {
        for (size_t s = b * kBlock; s < std::min(nq, (b + 1) * kBlock); ++s) {
          const size_t before = hits[b].size();
          start_in_block[s] = static_cast<uint32_t>(before);
          row_fn(s, order[s], hits[b]);
          (*offsets)[order[s] + 1] = hits[b].size() - before;
        }
      },
      1);
  for (size_t i = 0; i < nq; ++i) (*offsets)[i + 1] += (*offsets)[i];
  ids->resize((*offsets)[nq]);
  core::ParallelFor(
      0, blocks,
      [&](size_t b) {
        for (size_t s = b * kBlock; s < std::min(nq, (b + 1) * kBlock); ++s) {
          const uint32_t q = order[s];
          const auto first = hits[b].begin() + start_in_block[s];
          std::copy(first, first + ((*offsets)[q + 1] - (*offsets)[q]),
                    ids->begin() + (*offsets)[q]);
        }
      },
      1);
}

void GridEngine::AllWithinRadius(double r, std::vector<uint64_t>* offsets,
                                 std::vector<uint32_t>* ids) const {
  // Points in cell order: slot s is point order_[s] at sorted_[s].
  Rows(
      order_,
      [&](size_t s, uint32_t i, std::vector<uint32_t>& row) {
        RadiusOne(sorted_[s], i, r, row);
      },
      offsets, ids);
}

void GridEngine::WithinRadiusOf(const std::vector<core::Vec2>& qs, double r,
                                std::vector<uint64_t>* offsets,
                                std::vector<uint32_t>* ids) const {
  Rows(
      CellOrder(qs),
      [&](size_t, uint32_t i, std::vector<uint32_t>& row) {
        RadiusOne(qs[i], UINT32_MAX, r, row);
      },
      offsets, ids);
}

}  // namespace kinetri::bench
