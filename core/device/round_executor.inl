// The device executor's source, written once and compiled twice (see
// core/device/device_executor.h): included by cuda_backend.cu (nvcc, Thrust's
// CUDA system) and emulated_backend.cc (host compiler, Thrust's TBB system).
// The including file defines KINETRI_DEVICE_NS (the namespace of its build)
// and, for the emulated build, THRUST_CUB_WRAPPED_NAMESPACE so the two
// Thrust instantiations never share a symbol.
//
// The schedule is the round executor's (core/kinetic.cc), step for step:
// worklists are sorted and unique, a round's winners hold the smallest edge
// id on all six triangles of their footprint (and a fixing flip on the
// vertices it joins), the next worklist is built from the same elements. So
// for the same input the device mesh equals the round executor's, triangle
// numbering included. Only Thrust algorithms over the functors below run on
// the device; the host drives the rounds. It waits for the device only where
// it reads a result (a worklist's size): on the CUDA system every other
// algorithm returns at once (core/device/scratch_pool.inl), so a legalizing
// round waits twice and a fixing round five times; flip counts stay on the
// device until the attempt ends. Once a legalizing worklist is short, its
// rounds run in a device loop (LoopControl, "device loop" below): their
// sizes stay in device memory and the host reads one word per
// rounds_per_check rounds.
#ifndef KINETRI_DEVICE_NS
#error "define KINETRI_DEVICE_NS before including round_executor.inl"
#endif

#include <thrust/copy.h>
#include <thrust/count.h>
#include <thrust/device_vector.h>
#include <thrust/fill.h>
#include <thrust/for_each.h>
#include <thrust/gather.h>
#include <thrust/iterator/counting_iterator.h>
#include <thrust/merge.h>
#include <thrust/remove.h>
#include <thrust/scatter.h>
#include <thrust/sort.h>
#include <thrust/transform.h>
#include <thrust/transform_reduce.h>
#include <thrust/unique.h>

#include <algorithm>
#include <chrono>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <future>
#include <memory>
#include <mutex>
#include <new>
#include <stdexcept>
#include <type_traits>
#include <utility>
#include <vector>

#include "absl/strings/str_cat.h"
#include "core/device/atomic.h"
#include "core/device/changed_positions.h"
#include "core/device/checks.h"
#include "core/device/device_executor.h"
#include "core/device/device_queries.inl"
#include "core/device/profile.h"
#include "core/device/scratch_pool.inl"
#include "core/device/staging.inl"
#include "core/flip_rules.h"
#include "core/mesh.h"
#include "core/vec2.h"

namespace kinetri::core::device {
namespace KINETRI_DEVICE_NS {
namespace {

namespace thr = THRUST_NS_QUALIFIER;
using U32Vector = thr::device_vector<uint32_t>;
using Count = thr::counting_iterator<uint32_t>;

// Everything a functor carries to the device is a plain view.
static_assert(std::is_trivially_copyable_v<MeshView>);
static_assert(std::is_trivially_copyable_v<Vec2>);
static_assert(std::is_trivially_copyable_v<rules::FixProposal>);

template <typename T>
T* Raw(thr::device_vector<T>& v) {
  return thr::raw_pointer_cast(v.data());
}

KINETRI_HD inline uint32_t Canonical(const MeshView& m, uint32_t e) {
  const uint32_t f = m.twin[e];
  return e < f ? e : f;
}

struct TriangleBad {
  MeshView m;
  const Vec2* pos;
  KINETRI_HD bool operator()(uint32_t t) const {
    return !rules::TriangleOk(m, pos, t);
  }
};

struct ProposeFix {
  MeshView m;
  const Vec2* pos;
  KINETRI_HD rules::FixProposal operator()(uint32_t t) const {
    rules::FixProposal p = rules::ProposeFixFlip(m, pos, t);
    if (p.edge != kNoEdge) p.edge = Canonical(m, p.edge);
    return p;
  }
};

struct NoFlip {
  KINETRI_HD bool operator()(const rules::FixProposal& p) const {
    return p.edge == kNoEdge;
  }
};
struct IsSet {
  KINETRI_HD bool operator()(uint8_t f) const { return f != 0; }
};
struct IsClear {
  KINETRI_HD bool operator()(uint8_t f) const { return f == 0; }
};
struct EdgeLess {
  KINETRI_HD bool operator()(const rules::FixProposal& a,
                             const rules::FixProposal& b) const {
    return a.edge < b.edge;
  }
};
struct EdgeEqual {
  KINETRI_HD bool operator()(const rules::FixProposal& a,
                             const rules::FixProposal& b) const {
    return a.edge == b.edge;
  }
};

// Splits proposals into edges and the (two) vertices each one joins.
struct SplitProposal {
  const rules::FixProposal* props;
  uint32_t* edges;
  uint32_t* joins;
  uint32_t* kinds;
  KINETRI_HD void operator()(uint32_t i) const {
    edges[i] = props[i].edge;
    joins[2 * i] = props[i].new_u;
    joins[2 * i + 1] = props[i].new_w;
    kinds[i] = props[i].kind;
  }
};

// Claims: every proposal writes its edge id into the six triangles of its
// footprint (and its joined vertices) with an atomic min; a proposal wins
// when it holds all of them; then every claim is reset.
struct Claims {
  MeshView m;
  const uint32_t* edges;
  const uint32_t* joins;  // two per proposal, or null
  uint32_t* tri_claim;
  uint32_t* vert_claim;
  uint32_t num_vertices;

