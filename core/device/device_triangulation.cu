// CUDA executor (first slice): kernels over the shared host+device steps.
#include <cuda_runtime.h>

#include <string>
#include <vector>

#include "absl/strings/str_cat.h"
#include "core/device/device_buffer.h"
#include "core/device/device_triangulation.h"
#include "core/device/device_triangulation_impl.h"
#include "core/flip_rules.h"
#include "core/hint_grid.h"
#include "core/query_walks.h"

namespace kinetri::core::cuda {
namespace {

constexpr int kBlock = 256;
int Blocks(uint64_t n) { return static_cast<int>((n + kBlock - 1) / kBlock); }

__global__ void AllNearestKernel(TriangulationView v, uint32_t* nn,
                                 double* dist) {
  const uint32_t in = blockIdx.x * blockDim.x + threadIdx.x;
  if (in >= v.num_points) return;
  uint32_t best;
  double d;
  const uint32_t ext = v.ext_of_int[in];
  if (NearestOtherPoint(v, in, &best, &d)) {
    nn[ext] = best;
    dist[ext] = d;
  } else {
    nn[ext] = kNoVertex;
    dist[ext] = 0.0;
  }
}

__global__ void InvalidTrianglesKernel(MeshView m, const Vec2* pos, uint32_t nt,
                                       unsigned long long* count) {
  const uint32_t t = blockIdx.x * blockDim.x + threadIdx.x;
  if (t < nt && !rules::TriangleOk(m, pos, t)) atomicAdd(count, 1ull);
}

__global__ void IllegalEdgesKernel(MeshView m, const Vec2* pos, uint32_t ne,
                                   unsigned long long* count) {
  const uint32_t e = blockIdx.x * blockDim.x + threadIdx.x;
  if (e < ne && e < m.twin[e] && rules::IsIllegal(m, pos, e)) {
    atomicAdd(count, 1ull);
  }
}

}  // namespace

bool DeviceAvailable() {
  int count = 0;
  return cudaGetDeviceCount(&count) == cudaSuccess && count > 0;
}

DeviceTriangulation::DeviceTriangulation(std::unique_ptr<Impl> impl)
    : impl_(std::move(impl)) {}
DeviceTriangulation::DeviceTriangulation(DeviceTriangulation&&) noexcept =
    default;
DeviceTriangulation& DeviceTriangulation::operator=(
    DeviceTriangulation&&) noexcept = default;
DeviceTriangulation::~DeviceTriangulation() = default;

uint64_t DeviceTriangulation::device_bytes() const { return impl_->bytes; }

double DeviceTriangulation::bytes_per_point() const {
  const uint32_t n = impl_->view.num_points;
  return n ? static_cast<double>(impl_->bytes) / n : 0.0;
}

absl::StatusOr<DeviceTriangulation> DeviceTriangulation::Upload(
    const Triangulation& t) {
  if (!DeviceAvailable()) {
    return absl::FailedPreconditionError("no CUDA device present");
  }
  // The query view carries the neighbour rows; the coarse hint grid gives
  // position queries their walk starts.
  const TriangulationView h = t.query_view();
  const HintGrid grid(h);
  auto impl = std::make_unique<Impl>();
  const uint32_t n = h.num_points;
  const uint32_t ne = h.mesh.num_half_edges;
  absl::Status s;
  auto up = [&](auto& buf, const auto* src, size_t count) {
    if (s.ok() && src != nullptr) s = buf.Upload(src, count);
  };
  up(impl->pos, h.pos, n);
  up(impl->ext_of_int, h.ext_of_int, n);
  up(impl->int_of_ext, h.int_of_ext, n);
  up(impl->rep, h.rep, n);
  up(impl->dup_next, h.dup_next, n);
  up(impl->sites, h.sites, h.num_sites);
  if (h.planar()) {
    up(impl->origin, h.mesh.origin, ne);
    up(impl->twin, h.mesh.twin, ne);
    up(impl->vertex_edge, h.vertex_edge, n);
  } else {
    up(impl->line, h.line, h.num_sites);
    up(impl->line_rank, h.line_rank, n);
  }
  up(impl->adj_offsets, h.adj_offsets, size_t{n} + 1);
  up(impl->adj, h.adj, h.adj_offsets[n]);
  up(impl->hint_cells, grid.cells().data(), grid.cells().size());
  if (!s.ok()) return s;
  impl->hints = grid.view();
  impl->hints.cells = impl->hint_cells.ptr;
  TriangulationView& d = impl->view;
  d = h;
  d.pos = impl->pos.ptr;
  d.ext_of_int = impl->ext_of_int.ptr;
  d.int_of_ext = impl->int_of_ext.ptr;
  d.rep = impl->rep.ptr;
  d.dup_next = impl->dup_next.ptr;
  d.sites = impl->sites.ptr;
  d.mesh.origin = impl->origin.ptr;
  d.mesh.twin = impl->twin.ptr;
  d.vertex_edge = impl->vertex_edge.ptr;
  d.line = impl->line.ptr;
  d.line_rank = impl->line_rank.ptr;
  d.adj_offsets = impl->adj_offsets.ptr;
  d.adj = impl->adj.ptr;
  impl->bytes =
      (uint64_t{n} + 1 + h.adj_offsets[n] + grid.cells().size()) *
          sizeof(uint32_t) +
      uint64_t{n} * (sizeof(Vec2) + 5 * sizeof(uint32_t) +
                     (h.planar() ? sizeof(uint32_t) : 0)) +
      uint64_t{h.num_sites} * sizeof(uint32_t) * (h.planar() ? 1 : 2) +
      uint64_t{ne} * 2 * sizeof(uint32_t);
  // Device exact predicates keep large expansions on the stack: the
  // process-wide limit is raised once, never per call.
  static const cudaError_t stack_limit =
      cudaDeviceSetLimit(cudaLimitStackSize, 96 * 1024);
  s = Check(stack_limit, "stack limit");
  if (!s.ok()) return s;
  return DeviceTriangulation(std::move(impl));
}

absl::StatusOr<NeighborLists> DeviceTriangulation::AllNearestNeighbors() const {
  const uint32_t n = impl_->view.num_points;
  NeighborLists out;
  out.offsets.assign(size_t{n} + 1, 0);
  out.truncated.assign(n, 0);
  if (n == 0) return out;
  Buffer<uint32_t> nn;
  Buffer<double> dist;
  absl::Status s = Check(cudaMalloc(&nn.ptr, n * sizeof(uint32_t)), "malloc");
  if (s.ok()) s = Check(cudaMalloc(&dist.ptr, n * sizeof(double)), "malloc");
  if (!s.ok()) return s;
  AllNearestKernel<<<Blocks(n), kBlock>>>(impl_->view, nn.ptr, dist.ptr);
  s = Check(cudaGetLastError(), "launch");
  if (!s.ok()) return s;
  std::vector<uint32_t> h_nn(n);
  std::vector<double> h_dist(n);
  s = Check(cudaMemcpy(h_nn.data(), nn.ptr, n * sizeof(uint32_t),
                       cudaMemcpyDeviceToHost),
            "download");
  if (s.ok()) {
    s = Check(cudaMemcpy(h_dist.data(), dist.ptr, n * sizeof(double),
                         cudaMemcpyDeviceToHost),
              "download");
  }
  if (!s.ok()) return s;
  for (uint32_t i = 0; i < n; ++i) {
    out.offsets[i + 1] = out.offsets[i] + (h_nn[i] != kNoVertex ? 1 : 0);
    if (h_nn[i] == kNoVertex) continue;
    out.ids.push_back(h_nn[i]);
    out.distances.push_back(h_dist[i]);
  }
  return out;
}

namespace {
template <typename Launch>
absl::StatusOr<uint64_t> Count(Launch&& launch) {
  unsigned long long* d = nullptr;
  absl::Status s = Check(cudaMalloc(&d, sizeof(*d)), "malloc");
  if (s.ok()) s = Check(cudaMemset(d, 0, sizeof(*d)), "memset");
  if (s.ok()) {
    launch(d);
    s = Check(cudaGetLastError(), "launch");
  }
  unsigned long long h = 0;
  if (s.ok()) {
    s = Check(cudaMemcpy(&h, d, sizeof(h), cudaMemcpyDeviceToHost), "download");
  }
  if (d) cudaFree(d);
  if (!s.ok()) return s;
  return static_cast<uint64_t>(h);
}
}  // namespace

absl::StatusOr<uint64_t> DeviceTriangulation::CountInvalidTriangles() const {
  const MeshView m = impl_->view.mesh;
  const uint32_t nt = m.num_half_edges / 3;
  if (nt == 0) return uint64_t{0};
  const Vec2* pos = impl_->view.pos;
  return Count([&](unsigned long long* d) {
    InvalidTrianglesKernel<<<Blocks(nt), kBlock>>>(m, pos, nt, d);
  });
}

absl::StatusOr<uint64_t> DeviceTriangulation::CountIllegalEdges() const {
  const MeshView m = impl_->view.mesh;
  if (m.num_half_edges == 0) return uint64_t{0};
  const Vec2* pos = impl_->view.pos;
  return Count([&](unsigned long long* d) {
    IllegalEdgesKernel<<<Blocks(m.num_half_edges), kBlock>>>(
        m, pos, m.num_half_edges, d);
  });
}

}  // namespace kinetri::core::cuda
