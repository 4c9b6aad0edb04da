// Peer engine for the benchmarks: a uniform grid (cell list) rebuilt every
// step with a parallel counting sort; NN, k-NN and radius by ring search.
// Tuned as such grids are in practice: the sort also copies the positions
// into cell order (each cell's points are contiguous), and queries run in
// cell order, so neighbouring queries scan the same cells from cache.
#ifndef KINETRI_BENCH_GRID_ENGINE_H_
#define KINETRI_BENCH_GRID_ENGINE_H_

#include <cstddef>
#include <cstdint>
#include <vector>

#include "core/vec2.h"

namespace kinetri::bench {

class GridEngine {
 public:
  // cell: side of a cell (about the mean spacing, or the query radius).
  void Build(const std::vector<core::Vec2>& pts, double cell);
  // Nearest other point of each point.
  std::vector<uint32_t> AllNearest() const;
  // k nearest other points of each point, closest first (CSR, k per row).
  std::vector<uint32_t> AllKNearest(int k) const;
  // Number of other points within r of each point (and their ids, CSR).
  void AllWithinRadius(double r, std::vector<uint64_t>* offsets,
                       std::vector<uint32_t>* ids) const;
  // Nearest point of each query position.
  std::vector<uint32_t> NearestOf(const std::vector<core::Vec2>& qs) const;
  // k nearest points of each query position, closest first (k per row).
  std::vector<uint32_t> KNearestOf(const std::vector<core::Vec2>& qs,
                                   int k) const;
  // Points within r of each query position (CSR).
  void WithinRadiusOf(const std::vector<core::Vec2>& qs, double r,
                      std::vector<uint64_t>* offsets,
                      std::vector<uint32_t>* ids) const;

 private:
  // k nearest points of q other than `skip`, closest first, into out[0..k).
  void KNearestOne(const core::Vec2& q, uint32_t skip, int k,
                   uint32_t* out) const;
  // Points within r of q other than `skip`, appended to row.
  void RadiusOne(const core::Vec2& q, uint32_t skip, double r,
                 std::vector<uint32_t>& row) const;
  // Rows of queries 0..nq, computed in the order `order` (a permutation)
  // and returned as CSR in query order.
  template <typename RowFn>
  void Rows(const std::vector<uint32_t>& order, RowFn&& row_fn,
            std::vector<uint64_t>* offsets, std::vector<uint32_t>* ids) const;
  // Indices of qs sorted by grid cell.
  std::vector<uint32_t> CellOrder(const std::vector<core::Vec2>& qs) const;
  template <typename Visit>
  void Ring(int cx, int cy, int ring, Visit&& visit) const;
  int CellX(double x) const;
  int CellY(double y) const;

  const std::vector<core::Vec2>* pts_ = nullptr;
  double cell_ = 1.0, x0_ = 0.0, y0_ = 0.0;
  int nx_ = 1, ny_ = 1;
  std::vector<uint32_t> start_;     // CSR over cells
  std::vector<uint32_t> order_;     // point ids sorted by cell
  std::vector<core::Vec2> sorted_;  // their positions, in the same order
};

}  // namespace kinetri::bench

#endif  // KINETRI_BENCH_GRID_ENGINE_H_
