// CUDA executor (partial): a device-resident copy of a triangulation on
// which the shared host+device steps run as kernels: all-points nearest
// neighbour; k-NN and fixed-radius queries of points and of arbitrary
// positions (the mark-free searches of core/query_search.h, CSR rows built
// with a device scan); the fixing/legalizing scans (invalid triangles,
// illegal edges). Answers equal the CPU executor's (core/queries.h). Built
// only with CUDA (KINETRI_CUDA); no CUDA types leak out.
#ifndef KINETRI_CORE_DEVICE_DEVICE_TRIANGULATION_H_
#define KINETRI_CORE_DEVICE_DEVICE_TRIANGULATION_H_

#include <cstdint>
#include <memory>

#include "absl/status/statusor.h"
#include "absl/types/span.h"
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

  // The queries of core/queries.h, same arguments, checks and answers.
  absl::StatusOr<NeighborLists> KNearest(absl::Span<const Vec2> queries, int k,
                                         QueryLimits limits = {}) const;
  absl::StatusOr<NeighborLists> KNearestOfPoints(absl::Span<const uint32_t> ids,
                                                 int k, bool exclude_self,
                                                 QueryLimits limits = {}) const;
  absl::StatusOr<NeighborLists> WithinRadius(absl::Span<const Vec2> queries,
                                             double r, uint32_t max_results,
                                             QueryLimits limits = {}) const;
  absl::StatusOr<NeighborLists> WithinRadiusOfPoints(
      absl::Span<const uint32_t> ids, double r, bool exclude_self,
      uint32_t max_results, QueryLimits limits = {}) const;

  // Device memory held by the triangulation (query outputs excluded).
  uint64_t device_bytes() const;
  double bytes_per_point() const;

 private:
  struct Impl;
  explicit DeviceTriangulation(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace kinetri::core::cuda

#endif  // KINETRI_CORE_DEVICE_DEVICE_TRIANGULATION_H_