  KINETRI_HD void Claim(uint32_t i) const {
    uint32_t fp[6];
    rules::FlipFootprint(m, edges[i], fp);
    for (uint32_t t : fp) ClaimMin(&tri_claim[t], edges[i]);
    if (joins != nullptr) {
      for (int k = 0; k < 2; ++k) {
        const uint32_t v = joins[2 * i + k];
        if (v < num_vertices) ClaimMin(&vert_claim[v], edges[i]);
      }
    }
  }
  KINETRI_HD bool Won(uint32_t i) const {
    uint32_t fp[6];
    rules::FlipFootprint(m, edges[i], fp);
    for (uint32_t t : fp) {
      if (tri_claim[t] != edges[i]) return false;
    }
    if (joins != nullptr) {
      for (int k = 0; k < 2; ++k) {
        const uint32_t v = joins[2 * i + k];
        if (v < num_vertices && vert_claim[v] != edges[i]) return false;
      }
    }
    return true;
  }
  KINETRI_HD void Release(uint32_t i) const {
    uint32_t fp[6];
    rules::FlipFootprint(m, edges[i], fp);
    // (Several proposals may reset the same slot at once: relaxed atomic
    // stores.)
    for (uint32_t t : fp) StoreRelaxed(&tri_claim[t], kNoEdge);
    if (joins != nullptr) {
      for (int k = 0; k < 2; ++k) {
        const uint32_t v = joins[2 * i + k];
        if (v < num_vertices) StoreRelaxed(&vert_claim[v], kNoEdge);
      }
    }
  }
};
struct ClaimOp {
  Claims c;
  KINETRI_HD void operator()(uint32_t i) const { c.Claim(i); }
};
struct WonOp {
  Claims c;
  KINETRI_HD bool operator()(uint32_t i) const { return c.Won(i); }
};
struct ReleaseOp {
  Claims c;
  KINETRI_HD void operator()(uint32_t i) const { c.Release(i); }
};

// Footprint of winner w (six triangles) written at out + 6 * position, and
// its two own triangles at touched + 2 * position (if non-null).
struct WriteFootprint {
  MeshView m;
  const uint32_t* winner_edges;
  uint32_t* out;
  uint32_t* touched;
  KINETRI_HD void operator()(uint32_t i) const {
    uint32_t fp[6];
    rules::FlipFootprint(m, winner_edges[i], fp);
    for (int k = 0; k < 6; ++k) out[6 * i + k] = fp[k];
    if (touched != nullptr) {
      touched[2 * i] = fp[0];
      touched[2 * i + 1] = fp[1];
    }
  }
};

struct FlipOp {
  MeshView m;
  KINETRI_HD void operator()(uint32_t e) const { m.Flip(e); }
};

struct IsCanonical {
  MeshView m;
  KINETRI_HD bool operator()(uint32_t e) const { return e < m.twin[e]; }
};

// What a successful attempt changed against the base (the host's mesh):
// each half-edge whose origin or twin differs (index e, values origin and
// twin) and each vertex whose vertex_edge differs (index ne + v, values
// vertex_edge and 0), appended in any order while they fit in `cap`; the
// count goes on past it (the host then downloads the whole arrays).
struct AppendChanges {
  const uint32_t* origin;
  const uint32_t* twin;
  const uint32_t* vertex_edge;
  const uint32_t* base_origin;
  const uint32_t* base_twin;
  const uint32_t* base_vertex_edge;
  uint32_t ne;
  uint32_t cap;
  uint32_t* count;
  uint32_t* index;
  uint32_t* value;  // two per entry
  KINETRI_HD void operator()(uint32_t i) const {
    uint32_t a, b = 0;
    if (i < ne) {
      a = origin[i];
      b = twin[i];
      if (a == base_origin[i] && b == base_twin[i]) return;
    } else {
      a = vertex_edge[i - ne];
      if (a == base_vertex_edge[i - ne]) return;
    }
    const uint32_t k = FetchAdd(count, 1u);
    if (k >= cap) return;
    index[k] = i;
    value[2 * k] = a;
    value[2 * k + 1] = b;
  }
};

// The host's changes into the base (ChangedOnHost): entry index[k] (a
// half-edge's origin and twin below ne, else vertex ne - index's
// vertex_edge) takes value[2k], value[2k + 1], and value keeps the entry's
// old contents in their place (indices are distinct).
struct SwapInHostChanges {
  uint32_t* origin;
  uint32_t* twin;
  uint32_t* vertex_edge;
  uint32_t ne;
  const uint32_t* index;
  uint32_t* value;
  KINETRI_HD void operator()(uint32_t k) const {
    const uint32_t i = index[k];
    const uint32_t a = value[2 * k];
    if (i < ne) {
      const uint32_t b = value[2 * k + 1];
      value[2 * k] = origin[i];
      value[2 * k + 1] = twin[i];
      origin[i] = a;
      twin[i] = b;
    } else {
      value[2 * k] = vertex_edge[i - ne];
      vertex_edge[i - ne] = a;
    }
  }
};

// The three canonical edges of each seed triangle.
struct TriangleEdges {
  MeshView m;
  const uint32_t* triangles;
  uint32_t* out;
  KINETRI_HD void operator()(uint32_t i) const {
    const uint32_t t = triangles[i];
    for (uint32_t k = 0; k < 3; ++k) out[3 * i + k] = Canonical(m, 3 * t + k);
  }
};

// Flip counts kept on the device during an attempt (counters_): one word
// per fix kind (rules::FixProposal::kind, 1..3) and one for Delaunay flips.
constexpr uint32_t kDelaunay = 4;
constexpr uint32_t kCounters = 5;

// Counts the flip kind of each fixing winner (winner indices in the range).
struct CountKinds {
  const uint32_t* kinds;
  uint32_t* counters;
  KINETRI_HD void operator()(uint32_t i) const {
    AddRelaxed(&counters[kinds[i]], 1);
  }
};

// Legalizing: candidate i of a round is the edge edges[i], flagged in
// flags[i] once the claims are decided (1: it won).
struct Won {
  const uint32_t* edges;
  const uint8_t* flags;
};

// flags[i]: whether work[i] is a candidate of this round, i.e. known to be
// illegal (the mark is cleared: it is used once) or tested illegal now.
struct TestEdge {
  MeshView m;
  const Vec2* pos;
  const uint32_t* work;
  uint8_t* known;
  uint8_t* flags;
  KINETRI_HD void operator()(uint32_t i) const {
    const uint32_t e = work[i];
    if (e == kNoEdge) {
      flags[i] = 0;
    } else if (known[e] != 0) {
      known[e] = 0;
      flags[i] = 1;
    } else {
      flags[i] = rules::IsIllegal(m, pos, e) ? 1 : 0;
    }
  }
};

// Clears the known marks of the entries of a worklist (a stopped attempt).
struct ForgetKnown {
  uint8_t* known;
  KINETRI_HD void operator()(uint32_t e) const {
    if (e != kNoEdge) known[e] = 0;
  }
};

// flags[i] = whether candidate i won its claims; winners are counted.
struct DecideOp {
  Claims c;
  uint8_t* flags;
  uint32_t* flips;
  KINETRI_HD void operator()(uint32_t i) const {
    const bool won = c.Won(i);
    flags[i] = won ? 1 : 0;
    if (won) AddRelaxed(flips, 1);
  }
};

struct FlipWonOp {
  MeshView m;
  Won won;
  KINETRI_HD void operator()(uint32_t i) const {
    if (won.flags[i]) m.Flip(won.edges[i]);
  }
};

// Marks (value 0) or unmarks (kNoEdge) in tri_claim the two triangles of
// each winner (flips keep triangle ids; claims are released then).
struct MarkWonTriangles {
  MeshView m;
  Won won;
  uint32_t* tri_claim;
  uint32_t value;
  KINETRI_HD void operator()(uint32_t i) const {
    if (!won.flags[i]) return;
    const uint32_t e = won.edges[i];
    tri_claim[TriangleOf(e)] = value;
    tri_claim[TriangleOf(m.twin[e])] = value;
  }
};

// The next worklist, four entries per candidate at out + 4 i: a winner's
// four outer edges (after its flip), or a loser whose triangles did not
// flip (its four vertices did not change: still illegal, marked known),
// or nothing; kNoEdge fills the rest.
struct NextWork {
  MeshView m;
  Won won;
  const uint32_t* tri_claim;  // 0 on the winners' triangles
  uint8_t* known;
  uint32_t* out;
  KINETRI_HD void operator()(uint32_t i) const {
    const uint32_t e = won.edges[i];
    uint32_t* o = out + 4 * size_t{i};
    if (won.flags[i]) {
      const uint32_t f = m.twin[e];
      o[0] = Canonical(m, Next(e));
      o[1] = Canonical(m, Prev(e));
      o[2] = Canonical(m, Next(f));
      o[3] = Canonical(m, Prev(f));
      return;
    }
    const bool unchanged =
        tri_claim[TriangleOf(e)] != 0 && tri_claim[TriangleOf(m.twin[e])] != 0;
    if (unchanged) known[e] = 1;
    o[0] = unchanged ? e : kNoEdge;
    o[1] = o[2] = o[3] = kNoEdge;
  }
};

// Hull winding as a reduction over the ghost triangles (the ghosts form
// one cycle around the infinite vertex, so counting them equals walking
// them): it winds once iff there are at least three, each has a spoke with
// finite hull neighbours, and exactly one hull vertex is topmost locally.
struct HullCount {
  uint32_t ghosts = 0;
  uint32_t tops = 0;
  uint32_t bad = 0;
};
struct HullOf {
  MeshView m;
  const Vec2* pos;
  KINETRI_HD HullCount operator()(uint32_t t) const {
    HullCount c;
    if (m.IsFree(t) || !m.IsGhost(t)) return c;
    c.ghosts = 1;
    const uint32_t s = rules::SpokeOf(m, t);
    if (s == kNoEdge) {
      c.bad = 1;
      return c;
    }
    const uint32_t a = m.origin[s];
    const uint32_t pv = rules::SpokePrev(m, s), nx = rules::SpokeNext(m, s);
    if (pv == kInfiniteVertex || nx == kInfiniteVertex) {
      c.bad = 1;
      return c;
    }
    auto above = [&](uint32_t u, uint32_t v) {
      const Vec2 &x = pos[u], &y = pos[v];
      return x.y > y.y || (x.y == y.y && x.x > y.x);
    };
    c.tops = above(a, pv) && above(a, nx) ? 1 : 0;
    return c;
  }
};
struct HullPlus {
  KINETRI_HD HullCount operator()(const HullCount& a,
                                  const HullCount& b) const {
    HullCount c;
    c.ghosts = a.ghosts + b.ghosts;
    c.tops = a.tops + b.tops;
    c.bad = a.bad + b.bad;
    return c;
  }
};

struct IsGhostTriangle {
  MeshView m;
  KINETRI_HD bool operator()(uint32_t t) const {
    return !m.IsFree(t) && m.IsGhost(t);
  }
};

// Corners of the given triangles (kInfiniteVertex reported as kNoVertex).
struct Corners {
  MeshView m;
  const uint32_t* triangles;
  uint32_t* out;
  KINETRI_HD void operator()(uint32_t i) const {
    const uint32_t t = triangles[i];
    for (uint32_t k = 0; k < 3; ++k) {
      const uint32_t v = m.origin[3 * t + k];
      out[3 * i + k] = v == kInfiniteVertex ? kNoVertex : v;
    }
  }
};

// Hold-back, core/kinetic.cc's HoldCulprits step for step: the culprits of
// stalled triangle bad[i] (rules::Culprits) as keys vertex << 32 | a
// half-edge leaving it; kNoCulprit where there are fewer than three.
constexpr uint64_t kNoCulprit = ~uint64_t{0};
struct MovedSince {
  const Vec2* pos;
  const Vec2* from;
  KINETRI_HD bool operator()(uint32_t u) const { return pos[u] != from[u]; }
};
struct FindCulprits {
  MeshView m;
  const Vec2* pos;
  const Vec2* from;
  const uint32_t* bad;
  uint64_t* keys;
  KINETRI_HD void operator()(uint32_t i) const {
    uint32_t v[3], e[3];
    const int n =
        rules::Culprits(m, pos, from, bad[i], MovedSince{pos, from}, v, e);
    for (int k = 0; k < 3; ++k) {
      keys[3 * i + k] =
          k < n ? (uint64_t{v[k]} << 32) | uint64_t{e[k]} : kNoCulprit;
    }
  }
};
struct IsNoCulprit {
  KINETRI_HD bool operator()(uint64_t key) const { return key == kNoCulprit; }
};
struct SameCulprit {
  KINETRI_HD bool operator()(uint64_t a, uint64_t b) const {
    return (a >> 32) == (b >> 32);
  }
};
// Culprit i goes back to its old position and is listed in held.
struct HoldCulprit {
  const uint64_t* keys;
  Vec2* pos;
  const Vec2* from;
  uint32_t* held;
  KINETRI_HD void operator()(uint32_t i) const {
    const uint32_t v = static_cast<uint32_t>(keys[i] >> 32);
    pos[v] = from[v];
    held[i] = v;
  }
};
// The triangles whose validity reads culprit i (rules::
// ForEachStarAndHullRing): how many, then written from offset[i].
struct CulpritStarSize {
  MeshView m;
  const uint64_t* keys;
  uint32_t num_keys;  // size[num_keys] = 0
  uint32_t* size;
  KINETRI_HD void operator()(uint32_t i) const {
    uint32_t n = 0;
    if (i == num_keys) {
      size[i] = 0;
      return;
    }
    rules::ForEachStarAndHullRing(m, static_cast<uint32_t>(keys[i]),
                                  [&n](uint32_t) { ++n; });
    size[i] = n;
  }
};
struct WriteCulpritStar {
  MeshView m;
  const uint64_t* keys;
  const uint32_t* offset;
  uint32_t* out;
  KINETRI_HD void operator()(uint32_t i) const {
    uint32_t* at = out + offset[i];
    rules::ForEachStarAndHullRing(m, static_cast<uint32_t>(keys[i]),
                                  [&at](uint32_t t) { *at++ = t; });
  }
};
static_assert(std::is_trivially_copyable_v<FindCulprits>);
static_assert(std::is_trivially_copyable_v<HoldCulprit>);
static_assert(std::is_trivially_copyable_v<CulpritStarSize>);
static_assert(std::is_trivially_copyable_v<WriteCulpritStar>);

// vertex_edge after a round's flips, exactly as the host sets it
// (Mesh::UpdateVertexEdgesAfterFlip for each winner in ascending edge
// order): a quad corner gets the half-edge of the last winner that touches
// it. Pass 1 marks that winner (atomic max of its edge id + 1, so the order
// of the entries does not matter), pass 2 writes, pass 3 clears the marks.
struct QuadCorners {
  MeshView m;
  const uint32_t* winner_edges;
  uint32_t* vertex_edge;
  uint32_t* last;
  // Entries that won (null: every entry is a winner); the others are
  // skipped.
  const uint8_t* won = nullptr;
  KINETRI_HD bool Skip(uint32_t i) const { return won != nullptr && !won[i]; }
  // The six half-edges in UpdateVertexEdgesAfterFlip's order.
  KINETRI_HD void Edges(uint32_t i, uint32_t h[6]) const {
    const uint32_t e = winner_edges[i], f = m.twin[e];
    h[0] = e;
    h[1] = Next(e);
    h[2] = Prev(e);
    h[3] = f;
    h[4] = Next(f);
    h[5] = Prev(f);
  }
};
struct MarkLast {
  QuadCorners q;
  KINETRI_HD void operator()(uint32_t i) const {
    if (q.Skip(i)) return;
    uint32_t h[6];
    q.Edges(i, h);
    for (uint32_t k = 0; k < 6; ++k) {
      const uint32_t v = q.m.origin[h[k]];
      if (v != kInfiniteVertex) ClaimMax(&q.last[v], q.winner_edges[i] + 1);
    }
  }
};
struct WriteVertexEdges {
  QuadCorners q;
  KINETRI_HD void operator()(uint32_t i) const {
    if (q.Skip(i)) return;
    uint32_t h[6];
    q.Edges(i, h);
    const uint32_t mark = q.winner_edges[i] + 1;
    for (uint32_t k = 0; k < 6; ++k) {  // later entries win, as on the host
      const uint32_t v = q.m.origin[h[k]];
      if (v != kInfiniteVertex && q.last[v] == mark) q.vertex_edge[v] = h[k];
    }
  }
};
struct ClearLast {
  QuadCorners q;
  KINETRI_HD void operator()(uint32_t i) const {
    if (q.Skip(i)) return;
    uint32_t h[6];
    q.Edges(i, h);
    for (uint32_t k = 0; k < 6; ++k) {
      const uint32_t v = q.m.origin[h[k]];
      if (v != kInfiniteVertex) StoreRelaxed(&q.last[v], 0);
    }
  }
};

// The device loop (LoopControl): legalizing rounds whose sizes live in
// device memory. Two lists alternate as a round's worklist and the next;
// state words say which is current, their sizes, whether the loop runs,
// and what the running round found. Every algorithm of a round is launched
// over the loop's capacity and does nothing past the current size or once
// the loop has stopped.
enum LoopWord : uint32_t {
  kLoopCur,     // which list is the current worklist (0 or 1)
  kLoopCount0,  // entries of list 0
  kLoopCount1,  // entries of list 1
  kLoopStatus,  // LoopStatus
  kLoopCands,   // candidates of the running round
  kLoopRounds,  // rounds with candidates run since the loop started
  kLoopLost,    // set if an append found its list full (never expected)
  kLoopWords
};
enum LoopStatus : uint32_t {
  kLoopRunning,
  kLoopDone,      // a round found no candidate: the mesh is Delaunay
  kLoopOverflow,  // the next worklist is longer than the capacity
  kLoopBroken,    // an append found its list full: the attempt fails
};

struct Loop {
  uint32_t* state;
  uint32_t* list0;
  uint32_t* list1;
  uint32_t list_size;  // of each list: no worklist is longer (see NextWork)
  KINETRI_HD uint32_t Cur() const { return state[kLoopCur]; }
  KINETRI_HD const uint32_t* In() const { return Cur() != 0 ? list1 : list0; }
  KINETRI_HD bool Active(uint32_t i) const {
    return state[kLoopStatus] == kLoopRunning && i < state[kLoopCount0 + Cur()];
  }
  // Appends canonical edge e to the next worklist unless it is there:
  // queued holds one bit per half-edge, set while the edge waits in the next
  // list (a round's test clears the bits of its own list).
  KINETRI_HD void Push(uint32_t* queued, uint32_t e) const {
    const uint32_t bit = 1u << (e & 31);
    if ((FetchOr(&queued[e >> 5], bit) & bit) != 0) return;
    const uint32_t cur = Cur();
    const uint32_t at = FetchAdd(&state[kLoopCount0 + (cur ^ 1)], 1);
    // A list holds every canonical edge at most once: `at` < list_size.
    if (at < list_size) {
      (cur != 0 ? list0 : list1)[at] = e;
    } else {
      StoreRelaxed(&state[kLoopLost], 1);
    }
  }
};

// One phase of a device-loop round for worklist entry i; the phases are
// those of a host-driven round (Legalize), over the entries flagged as
// candidates instead of a compacted copy of them.
enum LoopPhase : uint32_t {
  kPhaseClaim,
  kPhaseDecide,
  kPhaseRelease,
  kPhaseFlip,
  kPhaseMarkLast,
  kPhaseWriteVertexEdges,
  kPhaseClearLast,
  kPhaseMarkWon,
  kPhaseNext,
  kPhaseUnmarkWon,
};
// The test phase of a device-loop round (apart from the other phases, so
// that only its kernel carries the exact in-circle's frame and registers):
// whether entry i is a candidate, known to be illegal (the mark is used
// once) or tested illegal now; the entry's queued bit is cleared.
struct LoopTest {
  Loop loop;
  MeshView m;
  const Vec2* pos;
  uint8_t* known;
  uint32_t* queued;
  uint8_t* cand;
  uint8_t* won;
  KINETRI_HD void operator()(uint32_t i) const {
    if (!loop.Active(i)) return;
    const uint32_t e = loop.In()[i];
    won[i] = 0;
    if (e == kNoEdge) {
      cand[i] = 0;
      return;
    }
    ClearBits(&queued[e >> 5], 1u << (e & 31));
    bool c;
    if (known[e] != 0) {
      known[e] = 0;
      c = true;
    } else {
      c = rules::IsIllegal(m, pos, e);
    }
    cand[i] = c ? 1 : 0;
    if (c) AddRelaxed(&loop.state[kLoopCands], 1);
  }
};

// The other phases, for the candidates.
struct LoopRound {
  Loop loop;
  MeshView m;
  uint8_t* known;
  uint32_t* queued;
  uint8_t* cand;  // per entry: a candidate of this round
  uint8_t* won;   // per entry: won its claims
  uint32_t* tri_claim;
  uint32_t* vertex_edge;
  uint32_t* last;
  uint32_t* flips;
  uint32_t phase;
  KINETRI_HD void operator()(uint32_t i) const {
    if (!loop.Active(i)) return;
    const uint32_t* in = loop.In();
    const uint32_t e = in[i];
    if (cand[i] == 0) return;
    const Claims c{m, in, nullptr, tri_claim, nullptr, 0};
    const Won w{in, won};
    const QuadCorners q{m, in, vertex_edge, last, won};
    switch (phase) {
      case kPhaseClaim:
        c.Claim(i);
        break;
      case kPhaseDecide: {
        const bool x = c.Won(i);
        won[i] = x ? 1 : 0;
        if (x) AddRelaxed(flips, 1);
        break;
      }
      case kPhaseRelease:
        c.Release(i);
        break;
      case kPhaseFlip:
        FlipWonOp{m, w}(i);
        break;
      case kPhaseMarkLast:
        MarkLast{q}(i);
        break;
      case kPhaseWriteVertexEdges:
        WriteVertexEdges{q}(i);
        break;
      case kPhaseClearLast:
        ClearLast{q}(i);
        break;
      case kPhaseMarkWon:
        MarkWonTriangles{m, w, tri_claim, 0}(i);
        break;
      case kPhaseNext:
        // As NextWork: a winner's four outer edges, or a loser whose
        // triangles did not flip (marked known).
        if (won[i] != 0) {
          const uint32_t f = m.twin[e];
          loop.Push(queued, Canonical(m, Next(e)));
          loop.Push(queued, Canonical(m, Prev(e)));
          loop.Push(queued, Canonical(m, Next(f)));
          loop.Push(queued, Canonical(m, Prev(f)));
        } else if (tri_claim[TriangleOf(e)] != 0 &&
                   tri_claim[TriangleOf(m.twin[e])] != 0) {
          known[e] = 1;
          loop.Push(queued, e);
        }
        break;
      case kPhaseUnmarkWon:
        MarkWonTriangles{m, w, tri_claim, kNoEdge}(i);
        break;
      default:
        break;
    }
  }
};

static_assert(std::is_trivially_copyable_v<LoopTest>);
static_assert(std::is_trivially_copyable_v<LoopRound>);

// The end of a device-loop round (one element): stops the loop when the
// round had no candidate, else makes the next worklist current, and stops
// it when that is longer than `capacity` (the host goes on).
struct LoopFinish {
  uint32_t* state;
  uint32_t capacity;
  KINETRI_HD void operator()(uint32_t) const {
    if (state[kLoopStatus] != kLoopRunning) return;
    if (state[kLoopLost] != 0) {
      state[kLoopStatus] = kLoopBroken;
      return;
    }
    if (state[kLoopCands] == 0) {
      state[kLoopStatus] = kLoopDone;
      return;
    }
    const uint32_t cur = state[kLoopCur];
    state[kLoopCands] = 0;
    ++state[kLoopRounds];
    state[kLoopCount0 + cur] = 0;
    state[kLoopCur] = cur ^ 1;
    if (state[kLoopCount0 + (cur ^ 1)] > capacity) {
      state[kLoopStatus] = kLoopOverflow;
    }
  }
};

// Starts a loop on list 0 holding n entries (their queued bits set).
struct LoopStart {
  uint32_t* state;
  uint32_t n;
  KINETRI_HD void operator()(uint32_t) const {
    state[kLoopCur] = 0;
    state[kLoopCount0] = n;
    state[kLoopCount1] = 0;
    state[kLoopStatus] = kLoopRunning;
    state[kLoopCands] = 0;
    state[kLoopRounds] = 0;
    state[kLoopLost] = 0;
  }
};

// Clears the queued bit of each edge of a worklist (handed back to the
// host).
struct ClearQueued {
  uint32_t* queued;
  KINETRI_HD void operator()(uint32_t e) const {
    if (e != kNoEdge) ClearBits(&queued[e >> 5], 1u << (e & 31));
  }
};

double Since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0)
      .count();
}

class RoundDeviceExecutor final : public DeviceExecutor {
 public:
  explicit RoundDeviceExecutor(DeviceBackend backend)
      : backend_(backend),
        device_(CurrentDevice()),
        loop_control_(DefaultLoopControl(backend)) {
    queries_.set_faults(&faults_);
#if THRUST_DEVICE_SYSTEM == THRUST_DEVICE_SYSTEM_CUDA
    // The session's own stream. Blocking (not cudaStreamNonBlocking): the
    // device vectors' own operations (resize, assign) run on the default
    // stream and stay in order with it.
    thr::cuda_cub::throw_on_error(
        cudaStreamCreateWithFlags(&stream_, cudaStreamDefault),
        "device executor: creating its stream");
#endif
  }

