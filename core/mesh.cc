// Owning half-edge mesh: construction, vertex->edge links, renumbering.
#include "core/mesh.h"

#include <algorithm>
#include <atomic>
#include <utility>

#include "core/parallel.h"

namespace kinetri::core {

uint64_t Mesh::ContentStamp::number() const {
  static std::atomic<uint64_t> last{0};
  if (touched_.load(std::memory_order_acquire)) {
    number_.store(last.fetch_add(1, std::memory_order_relaxed) + 1,
                  std::memory_order_relaxed);
    touched_.store(false, std::memory_order_release);
  }
  return number_.load(std::memory_order_relaxed);
}

Mesh::Mesh(uint32_t num_vertices, std::vector<uint32_t> origin,
           std::vector<uint32_t> twin, Layout layout)
    : num_vertices_(num_vertices),
      origin_(std::move(origin)),
      twin_(std::move(twin)) {
  if (layout == Layout::kCanonical) SortTriangles();
  RebuildVertexEdges();
}

void Mesh::SwapArrays(std::vector<uint32_t>* origin,
                      std::vector<uint32_t>* twin,
                      std::vector<uint32_t>* vertex_edge) {
  stamp_.Touch();
  origin_.swap(*origin);
  twin_.swap(*twin);
  vertex_edge_.swap(*vertex_edge);
}

namespace {

// One entry's terms of the two fingerprint sums.
inline uint32_t Term0(uint32_t value, uint32_t index) {
  return (value ^ (index * 0x9E3779B9u)) * 0x85EBCA6Bu;
}
inline uint32_t Term1(uint32_t value, uint32_t index) {
  return (value + (index * 0x7FEB352Du)) * 0xC2B2AE35u;
}

}  // namespace

Mesh::FingerprintSums Mesh::FingerprintParts() const {
  FingerprintSums out;
  auto add = [&](const std::vector<uint32_t>& a, int k) {
    constexpr size_t kBlock = size_t{1} << 16;
    const uint32_t* p = a.data();
    const size_t n = a.size();
    const uint32_t salt = static_cast<uint32_t>(k + 1);
    std::atomic<uint32_t> s0{salt}, s1{~salt};
    ParallelFor(
        0, (n + kBlock - 1) / kBlock,
        [&](size_t b) {
          const uint32_t end =
              static_cast<uint32_t>(std::min(n, (b + 1) * kBlock));
          uint32_t t0 = 0, t1 = 0;
          for (uint32_t i = static_cast<uint32_t>(b * kBlock); i < end; ++i) {
            t0 += Term0(p[i], i);
            t1 += Term1(p[i], i);
          }
          s0.fetch_add(t0, std::memory_order_relaxed);
          s1.fetch_add(t1, std::memory_order_relaxed);
        },
        1);
    out.s0[k] = s0.load();
    out.s1[k] = s1.load();
  };
  add(origin_, 0);
  add(twin_, 1);
  add(vertex_edge_, 2);
  return out;
}

void Mesh::FingerprintSums::Change(int array, uint32_t index, uint32_t from,
                                   uint32_t to) {
  s0[array] += Term0(to, index) - Term0(from, index);
  s1[array] += Term1(to, index) - Term1(from, index);
}

uint64_t Mesh::FingerprintSums::Combine() const {
  uint32_t lo = 0, hi = 0;
  for (int k = 0; k < 3; ++k) {
    lo = lo * 0x27D4EB2Fu + s0[k];
    hi = hi * 0x165667B1u + s1[k];
  }
  return (uint64_t{hi} << 32) | lo;
}

uint64_t Mesh::Fingerprint() const { return FingerprintParts().Combine(); }

void Mesh::RebuildVertexEdges() {
  stamp_.Touch();
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
  stamp_.Touch();
  uint32_t* org = origin_.data();
  ParallelFor(0, origin_.size(), [&](size_t e) {
    if (org[e] != kInfiniteVertex && org[e] != kNoVertex) {
      org[e] = new_of_old[org[e]];
    }
  });
  RebuildVertexEdges();
}

void Mesh::ResizeVertices(uint32_t num_vertices) {
  stamp_.Touch();
  num_vertices_ = num_vertices;
  vertex_edge_.resize(num_vertices_, kNoEdge);
}

void Mesh::RelabelVertex(uint32_t from, uint32_t to) {
  stamp_.Touch();
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
  SortTriangles();
  RebuildVertexEdges();
}

void Mesh::SortTriangles() {
  stamp_.Touch();
  const uint32_t nt = num_triangles();
  // Each triangle is keyed by its smallest vertex (the infinite vertex
  // counts as the largest) and turned so that this vertex comes first; the
  // vertex after it (unique among the triangles of that key: two would share
  // a directed edge) orders triangles of equal key.
  const uint32_t inf_key = num_vertices_;
  auto rank = [&](uint32_t v) { return v == kInfiniteVertex ? inf_key : v; };
  std::vector<uint32_t> key(nt), second(nt);
  std::vector<uint8_t> turn(nt);
  ParallelFor(0, nt, [&](size_t t) {
    uint32_t best = 0;
    for (uint32_t k = 1; k < 3; ++k) {
      if (rank(origin_[3 * t + k]) < rank(origin_[3 * t + best])) best = k;
    }
    key[t] = rank(origin_[3 * t + best]);
    second[t] = rank(origin_[3 * t + (best + 1) % 3]);
    turn[t] = static_cast<uint8_t>(best);
  });
  // Bucket by key: counts and places in parallel (the order a bucket gets
  // filled in does not matter: each bucket is sorted by `second` after).
  std::vector<uint32_t> start(size_t{num_vertices_} + 2, 0);
  ParallelFor(0, nt, [&](size_t t) {
    std::atomic_ref<uint32_t>(start[key[t] + 1])
        .fetch_add(1, std::memory_order_relaxed);
  });
  for (size_t i = 1; i < start.size(); ++i) start[i] += start[i - 1];
  std::vector<uint32_t> order(nt);
  {
    std::vector<uint32_t> fill(start.begin(), start.end() - 1);
    ParallelFor(0, nt, [&](size_t t) {
      const uint32_t at = std::atomic_ref<uint32_t>(fill[key[t]])
                              .fetch_add(1, std::memory_order_relaxed);
      order[at] = static_cast<uint32_t>(t);
    });
  }
  std::vector<uint32_t> new_of_old(nt);
  ParallelFor(0, size_t{num_vertices_} + 1, [&](size_t v) {
    uint32_t* b = order.data() + start[v];
    uint32_t* e = order.data() + start[v + 1];
    std::sort(b, e,
              [&](uint32_t x, uint32_t y) { return second[x] < second[y]; });
    for (uint32_t* i = b; i != e; ++i) {
      new_of_old[*i] = static_cast<uint32_t>(i - order.data());
    }
  });
  // Old half-edge 3t+k lands in slot k - turn[t] of the new triangle.
  auto moved = [&](uint32_t e) {
    const uint32_t t = e / 3;
    return 3 * new_of_old[t] + (e % 3 + 3 - turn[t]) % 3;
  };
  std::vector<uint32_t> origin(origin_.size()), twin(twin_.size());
  ParallelFor(0, nt, [&](size_t t) {
    for (uint32_t k = 0; k < 3; ++k) {
      const uint32_t e = static_cast<uint32_t>(3 * t + k);
      const uint32_t to = moved(e);
      origin[to] = origin_[e];
      twin[to] = moved(twin_[e]);
    }
  });
  origin_ = std::move(origin);
  twin_ = std::move(twin);
}

void Mesh::UpdateVertexEdgesAfterFlip(uint32_t e) {
  stamp_.Touch();
  const uint32_t f = twin_[e];
  for (uint32_t h : {e, Next(e), Prev(e), f, Next(f), Prev(f)}) {
    const uint32_t v = origin_[h];
    if (v != kInfiniteVertex) vertex_edge_[v] = h;
  }
}

uint32_t Mesh::AllocateTriangle() {
  stamp_.Touch();
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
  stamp_.Touch();
  for (uint32_t e = 3 * t; e < 3 * t + 3; ++e) {
    origin_[e] = kNoVertex;
    twin_[e] = kNoEdge;
  }
  free_.push_back(t);
}

void Mesh::Compact() {
  stamp_.Touch();
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
