// Half-edge triangle mesh (topology only) in structure-of-arrays form.
//
// Layout (all indices 32-bit):
//   * Triangle t owns half-edges 3t, 3t+1, 3t+2 in counter-clockwise order,
//     so triangle -> half-edge is implicit (3t) and Next/Prev are arithmetic.
//   * origin[e]       vertex at the start of half-edge e. The vertex opposite
//                     e in its own triangle is origin[Prev(e)], and the vertex
//                     across e (the one the Delaunay test needs) is
//                     origin[Prev(twin[e])]: one lookup once twin is loaded.
//   * twin[e]         the oppositely directed half-edge of the neighbour.
//   * vertex_edge[v]  one half-edge leaving v (kNoEdge for vertices that are
//                     not in the mesh, e.g. hidden duplicates).
//   * kInfiniteVertex closes the mesh: every hull edge a->b has a "ghost"
//                     triangle (b, a, inf) on its outer side, so the mesh is a
//                     closed sphere and every edge has two triangles.
//
/* Flip of the edge a-b shared by t1 = (a, b, c) and t2 = (b, a, d):

           c                         c
         /   \                     / | \
    ep /  t1   \ en           en' /  |  \ fp'
      /    e    \                /   |   \
     a --------- b    ==>       a  e | f  b
      \    f    /                \   |   /
    fn \  t2   / fp           ep' \  |  / fn'
         \   /                     \ | /
           d                         d
   (x' = the slot that holds the edge after the flip)
*/
//   t1 becomes (d, c, a): e = d->c, Next(e) = c->a, Prev(e) = a->d.
//   t2 becomes (c, d, b): f = c->d, Next(f) = d->b, Prev(f) = b->c.
//   The outer half-edges keep their neighbours; only the twin links of the
//   four outer edges are rewritten. vertex_edge is not touched by a flip
//   (callers refresh it after a batch; see Mesh::RebuildVertexEdges), which
//   keeps concurrent flips of non-adjacent triangle pairs race-free.
#ifndef KINETRI_CORE_MESH_H_
#define KINETRI_CORE_MESH_H_

#include <atomic>
#include <cstddef>
#include <cstdint>
#include <vector>

#include "core/hd.h"

namespace kinetri::core {

inline constexpr uint32_t kNoEdge = 0xFFFFFFFFu;
inline constexpr uint32_t kNoVertex = 0xFFFFFFFFu;
inline constexpr uint32_t kInfiniteVertex = 0xFFFFFFFEu;

KINETRI_HD inline uint32_t Next(uint32_t e) {
  return (e % 3 == 2) ? e - 2 : e + 1;
}
KINETRI_HD inline uint32_t Prev(uint32_t e) {
  return (e % 3 == 0) ? e + 2 : e - 1;
}
KINETRI_HD inline uint32_t TriangleOf(uint32_t e) { return e / 3; }

// Non-owning, trivially copyable view: what per-element kernels receive.
struct MeshView {
  uint32_t* origin = nullptr;
  uint32_t* twin = nullptr;
  uint32_t num_half_edges = 0;

  KINETRI_HD uint32_t Dest(uint32_t e) const { return origin[Next(e)]; }
  // Vertex of e's own triangle that is not on e.
  KINETRI_HD uint32_t Apex(uint32_t e) const { return origin[Prev(e)]; }
  // Vertex across e (apex of the twin's triangle).
  KINETRI_HD uint32_t Across(uint32_t e) const { return origin[Prev(twin[e])]; }
  // A triangle slot released by vertex removal (origin == kNoVertex).
  KINETRI_HD bool IsFree(uint32_t t) const {
    return origin[3 * t] == kNoVertex;
  }
  KINETRI_HD bool IsGhost(uint32_t t) const {
    return origin[3 * t] == kInfiniteVertex ||
           origin[3 * t + 1] == kInfiniteVertex ||
           origin[3 * t + 2] == kInfiniteVertex;
  }