  DeviceBackend backend() const override { return backend_; }
  void Invalidate() override {
    std::lock_guard<std::mutex> lock(attempt_mu_);
    host_changed_ = true;
    ClearHostChanges();
  }
  void ChangedOnHost(absl::Span<const uint32_t> triangles,
                     absl::Span<const uint32_t> vertices) override {
    std::lock_guard<std::mutex> lock(attempt_mu_);
    if (host_changed_) return;  // the whole mesh goes up anyway
    // More distinct entries than a patch holds (as a download's, an eighth
    // of the mesh): the whole mesh goes up. The lists are made unique when
    // repeats take them over that, so they stay within twice of it.
    const size_t cap = (base_origin_.size() + nv_) / 8;
    auto over = [&] {
      return 3 * host_triangles_.size() + host_vertices_.size() > cap;
    };
    if (3 * triangles.size() + vertices.size() <= cap) {
      host_triangles_.insert(host_triangles_.end(), triangles.begin(),
                             triangles.end());
      host_vertices_.insert(host_vertices_.end(), vertices.begin(),
                            vertices.end());
      if (over()) {
        SortUnique(host_triangles_);
        SortUnique(host_vertices_);
      }
      if (!over()) return;
    }
    host_changed_ = true;
    ClearHostChanges();
    host_triangles_.shrink_to_fit();
    host_vertices_.shrink_to_fit();
  }
  void PositionsWrittenAt(absl::Span<const uint32_t> to,
                          absl::Span<const uint32_t> from) override {
    std::lock_guard<std::mutex> lock(attempt_mu_);
    written_called_ = true;
    // (More than a sparse upload sends: the whole comparison is cheaper.)
    to_written_.Add(to, pos_mirror_.values.size() / 4);
    from_written_.Add(from, from_mirror_.values.size() / 4);
  }
  void set_loop_control(const LoopControl& control) override {
    std::lock_guard<std::mutex> lock(attempt_mu_);
    loop_control_ = control;
    if (loop_control_.rounds_per_check == 0) loop_control_.rounds_per_check = 1;
  }
  LoopControl loop_control() const override {
    std::lock_guard<std::mutex> lock(attempt_mu_);
    return loop_control_;
  }
  void InjectFault(const DeviceFault& fault) override { faults_.Arm(fault); }
  bool fault_armed() const override { return faults_.armed(); }
  uint32_t queries_in_flight() const override { return queries_.in_flight(); }

