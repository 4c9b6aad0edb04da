// Peer engine for the device executor: a uniform grid (cell list) rebuilt
// every step and queried for the all-points nearest neighbour, written once
// in CCCL (bench/device_grid.inl: Thrust sort_by_key, lower_bound, for_each)
// and built for the same two backends as the device executor (the emulated
// one on CPU threads, CUDA on a GPU), so `kinetri-device` is compared with
// a grid on the same machine model.
#ifndef KINETRI_BENCH_DEVICE_GRID_H_
#define KINETRI_BENCH_DEVICE_GRID_H_

#include <cstdint>
#include <memory>
#include <vector>

#include "core/device/device_executor.h"
#include "core/vec2.h"

namespace kinetri::bench {

class DeviceGrid {
 public:
  virtual ~DeviceGrid() = default;
  // Uploads the points and sorts them into square cells of side `cell`.
  virtual void Build(const std::vector<core::Vec2>& pts, double cell) = 0;
  // Nearest other point of each point (ring search; UINT32_MAX when the
  // point is alone), downloaded.
  virtual std::vector<uint32_t> AllNearest() = 0;
};

// The grid on `backend`; null when this build lacks it (or, for CUDA, has
// no GPU).
std::unique_ptr<DeviceGrid> MakeDeviceGrid(core::device::DeviceBackend backend);

}  // namespace kinetri::bench

#endif  // KINETRI_BENCH_DEVICE_GRID_H_
