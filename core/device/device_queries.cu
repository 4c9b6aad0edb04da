// Device k-NN and fixed-radius queries: one query per thread running the
// mark-free searches of core/query_search.h; rows sized in a first pass and
// placed with an exclusive scan, then filled and put in the exact order.
#include <cuda_runtime.h>
#include <thrust/execution_policy.h>
#include <thrust/scan.h>

#include <algorithm>
#include <vector>

#include "absl/strings/str_cat.h"
#include "core/device/device_buffer.h"
#include "core/device/device_triangulation.h"
#include "core/device/device_triangulation_impl.h"
#include "core/query_search.h"

namespace kinetri::core::cuda {
namespace {

constexpr int kBlock = 128;
int Blocks(uint64_t n) { return static_cast<int>((n + kBlock - 1) / kBlock); }

struct DeviceQuery {
  Vec2 q;
  uint32_t root;  // nearest site of q
  uint32_t self;  // external id to leave out, or kNoVertex
};

__global__ void PrepareIds(TriangulationView v, const uint32_t* ids,
                           uint32_t nq, bool exclude_self, DeviceQuery* out) {
  const uint32_t i = blockIdx.x * blockDim.x + threadIdx.x;
  if (i >= nq) return;
  const uint32_t in = v.int_of_ext[ids[i]];
  out[i] = {v.pos[in], v.rep[in], exclude_self ? ids[i] : kNoVertex};
}

__global__ void PreparePositions(TriangulationView v, HintGridView hints,
                                 const Vec2* qs, uint32_t nq,
                                 DeviceQuery* out) {
  const uint32_t i = blockIdx.x * blockDim.x + threadIdx.x;
  if (i >= nq) return;
  out[i] = {qs[i], WalkToNearestSite(v, qs[i], hints.Hint(qs[i])), kNoVertex};
}

__global__ void RadiusCount(TriangulationView v, const DeviceQuery* qs,
                            uint32_t nq, double r, uint64_t* counts) {
  const uint32_t i = blockIdx.x * blockDim.x + threadIdx.x;
  if (i >= nq) return;
  counts[i] = CountPointsWithin(v, qs[i].q, r, qs[i].root, qs[i].self);
}

__global__ void RadiusFill(TriangulationView v, const DeviceQuery* qs,
                           uint32_t nq, double r, const uint64_t* offsets,
                           uint32_t* points) {
  const uint32_t i = blockIdx.x * blockDim.x + threadIdx.x;
  if (i >= nq) return;
  uint64_t k = offsets[i];
  const DeviceQuery dq = qs[i];
  RadiusSearch(v, dq.q, r, dq.root, [&](uint32_t s) {
    for (uint32_t p = s; p != kNoVertex; p = v.dup_next[p]) {
      if (v.ext_of_int[p] != dq.self) points[k++] = p;
    }
  });
}

// Sorts each row (internal point ids) into the exact order of queries.h and
// writes external ids and distances.
__global__ void OrderRows(TriangulationView v, const DeviceQuery* qs,
                          uint32_t nq, const uint64_t* offsets,
                          uint32_t* points, uint32_t* ext, double* dist) {
  const uint32_t i = blockIdx.x * blockDim.x + threadIdx.x;
  if (i >= nq) return;
  const Vec2 q = qs[i].q;
  const uint64_t b = offsets[i], e = offsets[i + 1];
  auto before = [&](uint32_t a, uint32_t c) {
    const int s = CompareCloserCached(q, v.pos[a], SquaredDistance(q, v.pos[a]),
                                      v.pos[c], SquaredDistance(q, v.pos[c]));
    return s < 0 || (s == 0 && v.ext_of_int[a] < v.ext_of_int[c]);
  };
  for (uint64_t j = b + 1; j < e; ++j) {
    const uint32_t x = points[j];
    uint64_t m = j;
    while (m > b && before(x, points[m - 1])) {
      points[m] = points[m - 1];
      --m;
    }
    points[m] = x;
  }
  for (uint64_t j = b; j < e; ++j) {
    ext[j] = v.ext_of_int[points[j]];
    dist[j] = sqrt(SquaredDistance(q, v.pos[points[j]]));
  }
}

__global__ void KnnKernel(TriangulationView v, const DeviceQuery* qs,
                          uint32_t nq, uint32_t k, KnnEntry* buf,
                          uint64_t* counts) {
  const uint32_t i = blockIdx.x * blockDim.x + threadIdx.x;
  if (i >= nq) return;
  counts[i] = KNearestSearch(v, qs[i].q, k, qs[i].root, qs[i].self,
                             buf + uint64_t{i} * k);
}

__global__ void KnnCompact(TriangulationView v, uint32_t nq, uint32_t k,
                           const KnnEntry* buf, const uint64_t* offsets,
                           uint32_t* ext, double* dist) {
  const uint32_t i = blockIdx.x * blockDim.x + threadIdx.x;
  if (i >= nq) return;
  for (uint64_t j = offsets[i]; j < offsets[i + 1]; ++j) {
    const KnnEntry& en = buf[uint64_t{i} * k + (j - offsets[i])];
    ext[j] = v.ext_of_int[en.point];
    dist[j] = sqrt(en.d2);
  }
}

absl::Status Launched() { return Check(cudaGetLastError(), "launch"); }

// counts[0..nq) -> offsets[0..nq] (exclusive scan on the device); *total
// is offsets[nq], the only value read back.
absl::Status Scan(Buffer<uint64_t>& counts, uint32_t nq,
                  Buffer<uint64_t>* offsets, uint64_t* total) {
  absl::Status s = offsets->Allocate(size_t{nq} + 1);
  if (!s.ok()) return s;
  s = Check(cudaMemset(counts.ptr + nq, 0, sizeof(uint64_t)), "memset");
  if (!s.ok()) return s;
  thrust::exclusive_scan(thrust::device, counts.ptr, counts.ptr + nq + 1,
                         offsets->ptr);
  s = Check(cudaGetLastError(), "scan");
  if (!s.ok()) return s;
  return Check(cudaMemcpy(total, offsets->ptr + nq, sizeof *total,
                          cudaMemcpyDeviceToHost),
               "download");
}

// Downloads CSR rows; cuts rows to max_results (0: no cut) on the host.
absl::StatusOr<NeighborLists> Download(const Buffer<uint64_t>& offsets,
                                       uint32_t nq, const Buffer<uint32_t>& ext,
                                       const Buffer<double>& dist,
                                       uint32_t max_results) {
  NeighborLists full;
  full.offsets.resize(size_t{nq} + 1);
  absl::Status s = offsets.Download(full.offsets.data(), size_t{nq} + 1);
  if (!s.ok()) return s;
  const uint64_t total = full.offsets[nq];
  full.ids.resize(total);
  full.distances.resize(total);
  s = ext.Download(full.ids.data(), total);
  if (s.ok()) s = dist.Download(full.distances.data(), total);
  if (!s.ok()) return s;
  full.truncated.assign(nq, 0);
  if (max_results == 0) return full;
  NeighborLists cut;
  cut.offsets.assign(size_t{nq} + 1, 0);
  cut.truncated.assign(nq, 0);
  for (uint32_t i = 0; i < nq; ++i) {
    const uint64_t b = full.offsets[i];
    const uint64_t len = full.offsets[i + 1] - b;
    const uint64_t keep = len > max_results ? max_results : len;
    cut.truncated[i] = len > keep ? 1 : 0;
    cut.ids.insert(cut.ids.end(), full.ids.begin() + b,
                   full.ids.begin() + b + keep);
    cut.distances.insert(cut.distances.end(), full.distances.begin() + b,
                         full.distances.begin() + b + keep);
    cut.offsets[i + 1] = cut.offsets[i] + keep;
  }
  return cut;
}

absl::Status CheckIds(absl::Span<const uint32_t> ids, uint32_t n) {
  for (size_t i = 0; i < ids.size(); ++i) {
    if (ids[i] >= n) {
      return absl::NotFoundError(absl::StrCat(
          "ids[", i, "] = ", ids[i], ": no such point (size ", n, ")"));
    }
  }
  return absl::OkStatus();
}

// The queries of one call: point ids or positions.
struct QueryInput {
  absl::Span<const uint32_t> ids;
  absl::Span<const Vec2> positions;
  bool exclude_self = false;
  bool by_id() const { return positions.empty() && !ids.empty(); }
  size_t size() const { return by_id() ? ids.size() : positions.size(); }
};

absl::Status Prepare(const TriangulationView& v, const HintGridView& hints,
                     const QueryInput& in, Buffer<DeviceQuery>* out) {
  const uint32_t nq = static_cast<uint32_t>(in.size());
  absl::Status s = out->Allocate(nq);
  if (!s.ok() || nq == 0) return s;
  if (in.by_id()) {
    Buffer<uint32_t> ids;
    s = ids.Upload(in.ids.data(), nq);
    if (!s.ok()) return s;
    PrepareIds<<<Blocks(nq), kBlock>>>(v, ids.ptr, nq, in.exclude_self,
                                       out->ptr);
    s = Launched();
    if (s.ok()) s = Check(cudaDeviceSynchronize(), "prepare");
    return s;
  }
  Buffer<Vec2> qs;
  s = qs.Upload(in.positions.data(), nq);
  if (!s.ok()) return s;
  PreparePositions<<<Blocks(nq), kBlock>>>(v, hints, qs.ptr, nq, out->ptr);
  s = Launched();
  if (s.ok()) s = Check(cudaDeviceSynchronize(), "prepare");
  return s;
}

absl::StatusOr<NeighborLists> EmptyRows(size_t nq) {
  NeighborLists out;
  out.offsets.assign(nq + 1, 0);
  out.truncated.assign(nq, 0);
  return out;
}

absl::StatusOr<NeighborLists> Radius(const TriangulationView& v,
                                     const HintGridView& hints,
                                     const QueryInput& in, double r,
                                     uint32_t max_results, QueryLimits limits) {
  if (absl::Status s = CheckQueryRadius(r); !s.ok()) return s;
  const uint32_t nq = static_cast<uint32_t>(in.size());
  if (nq == 0 || v.num_sites == 0) return EmptyRows(nq);
  Buffer<DeviceQuery> qs;
  absl::Status s = Prepare(v, hints, in, &qs);
  Buffer<uint64_t> counts, offsets;
  if (s.ok()) s = counts.Allocate(size_t{nq} + 1);
  if (!s.ok()) return s;
  RadiusCount<<<Blocks(nq), kBlock>>>(v, qs.ptr, nq, r, counts.ptr);
  s = Launched();
  uint64_t total = 0;
  if (s.ok()) s = Scan(counts, nq, &offsets, &total);
  if (!s.ok()) return s;
  // The limit applies to the rows returned (after any per-row cut), as on
  // the CPU; the full rows are checked first only when no cut applies.
  if (limits.max_total_results && max_results == 0 &&
      total > limits.max_total_results) {
    return absl::ResourceExhaustedError(
        absl::StrCat("query produced ", total, " results, above the limit of ",
                     limits.max_total_results));
  }
  Buffer<uint32_t> points, ext;
  Buffer<double> dist;
  s = points.Allocate(total);
  if (s.ok()) s = ext.Allocate(total);
  if (s.ok()) s = dist.Allocate(total);
  if (!s.ok()) return s;
  RadiusFill<<<Blocks(nq), kBlock>>>(v, qs.ptr, nq, r, offsets.ptr, points.ptr);
  s = Launched();
  if (!s.ok()) return s;
  OrderRows<<<Blocks(nq), kBlock>>>(v, qs.ptr, nq, offsets.ptr, points.ptr,
                                    ext.ptr, dist.ptr);
  s = Launched();
  if (!s.ok()) return s;
  auto out = Download(offsets, nq, ext, dist, max_results);
  if (out.ok() && limits.max_total_results &&
      out->offsets[nq] > limits.max_total_results) {
    return absl::ResourceExhaustedError(absl::StrCat(
        "query produced ", out->offsets[nq], " results, above the limit of ",
        limits.max_total_results));
  }
  return out;
}

absl::StatusOr<NeighborLists> Knn(const TriangulationView& v,
                                  const HintGridView& hints,
                                  const QueryInput& in, int k,
                                  QueryLimits limits) {
  if (absl::Status s = CheckQueryK(k); !s.ok()) return s;
  const uint32_t nq = static_cast<uint32_t>(in.size());
  if (nq == 0 || v.num_sites == 0) return EmptyRows(nq);
  // Every row holds min(k, points other than the query's own).
  const uint32_t others =
      v.num_points - (in.by_id() && in.exclude_self ? 1u : 0u);
  const uint32_t kk = static_cast<uint32_t>(
      std::min<uint64_t>(static_cast<uint64_t>(k), v.num_points));
  const uint64_t total_rows =
      std::min<uint64_t>(static_cast<uint64_t>(k), others) * nq;
  if (limits.max_total_results && total_rows > limits.max_total_results) {
    return absl::ResourceExhaustedError(absl::StrCat(
        "query produced ", total_rows, " results, above the limit of ",
        limits.max_total_results));
  }
  Buffer<DeviceQuery> qs;
  absl::Status s = Prepare(v, hints, in, &qs);
  Buffer<KnnEntry> buf;
  Buffer<uint64_t> counts, offsets;
  if (s.ok()) s = buf.Allocate(uint64_t{kk} * nq);
  if (s.ok()) s = counts.Allocate(size_t{nq} + 1);
  if (!s.ok()) return s;
  KnnKernel<<<Blocks(nq), kBlock>>>(v, qs.ptr, nq, kk, buf.ptr, counts.ptr);
  s = Launched();
  uint64_t total = 0;
  if (s.ok()) s = Scan(counts, nq, &offsets, &total);
  if (!s.ok()) return s;
  if (limits.max_total_results && total > limits.max_total_results) {
    return absl::ResourceExhaustedError(
        absl::StrCat("query produced ", total, " results, above the limit of ",
                     limits.max_total_results));
  }
  Buffer<uint32_t> ext;
  Buffer<double> dist;
  s = ext.Allocate(total);
  if (s.ok()) s = dist.Allocate(total);
  if (!s.ok()) return s;
  KnnCompact<<<Blocks(nq), kBlock>>>(v, nq, kk, buf.ptr, offsets.ptr, ext.ptr,
                                     dist.ptr);
  s = Launched();
  if (!s.ok()) return s;
  return Download(offsets, nq, ext, dist, 0);
}

}  // namespace

absl::StatusOr<NeighborLists> DeviceTriangulation::KNearest(
    absl::Span<const Vec2> queries, int k, QueryLimits limits) const {
  if (absl::Status s = CheckQueryPositions(queries); !s.ok()) return s;
  QueryInput in;
  in.positions = queries;
  return Knn(impl_->view, impl_->hints, in, k, limits);
}

absl::StatusOr<NeighborLists> DeviceTriangulation::KNearestOfPoints(
    absl::Span<const uint32_t> ids, int k, bool exclude_self,
    QueryLimits limits) const {
  if (absl::Status s = CheckIds(ids, impl_->view.num_points); !s.ok()) return s;
  QueryInput in;
  in.ids = ids;
  in.exclude_self = exclude_self;
  return Knn(impl_->view, impl_->hints, in, k, limits);
}

absl::StatusOr<NeighborLists> DeviceTriangulation::WithinRadius(
    absl::Span<const Vec2> queries, double r, uint32_t max_results,
    QueryLimits limits) const {
  if (absl::Status s = CheckQueryPositions(queries); !s.ok()) return s;
  QueryInput in;
  in.positions = queries;
  return Radius(impl_->view, impl_->hints, in, r, max_results, limits);
}

absl::StatusOr<NeighborLists> DeviceTriangulation::WithinRadiusOfPoints(
    absl::Span<const uint32_t> ids, double r, bool exclude_self,
    uint32_t max_results, QueryLimits limits) const {
  if (absl::Status s = CheckIds(ids, impl_->view.num_points); !s.ok()) return s;
  QueryInput in;
  in.ids = ids;
  in.exclude_self = exclude_self;
  return Radius(impl_->view, impl_->hints, in, r, max_results, limits);
}

}  // namespace kinetri::core::cuda