  uint64_t device_bytes() const override {
    uint64_t words = 0;
    for (const U32Vector* v : {&origin_,      &twin_,        &vertex_edge_,
                               &base_origin_, &base_twin_,   &base_vertex_edge_,
                               &last_,        &tri_claim_,   &vert_claim_,
                               &work_,        &bad_,         &edges_,
                               &joins_,       &kinds_,       &winners_,
                               &win_edges_,   &next_,        &touched_,
                               &seeds_,       &counters_,    &loop_list0_,
                               &loop_list1_,  &loop_state_,  &queued_,
                               &patch_count_, &patch_index_, &patch_value_,
                               &held_,        &change_index_}) {
      words += v->capacity();
    }
    return words * sizeof(uint32_t) + known_.capacity() + flags_.capacity() +
           loop_cand_.capacity() + loop_won_.capacity() +
           (pos_.capacity() + from_.capacity() + change_value_.capacity()) *
               sizeof(Vec2) +
           culprit_keys_.capacity() * sizeof(uint64_t) +
           props_.capacity() * sizeof(rules::FixProposal) + pool_.bytes() +
           queries_.bytes();
  }

  uint64_t host_bytes() const override {
    return (pos_mirror_.values.capacity() + from_mirror_.values.capacity() +
            host_change_value_.capacity()) *
               sizeof(Vec2) +
           (to_written_.entries.capacity() + from_written_.entries.capacity() +
            host_change_index_.capacity() + host_patch_index_.capacity() +
            host_triangles_.capacity() + host_vertices_.capacity() +
            host_patch_value_.capacity() + host_origin_.capacity() +
            host_twin_.capacity() + host_vertex_edge_.capacity()) *
               sizeof(uint32_t) +
           staging_.bytes();
  }

  absl::StatusOr<NeighborLists> Query(const TriangulationView& host,
                                      uint64_t generation,
                                      const DeviceQuery& query) override {
    return queries_.Run(host, generation, query,
                        /*large_blocks=*/backend_ == DeviceBackend::kCuda);
  }

  ~RoundDeviceExecutor() override {
    // An attempt still running (its future outlived this executor, against
    // the contract) ends before the stream goes.
    std::lock_guard<std::mutex> lock(attempt_mu_);
#if THRUST_DEVICE_SYSTEM == THRUST_DEVICE_SYSTEM_CUDA
    cudaStreamSynchronize(stream_);
    cudaStreamDestroy(stream_);
#endif
    if (DeviceProfileLevel() == 0) return;
    std::fprintf(
        stderr,
        "[device profile] %s executor: %llu attempts, %llu fixing "
        "and %llu legalizing rounds, %llu device algorithms (the host "
        "waited for %llu); %llu legalizing rounds in device loops (%llu "
        "handed back); fix "
        "%.3f s, legalize %.3f s, transfers %.3f s (%.1f MB up, %.1f MB "
        "down; %llu of %llu mesh downloads carried only the changes; %llu "
        "host changes went up alone)\n",
        DeviceBackendName(backend_),
        static_cast<unsigned long long>(totals_.attempts),
        static_cast<unsigned long long>(totals_.counts.fix_rounds),
        static_cast<unsigned long long>(totals_.counts.legalize_rounds),
        static_cast<unsigned long long>(totals_.calls),
        static_cast<unsigned long long>(totals_.waits),
        static_cast<unsigned long long>(totals_.loop_rounds),
        static_cast<unsigned long long>(totals_.loop_returns),
        totals_.fix_seconds, totals_.legalize_seconds, totals_.transfer_seconds,
        double(totals_.bytes_uploaded) * 1e-6,
        double(totals_.bytes_downloaded) * 1e-6,
        static_cast<unsigned long long>(totals_.patched_downloads),
        static_cast<unsigned long long>(totals_.downloads),
        static_cast<unsigned long long>(totals_.patched_uploads));
    std::fprintf(stderr,
                 "[device profile] time by call site (each algorithm and the "
                 "host work after it; line 0: before the first):\n");
    clock_.Print(stderr, "round_executor.inl", 16);
  }

  absl::StatusOr<DeviceAttempt> Attempt(Mesh& mesh, absl::Span<const Vec2> to,
                                        absl::Span<const Vec2> from,
                                        const std::vector<uint32_t>* candidates,
                                        const std::vector<uint32_t>* seeds,
                                        double rebuild_fraction,
                                        const CancelToken* cancel) override {
    return AttemptAfter(CallerMark(nullptr), mesh, to, from, candidates, seeds,
                        rebuild_fraction, cancel);
  }

  std::future<absl::StatusOr<DeviceAttempt>> AttemptAsync(
      Mesh& mesh, absl::Span<const Vec2> to, absl::Span<const Vec2> from,
      const std::vector<uint32_t>* candidates,
      const std::vector<uint32_t>* seeds, double rebuild_fraction,
      const CancelToken* cancel, DeviceStream stream) override {
    try {
      // Recorded now, on the caller's thread: the caller's work so far.
      auto mark = std::make_shared<CallerMark>(stream.cuda_stream);
      return std::async(std::launch::async, [=, this, &mesh] {
        return AttemptAfter(*mark, mesh, to, from, candidates, seeds,
                            rebuild_fraction, cancel);
      });
    } catch (const std::exception& e) {  // no event, or no thread
      // The positions named for this attempt are not known to any other:
      // the next one compares whole arrays.
      std::lock_guard<std::mutex> lock(attempt_mu_);
      ForgetWrittenPositions();
      return Ready<DeviceAttempt>(absl::InternalError(
          absl::StrCat("device executor: AttemptAsync: ", e.what())));
    }
  }

  std::future<absl::StatusOr<NeighborLists>> QueryAsync(
      const TriangulationView& host, uint64_t generation,
      const DeviceQuery& query, DeviceStream stream) override {
    try {
      auto mark = std::make_shared<CallerMark>(stream.cuda_stream);
      return std::async(
          std::launch::async, [=, this]() -> absl::StatusOr<NeighborLists> {
            try {
              UseDevice(device_);
              mark->Follow(Stream{});  // the queries' stream: the default one
            } catch (const std::exception& e) {
              return absl::InternalError(
                  absl::StrCat("device executor: ", e.what()));
            }
            return Query(host, generation, query);
          });
    } catch (const std::exception& e) {
      return Ready<NeighborLists>(absl::InternalError(
          absl::StrCat("device executor: QueryAsync: ", e.what())));
    }
  }

 private:
  template <typename T>
  static std::future<absl::StatusOr<T>> Ready(absl::Status status) {
    std::promise<absl::StatusOr<T>> p;
    p.set_value(std::move(status));
    return p.get_future();
  }

  // An attempt whose device work follows `mark`, one at a time. A device
  // error (an exception of the CUDA system, or memory exhausted) comes back
  // as a status; the executor then forgets its device state (the next
  // attempt uploads the mesh and sets every mark again) and the host mesh
  // is as it was.
  absl::StatusOr<DeviceAttempt> AttemptAfter(
      const CallerMark& mark, Mesh& mesh, absl::Span<const Vec2> to,
      absl::Span<const Vec2> from, const std::vector<uint32_t>* candidates,
      const std::vector<uint32_t>* seeds, double rebuild_fraction,
      const CancelToken* cancel) {
    std::lock_guard<std::mutex> lock(attempt_mu_);
    try {
      UseDevice(device_);  // (an async form's thread starts on GPU 0)
      mark.Follow(stream_);
      return AttemptLocked(mesh, to, from, candidates, seeds, rebuild_fraction,
                           cancel);
    } catch (const std::bad_alloc&) {
      ForgetDeviceState();
      return absl::ResourceExhaustedError(
          "device executor: out of device memory during the attempt");
    } catch (const std::exception& e) {
      ForgetDeviceState();
      return absl::InternalError(absl::StrCat("device executor: ", e.what()));
    }
  }

  void ForgetDeviceState() {
    try {
      Drain(stream_);
    } catch (...) {  // a device already in error: nothing more to wait for
    }
    clock_.Stop();
    host_changed_ = true;
    ClearHostChanges();
    working_is_base_ = false;
    from_ready_ = false;
    pos_mirror_.valid = from_mirror_.valid = false;
    ForgetWrittenPositions();
    for (U32Vector* v : {&tri_claim_, &vert_claim_, &last_, &queued_, &held_}) {
      v->clear();
    }
    known_.clear();
  }

  DeviceAttempt AttemptLocked(Mesh& mesh, absl::Span<const Vec2> to,
                              absl::Span<const Vec2> from,
                              const std::vector<uint32_t>* candidates,
                              const std::vector<uint32_t>* seeds,
                              double rebuild_fraction,
                              const CancelToken* cancel) {
    const uint64_t calls = calls_, waits = waits_;
    clock_.Mark(0);  // line 0: the attempt's start up to its first algorithm
    DeviceAttempt out = AttemptOnDevice(mesh, to, from, candidates, seeds,
                                        rebuild_fraction, cancel);
    // Whatever the attempt launched last has finished (a stopped attempt
    // may end on calls the host did not wait for).
    Drain(stream_);
    clock_.Stop();
    out.device_calls = calls_ - calls;
    out.host_waits = waits_ - waits;
    ++totals_.attempts;
    totals_.calls += out.device_calls;
    totals_.waits += out.host_waits;
    totals_.loop_rounds += out.loop_rounds;
    totals_.loop_returns += out.loop_returns;
    totals_.counts += out.counts;
    totals_.fix_seconds += out.fix_seconds;
    totals_.legalize_seconds += out.legalize_seconds;
    totals_.transfer_seconds += out.transfer_seconds;
    totals_.bytes_uploaded += out.bytes_uploaded;
    totals_.bytes_downloaded += out.bytes_downloaded;
    totals_.downloads += out.fixed ? 1 : 0;
    totals_.patched_downloads += out.patched_downloads;
    totals_.patched_uploads += out.patched_uploads;
    if (DeviceProfileLevel() >= 2) {
      std::fprintf(stderr,
                   "[device profile] attempt: %llu device algorithms (%llu "
                   "waited for), %u "
                   "fixing and %u legalizing rounds (%u in device loops), "
                   "fix %.6f s, legalize "
                   "%.6f s, transfers %.6f s (%.1f MB up)%s\n",
                   static_cast<unsigned long long>(out.device_calls),
                   static_cast<unsigned long long>(out.host_waits),
                   out.counts.fix_rounds, out.counts.legalize_rounds,
                   out.loop_rounds, out.fix_seconds, out.legalize_seconds,
                   out.transfer_seconds, double(out.bytes_uploaded) * 1e-6,
                   out.fixed       ? ""
                   : out.cancelled ? " (cancelled)"
                   : out.tangled   ? " (tangled)"
                                   : " (stuck)");
    }
    return out;
  }

