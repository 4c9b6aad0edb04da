// Owning half-edge mesh: construction, vertex->edge links, renumbering.
#include "core/mesh.h"

#include <algorithm>
#include <atomic>
#include <utility>

#include "core/parallel.h"

namespace kinetri::core {

Mesh::Mesh(uint32_t num_vertices, std::vector<uint32_t> origin,
           std::vector<uint32_t> twin)
    : num_vertices_(num_vertices),
      origin_(std::move(origin)),
      twin_(std::move(twin)) {
  RebuildVertexEdges();
}

void Mesh::Assign(std::vector<uint32_t> origin, std::vector<uint32_t> twin,
                  std::vector<uint32_t> vertex_edge) {
  origin_ = std::move(origin);
  twin_ = std::move(twin);
  vertex_edge_ = std::move(vertex_edge);
}

void Mesh::RebuildVertexEdges() {
  vertex_edge_.assign(num_vertices_, kNoEdge);
  uint32_t* ve = vertex_edge_.data();
  const uint32_t* org = origin_.data();
  ParallelFor(0, origin_.size(), [&](size_t e) {
    const uint32_t v = org[e];
    if (v == kInfiniteVertex || v == kNoVertex) return;
    std::atomic_ref<uint32_t> slot(ve[v]);
    uint32_t cur = slot.load(std::memory_order_relaxed);
    const uint32_t mine = static_cast<uint32_t>(e);
    while (mine < cur &&
           !slot.compare_exchange_weak(cur, mine, std::memory_order_relaxed)) {
    }
  });
}

void Mesh::RenumberVertices(const std::vector<uint32_t>& new_of_old) {
  uint32_t* org = origin_.data();
  ParallelFor(0, origin_.size(), [&](size_t e) {
    if (org[e] != kInfiniteVertex && org[e] != kNoVertex) {
      org[e] = new_of_old[org[e]];
    }
  });
  RebuildVertexEdges();
}

void Mesh::ResizeVertices(uint32_t num_vertices) {
  num_vertices_ = num_vertices;
  vertex_edge_.resize(num_vertices_, kNoEdge);
}

void Mesh::RelabelVertex(uint32_t from, uint32_t to) {
  const uint32_t e0 = vertex_edge_[from];
  if (e0 != kNoEdge) {
    uint32_t e = e0;
    do {
      origin_[e] = to;
      e = twin_[Prev(e)];
    } while (e != e0);
  }
  vertex_edge_[to] = e0;
  vertex_edge_[from] = kNoEdge;
}

void Mesh::SortTrianglesByVertex() {
  const uint32_t nt = num_triangles();
  std::vector<uint32_t> key(nt);
  ParallelFor(0, nt, [&](size_t t) {
    uint32_t k = kInfiniteVertex;
    for (size_t e = 3 * t; e < 3 * t + 3; ++e) k = std::min(k, origin_[e]);
    key[t] = k == kInfiniteVertex ? num_vertices_ : k;
  });
  std::vector<uint32_t> start(size_t{num_vertices_} + 2, 0);
  for (uint32_t t = 0; t < nt; ++t) ++start[key[t] + 1];
  for (size_t i = 1; i < start.size(); ++i) start[i] += start[i - 1];
  std::vector<uint32_t> new_of_old(nt);
  for (uint32_t t = 0; t < nt; ++t) new_of_old[t] = start[key[t]]++;
  std::vector<uint32_t> origin(origin_.size()), twin(twin_.size());
  ParallelFor(0, nt, [&](size_t t) {
    const uint32_t nt3 = 3 * new_of_old[t];
    for (uint32_t k = 0; k < 3; ++k) {
      const uint32_t f = twin_[3 * t + k];
      origin[nt3 + k] = origin_[3 * t + k];
      twin[nt3 + k] = 3 * new_of_old[f / 3] + f % 3;
    }
  });
  origin_ = std::move(origin);
  twin_ = std::move(twin);
  RebuildVertexEdges();
}

void Mesh::UpdateVertexEdgesAfterFlip(uint32_t e) {
  const uint32_t f = twin_[e];
  for (uint32_t h : {e, Next(e), Prev(e), f, Next(f), Prev(f)}) {
    const uint32_t v = origin_[h];
    if (v != kInfiniteVertex) vertex_edge_[v] = h;
  }
}

uint32_t Mesh::AllocateTriangle() {
  if (!free_.empty()) {
    const uint32_t t = free_.back();
    free_.pop_back();
    return t;
  }
  const uint32_t t = num_triangles();
  origin_.resize(origin_.size() + 3, kNoVertex);
  twin_.resize(twin_.size() + 3, kNoEdge);
  return t;
}

void Mesh::FreeTriangle(uint32_t t) {
  for (uint32_t e = 3 * t; e < 3 * t + 3; ++e) {
    origin_[e] = kNoVertex;
    twin_[e] = kNoEdge;
  }
  free_.push_back(t);
}

void Mesh::Compact() {
  std::sort(free_.begin(), free_.end());
  size_t lo = 0;
  uint32_t last = num_triangles();
  while (lo < free_.size()) {
    // Drop free slots at the end.
    while (last > 0 && origin_[3 * (last - 1)] == kNoVertex) --last;
    if (free_[lo] >= last) break;
    const uint32_t dst = free_[lo++];
    const uint32_t src = last - 1;
    for (uint32_t k = 0; k < 3; ++k) {
      const uint32_t from = 3 * src + k, to = 3 * dst + k;
      origin_[to] = origin_[from];
      twin_[to] = twin_[from];
      twin_[twin_[to]] = to;
      const uint32_t v = origin_[to];
      if (v != kInfiniteVertex && vertex_edge_[v] == from) vertex_edge_[v] = to;
      origin_[from] = kNoVertex;
      twin_[from] = kNoEdge;
    }
    last = src;
  }
  while (last > 0 && origin_[3 * (last - 1)] == kNoVertex) --last;
  origin_.resize(size_t{3} * last);
  twin_.resize(size_t{3} * last);
  free_.clear();
}

}  // namespace kinetri::core