  // Flips edge e (see the drawing above). The caller guarantees that no
  // other flip touches the two triangles or their four neighbours.
  KINETRI_HD void Flip(uint32_t e) const {
    const uint32_t f = twin[e];
    const uint32_t en = Next(e), ep = Prev(e);
    const uint32_t fn = Next(f), fp = Prev(f);
    const uint32_t a = origin[e], b = origin[f];
    const uint32_t c = origin[ep], d = origin[fp];
    const uint32_t tw_en = twin[en], tw_ep = twin[ep];
    const uint32_t tw_fn = twin[fn], tw_fp = twin[fp];
    // t1 = (d, c, a)
    origin[e] = d;
    origin[en] = c;
    origin[ep] = a;
    twin[en] = tw_ep;
    twin[tw_ep] = en;
    twin[ep] = tw_fn;
    twin[tw_fn] = ep;
    // t2 = (c, d, b)
    origin[f] = c;
    origin[fn] = d;
    origin[fp] = b;
    twin[fn] = tw_fp;
    twin[tw_fp] = fn;
    twin[fp] = tw_en;
    twin[tw_en] = fp;
  }
  // Undoes Flip(e) (the same as flipping e three more times, in one).
  KINETRI_HD void Unflip(uint32_t e) const {
    const uint32_t f = twin[e];
    const uint32_t en = Next(e), ep = Prev(e);
    const uint32_t fn = Next(f), fp = Prev(f);
    const uint32_t d = origin[e], c = origin[en], a = origin[ep];
    const uint32_t b = origin[fp];
    const uint32_t tw_ep = twin[en], tw_fn = twin[ep];
    const uint32_t tw_fp = twin[fn], tw_en = twin[fp];
    origin[e] = a;
    origin[en] = b;
    origin[ep] = c;
    origin[f] = b;
    origin[fn] = a;
    origin[fp] = d;
    twin[en] = tw_en;
    twin[tw_en] = en;
    twin[ep] = tw_ep;
    twin[tw_ep] = ep;
    twin[fn] = tw_fn;
    twin[tw_fn] = fn;
    twin[fp] = tw_fp;
    twin[tw_fp] = fp;
  }
};

// Owning mesh. Vertices are 0..num_vertices-1 plus kInfiniteVertex.
class Mesh {
 public:
  Mesh() = default;

  // kAsGiven keeps the triangles in their slots; kCanonical sorts them as
  // SortTrianglesByVertex does.
  enum class Layout { kAsGiven, kCanonical };

  // Builds from counter-clockwise triangles (vertex triples, ghosts use
  // kInfiniteVertex) and the twin of each half-edge.
  Mesh(uint32_t num_vertices, std::vector<uint32_t> origin,
       std::vector<uint32_t> twin, Layout layout = Layout::kAsGiven);

  // A view that may write: the mesh's content_version() changes.
  MeshView view() {
    stamp_.Touch();
    return MeshView{origin_.data(), twin_.data(),
                    static_cast<uint32_t>(origin_.size())};
  }
  // The same view for reading only: writing through it, which the type
  // does not prevent, would go unseen by content_version().
  MeshView view() const {
    return MeshView{const_cast<uint32_t*>(origin_.data()),
                    const_cast<uint32_t*>(twin_.data()),
                    static_cast<uint32_t>(origin_.size())};
  }

  uint32_t num_vertices() const { return num_vertices_; }
  uint32_t num_half_edges() const {
    return static_cast<uint32_t>(origin_.size());
  }
  uint32_t num_triangles() const { return num_half_edges() / 3; }
  const std::vector<uint32_t>& origin() const { return origin_; }
  const std::vector<uint32_t>& twin() const { return twin_; }
  const std::vector<uint32_t>& vertex_edge() const { return vertex_edge_; }
  std::vector<uint32_t>& mutable_vertex_edge() {
    stamp_.Touch();
    return vertex_edge_;
  }

  // A number naming the mesh's contents (ContentStamp below): equal numbers,
  // equal meshes. Every non-const member renews it, view() included, so a
  // view taken before a call of this must not write after it (take a new
  // one). The device executor skips its pass over the host mesh while the
  // number is the one its copy was made from.
  uint64_t content_version() const { return stamp_.number(); }

  // Sets one half-edge's origin and twin (the device executor applies the
  // half-edges an attempt changed this way; with mutable_vertex_edge(), for
  // the vertices).
  void SetHalfEdge(uint32_t e, uint32_t origin, uint32_t twin) {
    stamp_.Touch();
    origin_[e] = origin;
    twin_[e] = twin;
  }

  // Swaps the arrays with a copy made elsewhere (the device executor's
  // download, which keeps the old ones for its next download): same
  // number of vertices and half-edges, no free slots added.
  void SwapArrays(std::vector<uint32_t>* origin, std::vector<uint32_t>* twin,
                  std::vector<uint32_t>* vertex_edge);

  // After Flip(e): points vertex_edge of the four quad vertices at
  // half-edges that now leave them (call serially: deterministic).
  void UpdateVertexEdgesAfterFlip(uint32_t e);