  DeviceAttempt AttemptOnDevice(Mesh& mesh, absl::Span<const Vec2> to,
                                absl::Span<const Vec2> from,
                                const std::vector<uint32_t>* candidates,
                                const std::vector<uint32_t>* seeds,
                                double rebuild_fraction,
                                const CancelToken* cancel) {
    DeviceAttempt out;
    auto t0 = std::chrono::steady_clock::now();
    const uint32_t nt = mesh.num_triangles();
    const uint32_t nv = mesh.num_vertices();
    // The base must be the host mesh. While the mesh's content_version()
    // is the one the base was made from, nothing has written to it (every
    // writing access renews the number): no check is needed. Changes the
    // host named (ChangedOnHost) are a promise, as the positions' lists
    // are: they go up alone, and the base's fingerprint sums follow them
    // without a pass over the host mesh. Otherwise, and for every named
    // upload under KINETRI_DEVICE_CHECK=1 (checks.h), the mesh is checked
    // by fingerprint (a parallel pass over the host arrays,
    // Mesh::Fingerprint, 6-9 ms at 1M points on 2 cores), so that a caller
    // that changed the mesh without Invalidate() costs an upload, not a
    // wrong mesh, and one that only took a writing view costs the pass.
    // The base's sums are kept: the download follows them through the
    // entries it changes (DownloadResult), without a second pass.
    const uint64_t version = mesh.content_version();
    const bool same_shape =
        base_origin_.size() == mesh.num_half_edges() && nv_ == nv;
    uint64_t fingerprint = base_fingerprint_;
    if (host_changed_ || !same_shape || version != base_version_) {
      // Named changes go up alone, the base's sums followed through them.
      // 1: they did; 0: none to send, or one out of range (a caller's bug:
      // a resync); -1: more than a patch holds. Below 1, with a name, the
      // whole mesh goes up.
      int patch = 0;
      Mesh::FingerprintSums followed = base_sums_;
      if (!host_changed_ && same_shape &&
          (!host_triangles_.empty() || !host_vertices_.empty())) {
        patch = UploadHostChanges(mesh, &followed, &out);
        if (patch <= 0) {
          out.resyncs = patch == 0 ? 1 : 0;
          host_changed_ = true;
        }
      }
      if (patch > 0 && !DeviceChecksOn()) {
        base_sums_ = followed;  // trusted: no pass
        fingerprint = base_fingerprint_ = followed.Combine();
        out.patched_uploads = 1;
      } else {
        base_sums_ = mesh.FingerprintParts();
        fingerprint = base_sums_.Combine();
        out.fingerprint_passes = 1;
        if (!host_changed_ && same_shape) {
          // The followed sums (or, with nothing named, the base's) must
          // give the host mesh's fingerprint, else something changed that
          // was not named.
          const uint64_t expected =
              patch > 0 ? followed.Combine() : base_fingerprint_;
          if (expected == fingerprint) {
            out.patched_uploads = patch > 0 ? 1 : 0;
            base_fingerprint_ = fingerprint;
          } else {
            out.resyncs = 1;
            host_changed_ = true;
          }
        }
      }
      base_version_ = version;
    }
    ClearHostChanges();
    if (host_changed_ || !same_shape) {
      // The host mesh changed (or was never here): it becomes the base.
      base_fingerprint_ = fingerprint;
      Upload(absl::MakeConstSpan(mesh.origin()), base_origin_);
      Upload(absl::MakeConstSpan(mesh.twin()), base_twin_);
      Upload(absl::MakeConstSpan(mesh.vertex_edge()), base_vertex_edge_);
      out.bytes_uploaded += 8ull * mesh.num_half_edges() + 4ull * nv;
      nv_ = nv;
      host_changed_ = false;
      working_is_base_ = false;
    }
    if (!working_is_base_) {
      // The attempt works on a copy of the base made on the device: a stuck
      // or cancelled attempt leaves the host mesh as it was, and the next
      // one starts again from the base without crossing the bus (on the
      // fourth GPU lease the re-uploads of whole meshes after stuck
      // attempts were most of a step's time at 1M points).
      origin_.assign(base_origin_.begin(), base_origin_.end());
      twin_.assign(base_twin_.begin(), base_twin_.end());
      vertex_edge_.assign(base_vertex_edge_.begin(), base_vertex_edge_.end());
      working_is_base_ = true;
    }
    // Positions the caller did not describe since the last attempt are
    // compared whole (PositionsWrittenAt).
    if (!written_called_) ForgetWrittenPositions();
    written_called_ = false;
    out.bytes_uploaded +=
        UploadChanged(to, pos_, pos_mirror_, to_written_, &out);
    from_host_ = from.size() == to.size() ? from : absl::Span<const Vec2>();
    from_ready_ = false;
    held_.clear();
    if (tri_claim_.size() != nt) tri_claim_.assign(nt, kNoEdge);
    if (vert_claim_.size() != nv) vert_claim_.assign(nv, kNoEdge);
    if (last_.size() != nv) last_.assign(nv, 0);
    if (candidates != nullptr) {
      Upload(absl::MakeConstSpan(*candidates), seeds_);
      out.bytes_uploaded += 4ull * candidates->size();
    }
    out.transfer_seconds += Since(t0);
    t0 = std::chrono::steady_clock::now();

    const MeshView m{Raw(origin_), Raw(twin_), mesh.num_half_edges()};
    const Vec2* p = Raw(pos_);
    // Invalid triangles (the first worklist).
    if (candidates == nullptr) {
      work_.resize(nt);
      work_.erase(thr::copy_if(P(), Count(0), Count(nt), work_.begin(),
                               TriangleBad{m, p}),
                  work_.end());
      if (work_.size() > rebuild_fraction * nt) {
        out.tangled = true;
        out.fix_seconds = Since(t0);
        return out;
      }
    } else {
      work_.resize(seeds_.size());
      work_.erase(thr::copy_if(P(), seeds_.begin(), seeds_.end(), work_.begin(),
                               TriangleBad{m, p}),
                  work_.end());
    }
    SortUnique(work_);
    touched_.clear();
    const bool keep_touched = seeds != nullptr;
    working_is_base_ = false;  // the attempt changes it from here
    const int fixed = Fix(m, p, nt, nv, keep_touched, cancel, &out);
    out.fix_seconds = Since(t0);
    if (fixed < 0) {
      out.cancelled = true;
      // (The positions it held back are not known here.)
      pos_mirror_.valid = false;
      return out;
    }
    DownloadHeld(&out);
    if (fixed == 0) return out;

    t0 = std::chrono::steady_clock::now();
    if (seeds == nullptr) {
      const uint32_t ne = mesh.num_half_edges();
      work_.resize(ne);
      work_.erase(
          thr::copy_if(P(), Count(0), Count(ne), work_.begin(), IsCanonical{m}),
          work_.end());
    } else {
      const size_t ns = seeds->size(), nt_touched = touched_.size();
      next_.resize(ns + nt_touched);
      staging_.ToDevice(seeds->data(), ns, Raw(next_), stream_);
      thr::copy(touched_.begin(), touched_.end(), next_.begin() + ns);
      out.bytes_uploaded += 4ull * ns;
      SortUnique(next_);
      work_.resize(3 * next_.size());
      thr::for_each(A(), Count(0), Count(static_cast<uint32_t>(next_.size())),
                    TriangleEdges{m, Raw(next_), Raw(work_)});
      SortUnique(work_);
    }
    if (!Legalize(m, p, cancel, &out)) {
      out.legalize_seconds = Since(t0);
      out.cancelled = true;
      return out;
    }
    out.legalize_seconds = Since(t0);

    // Download: the host mesh becomes the device mesh.
    clock_.Mark(__LINE__);
    t0 = std::chrono::steady_clock::now();
    DownloadResult(mesh, &out);  // (and base_fingerprint_)
    base_version_ = mesh.content_version();
    out.transfer_seconds += Since(t0);
    out.fixed = true;
    // The result is the host mesh now: it becomes the base (the next attempt
    // copies it back into the working arrays).
    base_origin_.swap(origin_);
    base_twin_.swap(twin_);
    base_vertex_edge_.swap(vertex_edge_);
    return out;
  }

  // Sends the entries the host named changed (ChangedOnHost: each
  // triangle's three half-edges, each vertex's vertex_edge) into the base,
  // bringing their old contents back to follow `sums` (the base's) through
  // them. Returns 1 when they went up (then the base is the host mesh if
  // nothing else changed: the caller may check `sums` against a pass); 0
  // when one was named out of range (a caller's bug) and -1 when they are
  // more than a patch holds, both before anything is sent: the caller then
  // uploads the whole mesh.
  int UploadHostChanges(const Mesh& mesh, Mesh::FingerprintSums* sums,
                        DeviceAttempt* out) {
    const uint32_t ne = mesh.num_half_edges();
    const uint32_t nv = nv_;
    const uint32_t cap = (ne + nv) / 8;
    SortUnique(host_triangles_);
    SortUnique(host_vertices_);
    const size_t np = 3 * host_triangles_.size() + host_vertices_.size();
    if (np > cap) return -1;
    if (!host_triangles_.empty() && host_triangles_.back() >= ne / 3) return 0;
    if (!host_vertices_.empty() && host_vertices_.back() >= nv) return 0;
    ExactCapacity(&host_patch_index_, cap);
    ExactCapacity(&host_patch_value_, 2ull * cap);
    host_patch_index_.resize(np);
    host_patch_value_.resize(2 * np);
    const std::vector<uint32_t>& origin = mesh.origin();
    const std::vector<uint32_t>& twin = mesh.twin();
    const std::vector<uint32_t>& ve = mesh.vertex_edge();
    size_t k = 0;
    for (uint32_t t : host_triangles_) {
      for (uint32_t e = 3 * t; e < 3 * t + 3; ++e, ++k) {
        host_patch_index_[k] = e;
        host_patch_value_[2 * k] = origin[e];
        host_patch_value_[2 * k + 1] = twin[e];
      }
    }
    for (uint32_t v : host_vertices_) {
      host_patch_index_[k] = ne + v;
      host_patch_value_[2 * k] = ve[v];
      host_patch_value_[2 * k + 1] = 0;
      ++k;
    }
    if (patch_index_.size() < cap) {
      patch_index_.resize(cap);
      patch_value_.resize(2ull * cap);
    }
    staging_.ToDevice(host_patch_index_.data(), np, Raw(patch_index_), stream_);
    staging_.ToDevice(host_patch_value_.data(), 2 * np, Raw(patch_value_),
                      stream_);
    thr::for_each(A(), Count(0), Count(static_cast<uint32_t>(np)),
                  SwapInHostChanges{Raw(base_origin_), Raw(base_twin_),
                                    Raw(base_vertex_edge_), ne,
                                    Raw(patch_index_), Raw(patch_value_)});
    (void)P();  // the old contents' download waits for the swap
    staging_.ToHost(Raw(patch_value_), 2 * np, host_patch_value_.data(),
                    stream_);
    for (k = 0; k < np; ++k) {
      const uint32_t i = host_patch_index_[k];
      if (i < ne) {
        sums->Change(0, i, host_patch_value_[2 * k], origin[i]);
        sums->Change(1, i, host_patch_value_[2 * k + 1], twin[i]);
      } else {
        sums->Change(2, i - ne, host_patch_value_[2 * k], ve[i - ne]);
      }
    }
    out->bytes_uploaded += 12ull * np;
    out->bytes_downloaded += 8ull * np;
    working_is_base_ = false;
    return 1;
  }

