// CUDA executor (first slice): a device-resident copy of a triangulation on
// which the shared host+device steps run as kernels: all-points nearest
// neighbour, and the fixing/legalizing scans (invalid triangles, illegal
// edges). Built only with CUDA (KINETRI_CUDA); no CUDA types leak out.
#ifndef KINETRI_CORE_CUDA_DEVICE_TRIANGULATION_H_
#define KINETRI_CORE_CUDA_DEVICE_TRIANGULATION_H_

#include <cstdint>
#include <memory>

#include "absl/status/statusor.h"
#include "core/queries.h"
#include "core/triangulation.h"

namespace kinetri::core::cuda {

// True when a CUDA device can be used (driver, runtime and a GPU present).
bool DeviceAvailable();

class DeviceTriangulation {
 public:
  // Uploads positions, numbering, coincident-point chains and the mesh.
  static absl::StatusOr<DeviceTriangulation> Upload(const Triangulation& t);

  DeviceTriangulation(DeviceTriangulation&&) noexcept;
  DeviceTriangulation& operator=(DeviceTriangulation&&) noexcept;
  ~DeviceTriangulation();

  // Same answers as core::AllNearestNeighbors (same per-point function).
  absl::StatusOr<NeighborLists> AllNearestNeighbors() const;
  // Triangles failing rules::TriangleOk, and canonical edges failing
  // rules::IsIllegal (both 0 for a Delaunay mesh).
  absl::StatusOr<uint64_t> CountInvalidTriangles() const;
  absl::StatusOr<uint64_t> CountIllegalEdges() const;

  uint64_t device_bytes() const;

 private:
  struct Impl;
  explicit DeviceTriangulation(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace kinetri::core::cuda

#endif  // KINETRI_CORE_CUDA_DEVICE_TRIANGULATION_H_