  // Triangle slots: removal frees two, insertion takes two. Allocate reuses
  // the most recently freed slot or appends (invalidating views).
  uint32_t AllocateTriangle();
  void FreeTriangle(uint32_t t);
  bool has_free_triangles() const { return !free_.empty(); }
  size_t num_free_triangles() const { return free_.size(); }
  // Undoes the FreeTriangle calls made since there were `count` free slots
  // (the caller restores their contents).
  void TakeBackFreed(size_t count) {
    stamp_.Touch();
    free_.resize(count);
  }
  // Moves the last triangles into free slots so that none remain.
  void Compact();

  // vertex_edge[v] = smallest half-edge leaving v (deterministic), in
  // parallel. Vertices with no edge get kNoEdge.
  void RebuildVertexEdges();

  // A 64-bit fingerprint of origin, twin and vertex_edge (each entry mixed
  // with its index into two 32-bit sums, in parallel: the sums do not
  // depend on the order). Equal meshes give equal fingerprints; one
  // changed entry always changes it, several but for about a 2^-64
  // chance. The device executor checks by it that the host mesh is still
  // the copy it keeps. A pass over the arrays (52 MB at 1M points).
  uint64_t Fingerprint() const;
  // The fingerprint in parts: the two sums of each array (0 origin, 1 twin,
  // 2 vertex_edge). A caller that changes known entries follows the
  // fingerprint with Change, without a pass (the device executor, as it
  // applies an attempt's changes).
  struct FingerprintSums {
    uint32_t s0[3] = {0, 0, 0};
    uint32_t s1[3] = {0, 0, 0};
    // Entry `index` of `array` changes from `from` to `to`.
    void Change(int array, uint32_t index, uint32_t from, uint32_t to);
    uint64_t Combine() const;  // == Fingerprint() of the mesh summed
  };
  FingerprintSums FingerprintParts() const;

  // Renames vertices: new id = new_of_old[old]. kInfiniteVertex is kept.
  void RenumberVertices(const std::vector<uint32_t>& new_of_old);
  // Changes the number of vertices: new ones are in no triangle yet
  // (vertex_edge kNoEdge); vertices that go must be in none.
  void ResizeVertices(uint32_t num_vertices);
  // Renames vertex `from` (in the mesh) to `to` (in none): every half-edge
  // leaving it, and its vertex_edge.
  void RelabelVertex(uint32_t from, uint32_t to);

  // Renumbers triangles in the order of their smallest vertex id, so that
  // with spatially ordered vertices the triangles of a neighbourhood sit
  // together in memory, and turns each so that slot 0 holds that vertex.
  // Triangles of the same smallest vertex follow the vertex after it. The
  // layout is canonical: two meshes of the same triangles (built in any
  // order, by any builder) are equal slot for slot afterwards. Free slots
  // must not exist.
  void SortTrianglesByVertex();

  bool empty() const { return origin_.empty(); }

 private:
  // SortTrianglesByVertex without the vertex_edge refresh.
  void SortTriangles();

  // Names the contents of an owning object by a number unique in the
  // process, renewed after any access that may write: two objects with the
  // same number() have equal contents. Touch() at every such access (cheap
  // where it repeats: a load once the stamp is marked); number() gives the
  // next number of the process when something touched it since the last
  // call. A copy keeps the number (its contents are equal); a moved-from
  // object is touched (its contents are gone). number() must not run
  // concurrently with a writer of the object.
  class ContentStamp {
   public:
    ContentStamp() = default;
    ContentStamp(const ContentStamp& other) { CopyFrom(other); }
    ContentStamp& operator=(const ContentStamp& other) {
      CopyFrom(other);
      return *this;
    }
    ContentStamp(ContentStamp&& other) noexcept {
      CopyFrom(other);
      other.Touch();
    }
    ContentStamp& operator=(ContentStamp&& other) noexcept {
      if (this != &other) {
        CopyFrom(other);
        other.Touch();
      }
      return *this;
    }
    void Touch() {
      if (!touched_.load(std::memory_order_relaxed)) {
        touched_.store(true, std::memory_order_relaxed);
      }
    }
    uint64_t number() const;

   private:
    void CopyFrom(const ContentStamp& other) {
      number_.store(other.number_.load(std::memory_order_relaxed),
                    std::memory_order_relaxed);
      touched_.store(other.touched_.load(std::memory_order_relaxed),
                     std::memory_order_relaxed);
    }
    mutable std::atomic<uint64_t> number_{0};
    mutable std::atomic<bool> touched_{true};
  };

  uint32_t num_vertices_ = 0;
  std::vector<uint32_t> origin_;
  std::vector<uint32_t> twin_;
  std::vector<uint32_t> vertex_edge_;
  std::vector<uint32_t> free_;
  ContentStamp stamp_;
};

}  // namespace kinetri::core

#endif  // KINETRI_CORE_MESH_H_