  static void SortUnique(std::vector<uint32_t>& v) {
    std::sort(v.begin(), v.end());
    v.erase(std::unique(v.begin(), v.end()), v.end());
  }
  void ClearHostChanges() {
    host_triangles_.clear();
    host_vertices_.clear();
  }

  // The policies of the Thrust algorithms below (temporaries from pool_):
  // P() for a call whose result the host reads (it waits for the device),
  // A() for the rest (no wait on the CUDA system). Each call counts one
  // device algorithm (and P() one wait), and marks its line on clock_.
  PoolPolicy P(int line = __builtin_LINE()) {
    faults_.BeforeCall();
    ++calls_;
    ++waits_;
    clock_.Mark(line);
    return Policy(pool_, stream_);
  }
  NoWaitPolicy A(int line = __builtin_LINE()) {
    faults_.BeforeCall();
    ++calls_;
    clock_.Mark(line);
    return PolicyNoWait(pool_, stream_);
  }

  // The host mesh becomes the working mesh. The base arrays are the host's,
  // so only the half-edges and vertex_edge entries that differ from them
  // need to cross the bus: they are found and gathered on the device, and
  // applied to the host mesh in place when they are at most an eighth of
  // the entries (a sparse attempt at 1M points changes a few thousand; a
  // dense one at sigma 0.01 a few percent); otherwise the whole arrays come
  // down, into host arrays kept from the previous download (the mesh's old
  // ones, of the same size: no allocation, no zero fill), swapped in whole.
  // Either way a failed copy leaves the host mesh as it was (a patch is
  // applied once it is all on the host). base_fingerprint_ becomes the
  // changed mesh's: from the attempt's sums followed through the patch, or
  // by a pass over the whole arrays.
  void DownloadResult(Mesh& mesh, DeviceAttempt* out) {
    const uint32_t ne = mesh.num_half_edges();
    const uint32_t nv = nv_;
    const uint32_t cap = (ne + nv) / 8;
    if (patch_count_.size() != 1) patch_count_.resize(1);
    if (patch_index_.size() < cap) {
      patch_index_.resize(cap);
      patch_value_.resize(2ull * cap);
    }
    thr::fill(A(), patch_count_.begin(), patch_count_.end(), 0u);
    thr::for_each(
        A(), Count(0), Count(ne + nv),
        AppendChanges{Raw(origin_), Raw(twin_), Raw(vertex_edge_),
                      Raw(base_origin_), Raw(base_twin_),
                      Raw(base_vertex_edge_), ne, cap, Raw(patch_count_),
                      Raw(patch_index_), Raw(patch_value_)});
    uint32_t np = 0;
    (void)P();  // the count's download waits for the append
    staging_.ToHost(Raw(patch_count_), 1, &np, stream_);
    if (np <= cap) {
      // (Reserved to the most a patch can hold, once: no doubling.)
      ExactCapacity(&host_patch_index_, cap);
      ExactCapacity(&host_patch_value_, 2ull * cap);
      host_patch_index_.resize(np);
      host_patch_value_.resize(2ull * np);
      staging_.ToHost(Raw(patch_index_), np, host_patch_index_.data(), stream_);
      staging_.ToHost(Raw(patch_value_), 2ull * np, host_patch_value_.data(),
                      stream_);
      std::vector<uint32_t>& ve = mesh.mutable_vertex_edge();
      const std::vector<uint32_t>& origin = mesh.origin();
      const std::vector<uint32_t>& twin = mesh.twin();
      Mesh::FingerprintSums& sums = base_sums_;
      for (uint32_t k = 0; k < np; ++k) {
        const uint32_t i = host_patch_index_[k];
        const uint32_t a = host_patch_value_[2 * k];
        if (i < ne) {
          const uint32_t b = host_patch_value_[2 * k + 1];
          sums.Change(0, i, origin[i], a);
          sums.Change(1, i, twin[i], b);
          mesh.SetHalfEdge(i, a, b);
        } else {
          sums.Change(2, i - ne, ve[i - ne], a);
          ve[i - ne] = a;
        }
      }
      base_fingerprint_ = sums.Combine();
      out->bytes_downloaded += 4 + 12ull * np;
      ++out->patched_downloads;
      return;
    }
    Download(origin_, &host_origin_);
    Download(twin_, &host_twin_);
    Download(vertex_edge_, &host_vertex_edge_);
    mesh.SwapArrays(&host_origin_, &host_twin_, &host_vertex_edge_);
    base_sums_ = mesh.FingerprintParts();
    base_fingerprint_ = base_sums_.Combine();
    out->bytes_downloaded += 4 + 8ull * ne + 4ull * nv;
  }

  // A device array of positions and the host's copy of what it holds.
  struct Mirror {
    std::vector<Vec2> values;
    bool valid = false;  // false: the device array is not known
  };

  void ForgetWrittenPositions() {
    to_written_.Forget();
    from_written_.Forget();
    written_called_ = false;
  }

  // The entries of a host array of positions written since its mirror was
  // sent, as PositionsWrittenAt names them (at most a quarter of the
  // array's entries, or none).
  struct Written {
    std::vector<uint32_t> entries;
    // Whether `entries` holds every write since the mirror was sent.
    bool known = false;
    void Add(absl::Span<const uint32_t> more, size_t most) {
      if (!known) return;
      if (entries.size() + more.size() > most) {
        Forget();
        return;
      }
      entries.insert(entries.end(), more.begin(), more.end());
    }
    void Forget() {
      known = false;
      entries.clear();
    }
    void Restart() {  // the mirror was sent: nothing written since
      known = true;
      entries.clear();
    }
  };

  // Makes `device` hold `host`, sending only the entries that differ from
  // the mirror when they are at most a quarter (a sparse step's few moving
  // vertices, where the whole array would cross the bus every attempt),
  // else the whole array. The entries that differ are looked for among
  // those `written` names when it knows them, else by a pass over both
  // arrays. Returns the bytes sent.
  uint64_t UploadChanged(absl::Span<const Vec2> host,
                         thr::device_vector<Vec2>& device, Mirror& mirror,
                         Written& written, DeviceAttempt* out) {
    const size_t n = host.size();
    if (mirror.valid && mirror.values.size() == n && device.size() == n) {
      const size_t most = n / 4;
      ExactCapacity(&host_change_index_, most);
      ExactCapacity(&host_change_value_, most);
      const absl::Span<const Vec2> old = mirror.values;
      bool found = false;
      if (written.known) {
        std::vector<uint32_t>& w = written.entries;
        std::sort(w.begin(), w.end());
        w.erase(std::unique(w.begin(), w.end()), w.end());
        found = (w.empty() || w.back() < n) &&
                ChangedPositionsAt(host, old, w, most, &host_change_index_,
                                   &host_change_value_);
        if (found && DeviceChecksOn()) {
          // The whole comparison must find nothing more.
          std::vector<uint32_t> index;
          std::vector<Vec2> value;
          if (!ChangedPositions(host, old, most, &index, &value) ||
              index != host_change_index_) {
            out->resyncs = 1;
            found = false;
          }
        }
      }
      if (found || ChangedPositions(host, old, most, &host_change_index_,
                                    &host_change_value_)) {
        const size_t nc = host_change_index_.size();
        mirror.valid = false;  // until the scatter is through
        if (nc > 0) {
          change_index_.resize(nc);
          change_value_.resize(nc);
          staging_.ToDevice(host_change_index_.data(), nc, Raw(change_index_),
                            stream_);
          staging_.ToDevice(host_change_value_.data(), nc, Raw(change_value_),
                            stream_);
          thr::scatter(A(), change_value_.begin(), change_value_.end(),
                       change_index_.begin(), device.begin());
          for (size_t j = 0; j < nc; ++j) {
            mirror.values[host_change_index_[j]] = host_change_value_[j];
          }
        }
        mirror.valid = true;
        written.Restart();
        return (sizeof(uint32_t) + sizeof(Vec2)) * nc;
      }
    }
    mirror.valid = false;
    Upload(host, device);
    ExactCapacity(&mirror.values, n);
    mirror.values.assign(host.begin(), host.end());
    mirror.valid = true;
    written.Restart();
    return sizeof(Vec2) * n;
  }

  // Makes v's capacity exactly `n` unless it is between n and n + n/4, so
  // that the host memory held stays within kDeviceHostBytesPerPoint
  // (a vector grown by doubling, or kept from a larger mesh, may hold
  // twice what it needs). Keeps no contents when it reallocates.
  template <typename T>
  static void ExactCapacity(std::vector<T>* v, size_t n) {
    if (v->capacity() >= n && v->capacity() <= n + n / 4) return;
    std::vector<T>().swap(*v);
    v->reserve(n);
  }

  // Host -> device and back through the pinned staging, on the stream.
  template <typename T>
  void Upload(absl::Span<const T> from, thr::device_vector<T>& to) {
    to.resize(from.size());
    staging_.ToDevice(from.data(), from.size(), Raw(to), stream_);
  }
  void Download(U32Vector& from, std::vector<uint32_t>* to) {
    // (The host arrays are the mesh's old ones: grown by joins, they may
    // hold more than this mesh needs.)
    ExactCapacity(to, from.size());
    to->resize(from.size());
    staging_.ToHost(Raw(from), from.size(), to->data(), stream_);
  }

  void SortUnique(U32Vector& v) {
    thr::sort(A(), v.begin(), v.end());
    v.erase(thr::unique(P(), v.begin(), v.end()), v.end());
  }

