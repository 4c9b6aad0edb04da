// The device-resident state of a DeviceTriangulation (CUDA sources only).
#ifndef KINETRI_CORE_DEVICE_DEVICE_TRIANGULATION_IMPL_H_
#define KINETRI_CORE_DEVICE_DEVICE_TRIANGULATION_IMPL_H_

#include <cstdint>

#include "core/device/device_buffer.h"
#include "core/device/device_triangulation.h"
#include "core/hint_grid.h"
#include "core/triangulation_view.h"

namespace kinetri::core::cuda {

struct DeviceTriangulation::Impl {
  Buffer<Vec2> pos;
  Buffer<uint32_t> ext_of_int, int_of_ext, rep, dup_next, sites, origin, twin,
      vertex_edge, line, line_rank;
  Buffer<uint32_t> adj_offsets, adj;  // neighbour rows (queries)
  Buffer<uint32_t> hint_cells;        // start sites of position queries
  TriangulationView view;             // with device pointers
  HintGridView hints;                 // with device pointers
  uint64_t bytes = 0;
};

}  // namespace kinetri::core::cuda

#endif  // KINETRI_CORE_DEVICE_DEVICE_TRIANGULATION_IMPL_H_
