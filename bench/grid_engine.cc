// Peer engine for the benchmarks: a uniform grid (cell list) rebuilt every
// step with a parallel counting sort; NN, k-NN and radius by ring search.
#include "bench/grid_engine.h"

#include <algorithm>
#include <atomic>
#include <cmath>

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
  core::ParallelFor(0, n, [&](size_t i) {
    order_[fill[cell_of[i]].fetch_add(1, std::memory_order_relaxed)] =
        static_cast<uint32_t>(i);
  });
}

template <typename Visit>
void GridEngine::Ring(int cx, int cy, int ring, Visit&& visit) const {
  for (int y = cy - ring; y <= cy + ring; ++y) {
    if (y < 0 || y >= ny_) continue;
    const bool edge_row = (y == cy - ring || y == cy + ring);
    for (int x = cx - ring; x <= cx + ring; x += edge_row ? 1 : 2 * ring) {
      if (x >= 0 && x < nx_) {
        const size_t c = size_t(y) * nx_ + x;
        for (uint32_t k = start_[c]; k < start_[c + 1]; ++k) visit(order_[k]);
      }
      if (ring == 0) break;
    }
  }
}

void GridEngine::KNearestOne(const core::Vec2& q, uint32_t skip, int k,
                             uint32_t* out) const {
  const auto& pts = *pts_;
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
    Ring(cx, cy, ring, [&](uint32_t j) {
      if (j == skip) return;
      const double dx = pts[j].x - q.x, dy = pts[j].y - q.y;
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
  const auto& pts = *pts_;
  const int reach = static_cast<int>(std::ceil(r / cell_));
  const int cx = CellX(q.x), cy = CellY(q.y);
  for (int ring = 0; ring <= reach; ++ring) {
    Ring(cx, cy, ring, [&](uint32_t j) {
      if (j == skip) return;
      const double dx = pts[j].x - q.x, dy = pts[j].y - q.y;
      if (dx * dx + dy * dy <= r * r) row.push_back(j);
    });
  }
}

std::vector<uint32_t> GridEngine::AllKNearest(int k) const {
  const size_t n = pts_->size();
  std::vector<uint32_t> out(n * k, UINT32_MAX);
  core::ParallelFor(
      0, n,
      [&](size_t i) {
        KNearestOne((*pts_)[i], static_cast<uint32_t>(i), k, &out[i * k]);
      },
      256);
  return out;
}

std::vector<uint32_t> GridEngine::AllNearest() const { return AllKNearest(1); }

std::vector<uint32_t> GridEngine::NearestOf(
    const std::vector<core::Vec2>& qs) const {
  std::vector<uint32_t> out(qs.size(), UINT32_MAX);
  core::ParallelFor(
      0, qs.size(), [&](size_t i) { KNearestOne(qs[i], UINT32_MAX, 1, &out[i]); },
      256);
  return out;
}

// Rows built per block of queries into block buffers, then one CSR.
template <typename RowFn>
void GridEngine::Rows(size_t nq, RowFn&& row_fn,
                      std::vector<uint64_t>* offsets,
                      std::vector<uint32_t>* ids) const {
  constexpr size_t kBlock = 256;
  const size_t blocks = (nq + kBlock - 1) / kBlock;
  std::vector<std::vector<uint32_t>> hits(blocks);
  offsets->assign(nq + 1, 0);
  core::ParallelFor(
      0, blocks,
      [&](size_t b) {
        for (size_t i = b * kBlock; i < std::min(nq, (b + 1) * kBlock); ++i) {
          const size_t before = hits[b].size();
          row_fn(i, hits[b]);
          (*offsets)[i + 1] = hits[b].size() - before;
        }
      },
      1);
  for (size_t i = 0; i < nq; ++i) (*offsets)[i + 1] += (*offsets)[i];
  ids->resize((*offsets)[nq]);
  core::ParallelFor(
      0, blocks,
      [&](size_t b) {
        std::copy(hits[b].begin(), hits[b].end(),
                  ids->begin() + (*offsets)[b * kBlock]);
      },
      1);
}

void GridEngine::AllWithinRadius(double r, std::vector<uint64_t>* offsets,
                                 std::vector<uint32_t>* ids) const {
  Rows(
      pts_->size(),
      [&](size_t i, std::vector<uint32_t>& row) {
        RadiusOne((*pts_)[i], static_cast<uint32_t>(i), r, row);
      },
      offsets, ids);
}

void GridEngine::WithinRadiusOf(const std::vector<core::Vec2>& qs, double r,
                                std::vector<uint64_t>* offsets,
                                std::vector<uint32_t>* ids) const {
  Rows(
      qs.size(),
      [&](size_t i, std::vector<uint32_t>& row) {
        RadiusOne(qs[i], UINT32_MAX, r, row);
      },
      offsets, ids);
}

}  // namespace kinetri::bench