  // Fixing rounds over work_ (sorted, unique). 1: fixed (and the hull winds
  // once); 0: stuck (out->stuck_corners filled); -1: cancelled.
  int Fix(const MeshView& m, const Vec2* p, uint32_t nt, uint32_t nv,
          bool keep_touched, const CancelToken* cancel, DeviceAttempt* out) {
    FlipCounts counts;
    counters_.resize(kCounters);
    thr::fill(A(), counters_.begin(), counters_.end(), 0u);
    while (true) {
      if (cancel != nullptr && cancel->Cancelled()) return -1;
      bad_.resize(work_.size());
      bad_.erase(thr::copy_if(P(), work_.begin(), work_.end(), bad_.begin(),
                              TriangleBad{m, p}),
                 bad_.end());
      if (bad_.empty()) break;
      const uint32_t nb = static_cast<uint32_t>(bad_.size());
      props_.resize(nb);
      thr::transform(A(), bad_.begin(), bad_.end(), props_.begin(),
                     ProposeFix{m, p});
      props_.erase(thr::remove_if(P(), props_.begin(), props_.end(), NoFlip{}),
                   props_.end());
      if (props_.empty()) {
        // Stalled: hold the culprits back and go on around them (when the
        // caller gave the old positions), else stuck.
        if (HoldCulprits(m, out)) continue;
        Stuck(m, bad_, out);
        return 0;
      }
      thr::sort(A(), props_.begin(), props_.end(), EdgeLess{});
      props_.erase(thr::unique(P(), props_.begin(), props_.end(), EdgeEqual{}),
                   props_.end());
      const uint32_t np = static_cast<uint32_t>(props_.size());
      edges_.resize(np);
      joins_.resize(2 * np);
      kinds_.resize(np);
      thr::for_each(A(), Count(0), Count(np),
                    SplitProposal{thr::raw_pointer_cast(props_.data()),
                                  Raw(edges_), Raw(joins_), Raw(kinds_)});
      const uint32_t nw =
          SelectWinners(Claims{m, Raw(edges_), Raw(joins_), Raw(tri_claim_),
                               Raw(vert_claim_), nv},
                        np);
      // Next worklist: the still-invalid triangles plus every winner's
      // footprint (taken before flipping; flips keep triangle ids).
      win_edges_.resize(nw);
      thr::gather(A(), winners_.begin(), winners_.end(), edges_.begin(),
                  win_edges_.begin());
      next_.resize(nb + 6ull * nw);
      thr::copy(A(), bad_.begin(), bad_.end(), next_.begin());
      const size_t touched_base = touched_.size();
      if (keep_touched) touched_.resize(touched_base + 2ull * nw);
      thr::for_each(A(), Count(0), Count(nw),
                    WriteFootprint{
                        m, Raw(win_edges_), Raw(next_) + nb,
                        keep_touched ? Raw(touched_) + touched_base : nullptr});
      FlipWinners(m, nw);
      // The winners' flip kinds, counted on the device (read once fixed).
      thr::for_each(A(), winners_.begin(), winners_.end(),
                    CountKinds{Raw(kinds_), Raw(counters_)});
      ++counts.fix_rounds;
      SortUnique(next_);
      work_.swap(next_);
    }
    const HullCount hull = thr::transform_reduce(
        P(), Count(0), Count(nt), HullOf{m, p}, HullCount{}, HullPlus{});
    if (hull.bad != 0 || hull.ghosts < 3 || hull.tops != 1) {
      // Every triangle is valid but the hull winds more than once: the
      // ghost triangles' vertices are the ones to hold back.
      bad_.resize(nt);
      bad_.erase(thr::copy_if(P(), Count(0), Count(nt), bad_.begin(),
                              IsGhostTriangle{m}),
                 bad_.end());
      Stuck(m, bad_, out);
      return 0;
    }
    uint32_t kinds[kCounters];
    ReadCounters(kinds);
    counts.interior_fix += kinds[rules::kInteriorFlip];
    counts.hull_absorb += kinds[rules::kHullAbsorb];
    counts.hull_release += kinds[rules::kHullRelease];
    out->counts += counts;
    return 1;
  }

  // Legalizing rounds over work_ (canonical edges, sorted, unique). False
  // when cancelled. Each predicate is evaluated once per change: a round's
  // candidates are the illegal edges of work_ plus the edges known to be
  // illegal (losers of the last round whose triangles did not flip, marked
  // in known_ and not tested again), in ascending order. The winners are
  // those of re-testing every loser (a loser whose triangle flipped comes
  // back as an outer edge of its quad), as in the round executor
  // (core/kinetic.cc). Winners are flagged, not gathered: the host waits
  // twice per round, for the candidates' count and the next worklist's
  // (kNoEdge entries in work_ are placeholders, never candidates).
  //
  // Once the worklist fits the device loop (LoopControl), rounds run there
  // until legalizing ends or the worklist outgrows it again.
  bool Legalize(const MeshView& m, const Vec2* p, const CancelToken* cancel,
                DeviceAttempt* out) {
    FlipCounts* counts = &out->counts;
    if (known_.size() != m.num_half_edges) {
      known_.assign(m.num_half_edges, 0);
    }
    counters_.resize(kCounters);
    thr::fill(A(), counters_.begin(), counters_.end(), 0u);
    const uint32_t loop_size = LoopListSize(m);
    const uint32_t loop_launch = std::min(loop_control_.capacity, loop_size);
    while (true) {
      const uint32_t nwork = static_cast<uint32_t>(work_.size());
      if (cancel != nullptr && cancel->Cancelled()) {
        // Leave known_ clear for the next attempt.
        thr::for_each(A(), work_.begin(), work_.end(),
                      ForgetKnown{Raw(known_)});
        return false;
      }
      if (nwork != 0 && nwork <= loop_launch) {
        const LoopStatus end =
            RunLoop(m, p, loop_size, loop_launch, cancel, out);
        if (end == kLoopDone) break;
        continue;  // work_: the loop's worklist (cancelled or too long)
      }
      flags_.resize(nwork);
      thr::for_each(A(), Count(0), Count(nwork),
                    TestEdge{m, p, Raw(work_), Raw(known_), Raw(flags_)});
      edges_.resize(nwork);
      edges_.erase(thr::copy_if(P(), work_.begin(), work_.end(), flags_.begin(),
                                edges_.begin(), IsSet{}),
                   edges_.end());
      if (edges_.empty()) break;
      const uint32_t ni = static_cast<uint32_t>(edges_.size());
      const Claims c{m, Raw(edges_), nullptr, Raw(tri_claim_), nullptr, 0};
      flags_.resize(ni);
      thr::for_each(A(), Count(0), Count(ni), ClaimOp{c});
      thr::for_each(A(), Count(0), Count(ni),
                    DecideOp{c, Raw(flags_), Raw(counters_) + kDelaunay});
      thr::for_each(A(), Count(0), Count(ni), ReleaseOp{c});
      const Won won{Raw(edges_), Raw(flags_)};
      thr::for_each(A(), Count(0), Count(ni), FlipWonOp{m, won});
      const QuadCorners q{m, Raw(edges_), Raw(vertex_edge_), Raw(last_),
                          Raw(flags_)};
      thr::for_each(A(), Count(0), Count(ni), MarkLast{q});
      thr::for_each(A(), Count(0), Count(ni), WriteVertexEdges{q});
      thr::for_each(A(), Count(0), Count(ni), ClearLast{q});
      // The winners' triangles are marked (0) while the next worklist is
      // written: the four outer edges of each flipped quad, and each loser
      // whose triangles did not flip (still illegal, marked known).
      thr::for_each(A(), Count(0), Count(ni),
                    MarkWonTriangles{m, won, Raw(tri_claim_), 0});
      work_.resize(4ull * ni);
      thr::for_each(A(), Count(0), Count(ni),
                    NextWork{m, won, Raw(tri_claim_), Raw(known_), Raw(work_)});
      thr::for_each(A(), Count(0), Count(ni),
                    MarkWonTriangles{m, won, Raw(tri_claim_), kNoEdge});
      ++counts->legalize_rounds;
      SortUnique(work_);
    }
    uint32_t flips[kCounters];
    ReadCounters(flips);
    counts->delaunay += flips[kDelaunay];
    return true;
  }

  // Edges a device-loop list can hold: every canonical edge, at most four
  // per entry the loop may run on.
  uint32_t LoopListSize(const MeshView& m) const {
    const uint64_t all = m.num_half_edges / 2 + 1;
    return static_cast<uint32_t>(
        std::min<uint64_t>(all, 4ull * loop_control_.capacity));
  }

  // Legalizing rounds in a device loop, starting from work_ (sorted,
  // unique, at most `launch` entries). kLoopDone: no illegal edge is left.
  // Otherwise work_ is the loop's worklist (sorted, unique, its queued bits
  // clear) when it outgrew `launch` (kLoopOverflow) or the attempt is
  // cancelled (kLoopRunning; polled between checks).
  LoopStatus RunLoop(const MeshView& m, const Vec2* p, uint32_t list_size,
                     uint32_t launch, const CancelToken* cancel,
                     DeviceAttempt* out) {
    if (queued_.size() != (m.num_half_edges + 31) / 32) {
      queued_.assign((m.num_half_edges + 31) / 32, 0u);
    }
    if (loop_list0_.size() < list_size) {
      loop_list0_.resize(list_size);
      loop_list1_.resize(list_size);
    }
    if (loop_cand_.size() < launch) {
      loop_cand_.resize(launch);
      loop_won_.resize(launch);
    }
    loop_state_.resize(kLoopWords);
    const uint32_t n = static_cast<uint32_t>(work_.size());
    // (The first list's queued bits stay clear: a round clears its list's
    // bits before it appends to the next.)
    thr::copy(A(), work_.begin(), work_.end(), loop_list0_.begin());
    thr::for_each(A(), Count(0), Count(1), LoopStart{Raw(loop_state_), n});
    const Loop loop{Raw(loop_state_), Raw(loop_list0_), Raw(loop_list1_),
                    list_size};
    const LoopTest test{
        loop, m, p, Raw(known_), Raw(queued_), Raw(loop_cand_), Raw(loop_won_)};
    LoopRound round{loop,
                    m,
                    Raw(known_),
                    Raw(queued_),
                    Raw(loop_cand_),
                    Raw(loop_won_),
                    Raw(tri_claim_),
                    Raw(vertex_edge_),
                    Raw(last_),
                    Raw(counters_) + kDelaunay,
                    0};
    uint32_t state[kLoopWords];
    while (true) {
      for (uint32_t r = 0; r < loop_control_.rounds_per_check; ++r) {
        thr::for_each(A(), Count(0), Count(launch), test);
        for (uint32_t phase = kPhaseClaim; phase <= kPhaseUnmarkWon; ++phase) {
          round.phase = phase;
          thr::for_each(A(), Count(0), Count(launch), round);
        }
        thr::for_each(A(), Count(0), Count(1),
                      LoopFinish{Raw(loop_state_), launch});
      }
      (void)P();  // the state's download waits for the rounds
      staging_.ToHost(Raw(loop_state_), kLoopWords, state, stream_);
      if (state[kLoopStatus] != kLoopRunning ||
          (cancel != nullptr && cancel->Cancelled())) {
        break;
      }
    }
    if (state[kLoopStatus] == kLoopBroken) {
      // (AttemptAfter turns this into a status and resets the marks.)
      throw std::runtime_error(
          "a device loop's worklist outgrew its list (a bug)");
    }
    out->counts.legalize_rounds += state[kLoopRounds];
    out->loop_rounds += state[kLoopRounds];
    if (state[kLoopStatus] == kLoopDone) return kLoopDone;
    // Back to the host: the current list becomes work_.
    const uint32_t cur = state[kLoopCur];
    U32Vector& list = cur != 0 ? loop_list1_ : loop_list0_;
    const uint32_t size = state[kLoopCount0 + cur];
    work_.resize(size);
    thr::copy(A(), list.begin(), list.begin() + size, work_.begin());
    thr::for_each(A(), work_.begin(), work_.end(), ClearQueued{Raw(queued_)});
    SortUnique(work_);
    if (state[kLoopStatus] == kLoopOverflow) ++out->loop_returns;
    return static_cast<LoopStatus>(state[kLoopStatus]);
  }

  // The device counters into `out` (kCounters words), waiting for them.
  void ReadCounters(uint32_t* out) {
    (void)P();  // counts the call and the wait
    thr::copy(counters_.begin(), counters_.end(), out);
  }

  // Flips the edges in win_edges_ (disjoint footprints) and refreshes
  // vertex_edge of their quads' corners.
  void FlipWinners(const MeshView& m, uint32_t nw) {
    thr::for_each(A(), win_edges_.begin(), win_edges_.end(), FlipOp{m});
    const QuadCorners q{m, Raw(win_edges_), Raw(vertex_edge_), Raw(last_)};
    thr::for_each(A(), Count(0), Count(nw), MarkLast{q});
    thr::for_each(A(), Count(0), Count(nw), WriteVertexEdges{q});
    thr::for_each(A(), Count(0), Count(nw), ClearLast{q});
  }

  // Claims for n proposals; winners_ receives the indices of the winners
  // (ascending), flags_ one byte per proposal (1: won). Returns their count.
  uint32_t SelectWinners(const Claims& c, uint32_t n) {
    thr::for_each(A(), Count(0), Count(n), ClaimOp{c});
    flags_.resize(n);
    thr::transform(A(), Count(0), Count(n), flags_.begin(), WonOp{c});
    winners_.resize(n);
    winners_.erase(thr::copy_if(P(), Count(0), Count(n), flags_.begin(),
                                winners_.begin(), IsSet{}),
                   winners_.end());
    thr::for_each(A(), Count(0), Count(n), ReleaseOp{c});
    return static_cast<uint32_t>(winners_.size());
  }

  // One hold-back (core/kinetic.cc's HoldCulprits, step for step): the
  // culprits of bad_ (a vertex once, with its smallest half-edge found) go
  // back to their old positions and are appended to held_; work_ becomes
  // bad_ plus every triangle whose validity reads a held vertex. False when
  // no old positions were given or no stalled triangle has a culprit. The
  // old positions are uploaded at the attempt's first hold-back.
  bool HoldCulprits(const MeshView& m, DeviceAttempt* out) {
    if (from_host_.empty()) return false;
    if (!from_ready_) {
      const auto t0 = std::chrono::steady_clock::now();
      out->bytes_uploaded +=
          UploadChanged(from_host_, from_, from_mirror_, from_written_, out);
      out->transfer_seconds += Since(t0);
      from_ready_ = true;
    }
    const uint32_t nb = static_cast<uint32_t>(bad_.size());
    culprit_keys_.resize(3ull * nb);
    thr::for_each(
        A(), Count(0), Count(nb),
        FindCulprits{m, Raw(pos_), Raw(from_), Raw(bad_), Raw(culprit_keys_)});
    culprit_keys_.erase(thr::remove_if(P(), culprit_keys_.begin(),
                                       culprit_keys_.end(), IsNoCulprit{}),
                        culprit_keys_.end());
    thr::sort(A(), culprit_keys_.begin(), culprit_keys_.end());
    culprit_keys_.erase(thr::unique(P(), culprit_keys_.begin(),
                                    culprit_keys_.end(), SameCulprit{}),
                        culprit_keys_.end());
    const uint32_t nh = static_cast<uint32_t>(culprit_keys_.size());
    if (nh == 0) return false;
    const size_t held_before = held_.size();
    held_.resize(held_before + nh);
    thr::for_each(A(), Count(0), Count(nh),
                  HoldCulprit{Raw(culprit_keys_), Raw(pos_), Raw(from_),
                              Raw(held_) + held_before});
    edges_.resize(nh + 1);  // star sizes (0 last), then their offsets
    thr::for_each(A(), Count(0), Count(nh + 1),
                  CulpritStarSize{m, Raw(culprit_keys_), nh, Raw(edges_)});
    thr::exclusive_scan(A(), edges_.begin(), edges_.end(), edges_.begin());
    uint32_t stars = 0;
    (void)P();  // the total's download waits for the scan
    staging_.ToHost(Raw(edges_) + nh, 1, &stars, stream_);
    next_.resize(size_t{nb} + stars);
    thr::copy(A(), bad_.begin(), bad_.end(), next_.begin());
    thr::for_each(
        A(), Count(0), Count(nh),
        WriteCulpritStar{m, Raw(culprit_keys_), Raw(edges_), Raw(next_) + nb});
    SortUnique(next_);
    work_.swap(next_);
    return true;
  }

  // The vertices the attempt held back (DeviceAttempt::held).
  void DownloadHeld(DeviceAttempt* out) {
    if (held_.empty()) return;
    Download(held_, &out->held);
    out->bytes_downloaded += 4ull * held_.size();
    // HoldCulprit moved them to their old positions on the device.
    if (pos_mirror_.valid) {
      for (uint32_t v : out->held) pos_mirror_.values[v] = from_host_[v];
    }
  }

  void Stuck(const MeshView& m, U32Vector& triangles, DeviceAttempt* out) {
    const uint32_t n = static_cast<uint32_t>(triangles.size());
    next_.resize(3ull * n);
    thr::for_each(P(), Count(0), Count(n),
                  Corners{m, Raw(triangles), Raw(next_)});
    out->stuck_corners.resize(3ull * n);
    thr::copy(next_.begin(), next_.end(), out->stuck_corners.begin());
    out->bytes_downloaded += 12ull * n;
  }

  const DeviceBackend backend_;
  const int device_;  // the GPU it was made on (the async forms' threads)
  // One attempt at a time (AttemptAsync); also guards host_changed_ and
  // loop_control_ against calls from other threads.
  mutable std::mutex attempt_mu_;
  LoopControl loop_control_;
  bool host_changed_ = true;  // Invalidate(): the base is not the host's
  // Otherwise, the triangles and vertices the host declared changed since
  // the base was the host mesh (ChangedOnHost).
  std::vector<uint32_t> host_triangles_, host_vertices_;
  uint64_t base_fingerprint_ = 0;  // Mesh::Fingerprint() of the base
  // The host mesh's content_version() when it was last the base.
  uint64_t base_version_ = 0;
  // The fingerprint sums of the base (Mesh::FingerprintParts), followed
  // through each patched download.
  Mesh::FingerprintSums base_sums_;
  bool working_is_base_ = false;  // origin_, twin_, vertex_edge_ == base
  uint32_t nv_ = 0;
  // The host mesh on the device (the base) and the copy an attempt changes.
  U32Vector base_origin_, base_twin_, base_vertex_edge_;
  U32Vector origin_, twin_, vertex_edge_;
  U32Vector last_;  // per vertex: last winner touching it (0 between rounds)
  thr::device_vector<Vec2> pos_;
  // Hold-back (HoldCulprits): the attempt's old positions on the host, and
  // on the device once a round stalls; the vertices held so far; scratch.
  absl::Span<const Vec2> from_host_;
  bool from_ready_ = false;
  thr::device_vector<Vec2> from_;
  // What pos_ and from_ hold, so that an attempt sends only the positions
  // that changed (UploadChanged), and the changes on their way up.
  Mirror pos_mirror_, from_mirror_;
  // What the caller wrote to them since they were sent (PositionsWrittenAt),
  // and whether it said so before this attempt.
  Written to_written_, from_written_;
  bool written_called_ = false;
  std::vector<uint32_t> host_change_index_;
  std::vector<Vec2> host_change_value_;
  U32Vector change_index_;
  thr::device_vector<Vec2> change_value_;
  U32Vector held_;
  thr::device_vector<uint64_t> culprit_keys_;
  // A successful attempt's changes on their way down (AppendChanges).
  U32Vector patch_count_, patch_index_, patch_value_;
  std::vector<uint32_t> host_patch_index_, host_patch_value_;
  U32Vector tri_claim_, vert_claim_;  // kNoEdge between rounds
  // Scratch kept across rounds and steps (grown, never shrunk).
  U32Vector work_, bad_, edges_, joins_, kinds_, winners_, win_edges_, next_,
      touched_, seeds_;
  // Per half-edge: 1 while it waits in work_ as a loser known to be illegal.
  thr::device_vector<uint8_t> known_;
  // The device loop: its two worklists, its state (LoopWord), one bit per
  // half-edge set while the edge waits in a list (clear between loops), and
  // per entry whether it is a candidate and won.
  U32Vector loop_list0_, loop_list1_, loop_state_, queued_;
  thr::device_vector<uint8_t> loop_cand_, loop_won_;
  // Flip counts kept on the device during an attempt: per fix kind
  // (rules::FixProposal::kind) and kDelaunay.
  U32Vector counters_;
  thr::device_vector<uint8_t> flags_;
  thr::device_vector<rules::FixProposal> props_;
  ScratchPool pool_;  // Thrust's temporaries, kept across rounds and steps
  Stream stream_{};   // every algorithm and copy of the attempts
  Staging staging_;   // pinned chunks of the uploads and downloads
  // The host arrays the next mesh download goes into (the host mesh's
  // previous ones, swapped out by the last download).
  std::vector<uint32_t> host_origin_, host_twin_, host_vertex_edge_;
  uint64_t calls_ = 0;   // device algorithms launched (P() and A() calls)
  uint64_t waits_ = 0;   // ... of which the host waited for (P() calls)
  CallSiteClock clock_;  // where the attempts' time goes, by call site
  // Over the executor's life (KINETRI_DEVICE_PROFILE prints them).
  struct Totals {
    uint64_t attempts = 0;
    uint64_t calls = 0;
    uint64_t waits = 0;
    uint64_t loop_rounds = 0;
    uint64_t loop_returns = 0;
    FlipCounts counts;
    double fix_seconds = 0.0;
    double legalize_seconds = 0.0;
    double transfer_seconds = 0.0;
    uint64_t bytes_uploaded = 0;
    uint64_t bytes_downloaded = 0;
    uint64_t downloads = 0;
    uint64_t patched_downloads = 0;
    uint64_t patched_uploads = 0;
  } totals_;
  FaultInjector faults_;  // DeviceExecutor::InjectFault
  QueryEngine queries_;   // the query view and the queries over it
};

}  // namespace

std::unique_ptr<DeviceExecutor> MakeExecutor(DeviceBackend backend) {
  return std::make_unique<RoundDeviceExecutor>(backend);
}

}  // namespace KINETRI_DEVICE_NS
}  // namespace kinetri::core::device
