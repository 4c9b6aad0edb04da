// CPU executor of the kinetic update: per-region stacks (see the header).
#include "core/region_executor.h"

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstring>
#include <optional>

#include "absl/strings/str_cat.h"
#include "core/flip_rules.h"
#include "core/mesh_scan.h"
#include "core/parallel.h"
#include "core/predicates.h"
#include "core/vertex_ops.h"

namespace kinetri::core {

void RegionExecutor::Region::ClearWork() {
  stack.clear();
  waiting.clear();
  deferred.clear();
  log.clear();
  counts = FlipCounts{};
}

namespace {

double SecondsSince(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0)
      .count();
}

using Bounds = RegionSlots;

// Regions per coarse region (the parallel pass over what crossed region
// boundaries while legalizing).
constexpr size_t kCoarse = 8;

// Triangles sampled before a dense scan to predict a rebuild.
constexpr uint32_t kRebuildSamples = 2048;

// Every triangle around the origin of e0 lies in b (e0's triangle does).
// Reads only slots of triangles already known to lie in b.
bool StarIn(const MeshView& m, uint32_t e0, Bounds b) {
  uint32_t x = e0;
  for (uint32_t i = 0; i < (1u << 16); ++i) {
    const uint32_t y = m.twin[Prev(x)];
    if (!b.In(TriangleOf(y))) return false;
    if (y == e0) return true;
    x = y;
  }
  return false;
}

// The neighbours of t lie in b.
bool NeighboursIn(const MeshView& m, uint32_t t, Bounds b) {
  for (uint32_t e = 3 * t; e < 3 * t + 3; ++e) {
    if (!b.In(TriangleOf(m.twin[e]))) return false;
  }
  return true;
}

// The read predicate of the bounded rules (core/flip_rules.h): a fix
// proposed inside a region reads only the region's triangles.
struct InBounds {
  Bounds b;
  bool operator()(uint32_t t) const { return b.In(t); }
};

// After Flip(e) or Unflip(e): every vertex whose vertex_edge (in ve) lay in
// the two triangles of e and no longer leaves it gets the first half-edge
// of the two triangles that does (in the order e, Next(e), Prev(e), f,
// Next(f), Prev(f)). Only entries that point into the two triangles are
// written, so a region that flips only its own triangles writes only
// entries that no other region writes, in its own (deterministic) order;
// other regions read an entry only to find that it is not theirs, and
// every access is atomic.
void RepairVertexEdges(const MeshView& m, uint32_t* ve, uint32_t e) {
  const uint32_t f = m.twin[e];
  const uint32_t t1 = TriangleOf(e), t2 = TriangleOf(f);
  const uint32_t hs[6] = {e, Next(e), Prev(e), f, Next(f), Prev(f)};
  for (uint32_t h : hs) {
    const uint32_t v = m.origin[h];
    if (v == kInfiniteVertex) continue;
    std::atomic_ref<uint32_t> slot(ve[v]);
    const uint32_t cur = slot.load(std::memory_order_relaxed);
    const uint32_t ct = TriangleOf(cur);
    if ((ct == t1 || ct == t2) && m.origin[cur] != v) {
      slot.store(h, std::memory_order_relaxed);
    }
  }
}

void CountFix(uint32_t kind, FlipCounts* c) {
  switch (kind) {
    case rules::kInteriorFlip:
      ++c->interior_fix;
      break;
    case rules::kHullAbsorb:
      ++c->hull_absorb;
      break;
    case rules::kHullRelease:
      ++c->hull_release;
      break;
    default:
      break;
  }
}

// Fixing with a LIFO stack inside b. Invalid triangles with no repairing
// flip wait until a flip has happened since they were looked at; what is
// left in `waiting` at the end is stuck (for this region). Bounded, the
// fix rule reads only b, and a flip runs only when it writes only b.
// vertex_edge (ve) is kept valid (RepairVertexEdges).
template <bool kBounded>
void FixLoop(const MeshView& m, const Vec2* p, Bounds b,
             std::vector<uint32_t>& stack, std::vector<uint32_t>& waiting,
             std::vector<uint32_t>& deferred, std::vector<uint32_t>* log,
             FlipCounts* counts, uint8_t* mark, uint32_t* ve, uint32_t* across,
             std::vector<uint32_t>* flipped = nullptr) {
  while (true) {
    bool progress = false;
    while (!stack.empty()) {
      const uint32_t t = stack.back();
      stack.pop_back();
      // A ghost's validity reads its neighbours (the hull turn).
      if (kBounded && m.IsGhost(t) && !NeighboursIn(m, t, b)) {
        deferred.push_back(t);
        continue;
      }
      if (rules::TriangleOk(m, p, t)) continue;
      bool outside = false;
      const rules::FixProposal prop =
          kBounded ? rules::ProposeFixFlip(m, p, t, InBounds{b}, &outside)
                   : rules::ProposeFixFlip(m, p, t);
      if (outside) {
        deferred.push_back(t);
        continue;
      }
      if (prop.edge == kNoEdge) {
        waiting.push_back(t);
        continue;
      }
      uint32_t fp[6];
      rules::FlipFootprint(m, prop.edge, fp);
      if (kBounded) {
        bool inside = true;
        for (uint32_t x : fp) inside = inside && b.In(x);
        if (!inside) {
          deferred.push_back(t);
          continue;
        }
      }
      m.Flip(prop.edge);
      RepairVertexEdges(m, ve, prop.edge);
      if (log) log->push_back(prop.edge);
      CountFix(prop.kind, counts);
      if (mark) mark[fp[0]] = mark[fp[1]] = 1;
      if (flipped) {
        flipped->push_back(fp[0]);
        flipped->push_back(fp[1]);
      }
      if (across) {
        RefreshAcross(m, fp[0], across);
        RefreshAcross(m, fp[1], across);
      }
      progress = true;
      for (int k = 5; k >= 0; --k) stack.push_back(fp[k]);
    }
    if (waiting.empty() || !progress) return;
    stack.swap(waiting);
  }
}

// Delaunay flips with a LIFO stack of half-edges inside b (each half-edge's
// own triangle lies in b); vertex_edge (ve) is kept valid
// (RepairVertexEdges). `log` (optional): the flipped half-edges, in order.
// The first `known_illegal` entries of the stack (its bottom) were found
// illegal by the scan: popped while both their triangles are unmarked
// (neither flipped nor around a held vertex since, so the same four
// vertices at the same positions) they are flipped without testing again.
template <bool kBounded>
void LegalizeLoop(const MeshView& m, const Vec2* p, Bounds b,
                  std::vector<uint32_t>& stack, std::vector<uint32_t>& deferred,
                  FlipCounts* counts, uint8_t* mark, uint32_t* ve,
                  uint32_t* across, std::vector<uint32_t>* log = nullptr,
                  size_t known_illegal = 0) {
  // The scan's illegal edges lie scattered over the region's slots, out of
  // cache by now (every region has been scanned since): their triangles
  // are prefetched kFar entries ahead; the triangles across, the vertices'
  // positions and vertex_edge entries kNear ahead.
  constexpr size_t kFar = 8, kNear = 4;
  while (!stack.empty()) {
    const size_t depth = stack.size();
    if (depth <= known_illegal) {
      if (depth > kFar) {
        const uint32_t a = stack[depth - 1 - kFar];
        __builtin_prefetch(&m.twin[a]);
        __builtin_prefetch(&m.origin[a]);
      }
      if (depth > kNear) {
        const uint32_t a = stack[depth - 1 - kNear];
        const uint32_t t = 3 * TriangleOf(a);
        const uint32_t fa = m.twin[a];
        __builtin_prefetch(&m.origin[fa]);
        __builtin_prefetch(&m.twin[fa]);
        for (uint32_t k = 0; k < 3; ++k) {
          const uint32_t v = m.origin[t + k];
          if (v < kInfiniteVertex) {
            __builtin_prefetch(&p[v]);
            __builtin_prefetch(&ve[v]);
          }
        }
      }
    }
    const uint32_t e = stack.back();
    stack.pop_back();
    if (m.origin[e] == kNoVertex) continue;  // free slot
    const uint32_t f = m.twin[e];
    if (kBounded && !b.In(TriangleOf(f))) {
      deferred.push_back(e);
      continue;
    }
    const bool known = stack.size() < known_illegal && mark != nullptr &&
                       !mark[TriangleOf(e)] && !mark[TriangleOf(f)];
    if (!known && !rules::IsIllegal(m, p, e)) continue;
    if (kBounded && !(b.In(TriangleOf(m.twin[Next(e)])) &&
                      b.In(TriangleOf(m.twin[Prev(e)])) &&
                      b.In(TriangleOf(m.twin[Next(f)])) &&
                      b.In(TriangleOf(m.twin[Prev(f)])))) {
      deferred.push_back(e);
      continue;
    }
    m.Flip(e);
    RepairVertexEdges(m, ve, e);
    if (log) log->push_back(e);
    ++counts->delaunay;
    if (mark) mark[TriangleOf(e)] = mark[TriangleOf(f)] = 1;
    if (across) {
      RefreshAcross(m, TriangleOf(e), across);
      RefreshAcross(m, TriangleOf(f), across);
    }
    stack.push_back(Next(e));
    stack.push_back(Prev(e));
    stack.push_back(Next(f));
    stack.push_back(Prev(f));
  }
}

// Triangles around the origin of half-edge e0, appended to out.
void AppendStarFrom(const MeshView& m, uint32_t e0,
                    std::vector<uint32_t>* out) {
  if (e0 == kNoEdge) return;
  uint32_t e = e0;
  do {
    out->push_back(TriangleOf(e));
    e = m.twin[Prev(e)];
  } while (e != e0);
}

// The star of the origin of e0 plus, for its ghost triangles, their
// neighbours (the hull turns at its hull neighbours depend on it too).
void AppendStarAndHullRingFrom(const MeshView& m, uint32_t e0,
                               std::vector<uint32_t>* out) {
  rules::ForEachStarAndHullRing(m, e0,
                                [out](uint32_t t) { out->push_back(t); });
}

// The half-edges of the triangles around the origin of e0 and of the
// triangles fixing flipped (`flipped`: both triangles of each flip, taken
// when it ran: a later flip may rewrite a flipped half-edge's triangle, so
// that its twin no longer lies in the other one): what legalizing after a
// held vertex's move must test. `around` is scratch.
void SeedLegalizeAfterMove(const MeshView& m, uint32_t e0,
                           const std::vector<uint32_t>& flipped,
                           std::vector<uint32_t>* around,
                           std::vector<uint32_t>* stack) {
  stack->clear();
  around->clear();
  AppendStarFrom(m, e0, around);
  around->insert(around->end(), flipped.begin(), flipped.end());
  for (uint32_t t : *around) {
    for (uint32_t e = 3 * t; e < 3 * t + 3; ++e) stack->push_back(e);
  }
}

// The same from vertex_edge (which must be valid for v).
void AppendStar(const Mesh& mesh, uint32_t v, std::vector<uint32_t>* out) {
  AppendStarFrom(mesh.view(), mesh.vertex_edge()[v], out);
}
void AppendStarAndHullRing(const Mesh& mesh, uint32_t v,
                           std::vector<uint32_t>* out) {
  AppendStarAndHullRingFrom(mesh.view(), mesh.vertex_edge()[v], out);
}

// Unflips the logged flips, newest first, keeping vertex_edge (ve) and
// the across entries (when not null) valid.
void Undo(const MeshView& m, const std::vector<uint32_t>& log, uint32_t* ve,
          uint32_t* across) {
  for (auto it = log.rbegin(); it != log.rend(); ++it) {
    m.Unflip(*it);
    RepairVertexEdges(m, ve, *it);
    if (across) {
      RefreshAcross(m, TriangleOf(*it), across);
      RefreshAcross(m, TriangleOf(m.twin[*it]), across);
    }
  }
}

std::optional<Vec2> Halfway(const Vec2& a, const Vec2& b) {
  const Vec2 h{a.x + 0.5 * (b.x - a.x), a.y + 0.5 * (b.y - a.y)};
  if (!InExactDomain(h.x) || !InExactDomain(h.y) || h == a || h == b) {
    return std::nullopt;
  }
  return h;
}

// After a failed move from `from` towards *goal: the next goal is halfway
// (false when max_halvings are used up or the halfway point is not new).
bool Bisect(const Vec2& from, const RegionStepPolicy& policy, Vec2* goal,
            int* halvings, RegionStepStats* stats) {
  if (*halvings >= policy.max_halvings) return false;
  const std::optional<Vec2> h = Halfway(from, *goal);
  if (!h) return false;
  ++*halvings;
  ++stats->halvings;
  *goal = *h;
  return true;
}

}  // namespace

void RegionExecutor::Hold(uint32_t v, uint32_t edge,
                          std::vector<HeldVertex>* to) {
  // Not held before, so its entry is still its target.
  std::vector<Vec2>& cur = *cur_;
  const Vec2 target = cur[v];
  held_[v] = 1;
  cur[v] = (*from_)[v];
  if (to != nullptr) {
    to->push_back({v, edge, target});
  } else {
    held_list_.push_back(v);
    held_edge_.push_back(edge);
    held_target_.push_back(target);
  }
}

void RegionExecutor::HoldMovingNeighbours(const Mesh& mesh,
                                          const std::vector<uint32_t>& vertices,
                                          std::vector<uint32_t>* around) {
  const MeshView m = mesh.view();
  for (uint32_t v : vertices) {
    if (v >= held_.size()) continue;
    around->clear();
    AppendStar(mesh, v, around);
    for (uint32_t t : *around) {
      for (uint32_t e = 3 * t; e < 3 * t + 3; ++e) {
        const uint32_t w = m.origin[e];
        if (w < held_.size() && !held_[w] && (*cur_)[w] != (*from_)[w]) {
          Hold(w, e);
        }
      }
    }
  }
}

void RegionExecutor::HoldMovingHullVertices(const MeshView& m) {
  const uint32_t nt = m.num_half_edges / 3;
  const uint32_t g0 = hull_hint_;
  if (g0 >= nt || m.IsFree(g0) || !m.IsGhost(g0)) return;
  uint32_t g = g0;
  for (uint32_t steps = 0; steps <= nt; ++steps) {
    const uint32_t s = rules::SpokeOf(m, g);
    if (s == kNoEdge) return;
    const uint32_t v = m.origin[s];
    if (v < held_.size() && !held_[v] && (*cur_)[v] != (*from_)[v]) Hold(v, s);
    g = TriangleOf(m.twin[Next(s)]);
    if (g == g0) return;
  }
}

void RegionExecutor::HoldCulprits(const Mesh& mesh,
                                  std::vector<uint32_t> queue) {
  HoldCulpritsIn<false>(mesh.view(), Bounds{}, queue, nullptr, nullptr);
}

// Bounded (a region in parallel): it reads only triangles of b, holds only
// vertices whose star lies in b and off the hull (no other region reads or
// writes their position or held_ flag), and leaves the rest in *deferred
// for the serial pass; the held (vertex, half-edge) pairs go to *holds.
// Unbounded (serial): straight to the held lists (holds null). The
// positions of vertices a region does not own are not written by anyone
// while regions run.
template <bool kBounded>
void RegionExecutor::HoldCulpritsIn(const MeshView& m, RegionSlots b,
                                    std::vector<uint32_t>& queue,
                                    std::vector<uint32_t>* deferred,
                                    std::vector<HeldVertex>* holds) {
  const Vec2* p = cur_->data();
  const std::vector<Vec2>& from = *from_;
  std::vector<uint32_t> around;
  std::vector<uint32_t> rings[3];
  auto moving = [&](uint32_t u) {
    return u < held_.size() && !held_[u] && (*cur_)[u] != from[u];
  };
  for (size_t i = 0; i < queue.size(); ++i) {
    const uint32_t t = queue[i];
    if (kBounded && m.IsGhost(t) && !NeighboursIn(m, t, b)) {
      deferred->push_back(t);
      continue;
    }
    if (rules::TriangleOk(m, p, t)) continue;
    bool outside = false;
    const rules::FixProposal prop =
        kBounded ? rules::ProposeFixFlip(m, p, t, InBounds{b}, &outside)
                 : rules::ProposeFixFlip(m, p, t);
    if (outside) {
      deferred->push_back(t);
      continue;
    }
    if (prop.edge != kNoEdge) continue;
    // The vertices TriangleOk(t) reads (rules::Culprits' candidates), each
    // with a half-edge leaving it (vertex_edge may be stale while fixing).
    uint32_t cand[3], edge[3];
    if (!rules::DecidingEdges(m, t, edge)) continue;
    for (int k = 0; k < 3; ++k) cand[k] = m.origin[edge[k]];
    if (kBounded) {
      // Every vertex it may try or hold: its star in b, off the hull.
      bool owned = true;
      for (int k = 0; k < 3 && owned; ++k) {
        if (!moving(cand[k])) continue;
        rings[k].clear();
        if (!StarIn(m, edge[k], b)) {
          owned = false;
          break;
        }
        AppendStarFrom(m, edge[k], &rings[k]);
        for (uint32_t x : rings[k]) owned = owned && !m.IsGhost(x);
      }
      if (!owned) {
        deferred->push_back(t);
        continue;
      }
    }
    uint32_t culprit[3], culprit_edge[3];
    const int num_culprits =
        rules::Culprits(m, p, from.data(), t, moving, culprit, culprit_edge);
    for (int c = 0; c < num_culprits; ++c) {
      const uint32_t u = culprit[c];
      Hold(u, culprit_edge[c], holds);
      around.clear();
      if (kBounded) {
        for (int k = 0; k < 3; ++k) {
          if (edge[k] == culprit_edge[c]) around = rings[k];
        }
      } else {
        AppendStarAndHullRingFrom(m, culprit_edge[c], &around);
      }
      for (uint32_t x : around) {
        if (!rules::TriangleOk(m, p, x)) queue.push_back(x);
      }
    }
  }
}

bool RegionExecutor::DenseFix(Mesh& mesh, const std::vector<uint32_t>& moved,
                              const RegionStepPolicy& policy,
                              RegionStepStats* stats, std::string* reason) {
  (void)moved;
  const MeshView m = mesh.view();
  uint32_t* ve = mesh.mutable_vertex_edge().data();
  uint32_t* const across = LiveAcross();
  const uint32_t rt = policy.region_triangles;
  const uint32_t nt = mesh.num_triangles();
  Region serial;
  std::vector<uint32_t> around;
  for (int attempt = 0; attempt < policy.max_passes; ++attempt) {
    ++stats->fix_attempts;
    // Whether this attempt held moving neighbours of triangles stuck with
    // every vertex held.
    bool held_around_stuck = false;
    const Vec2* p = cur_->data();
    // Fix every region in parallel; nothing crosses a region boundary.
    tbb::parallel_for(tbb::blocked_range<size_t>(0, regions_.size(), 1),
                      [&](const tbb::blocked_range<size_t>& range) {
                        for (size_t r = range.begin(); r != range.end(); ++r) {
                          Region& g = regions_[r];
                          g.ClearWork();
                          if (g.invalid.empty() || Cancelled()) continue;
                          g.stack.assign(g.invalid.rbegin(), g.invalid.rend());
                          const Bounds b{static_cast<uint32_t>(r * rt),
                                         static_cast<uint32_t>(std::min<size_t>(
                                             nt, (r + 1) * size_t{rt}))};
                          FixLoop<true>(m, p, b, g.stack, g.waiting, g.deferred,
                                        &g.log, &g.counts, tri_mark_.data(), ve,
                                        across);
                        }
                      });
    if (Cancelled()) {
      // Back to the mesh of `from` (regions are independent: any order).
      for (auto it = regions_.rbegin(); it != regions_.rend(); ++it) {
        Undo(m, it->log, ve, across);
      }
      *reason = "cancelled";
      return false;
    }
    // The serial pass: boundary elements and region-stuck triangles.
    serial.ClearWork();
    for (Region& g : regions_) {
      serial.stack.insert(serial.stack.end(), g.waiting.rbegin(),
                          g.waiting.rend());
      serial.stack.insert(serial.stack.end(), g.deferred.rbegin(),
                          g.deferred.rend());
      stats->deferred += static_cast<uint32_t>(g.deferred.size());
    }
    FixLoop<false>(m, p, Bounds{}, serial.stack, serial.waiting,
                   serial.deferred, &serial.log, &serial.counts,
                   tri_mark_.data(), ve, across);
    // Stuck triangles, or a hull that winds twice: hold their culprits
    // (the moving hull vertices) where the mesh is now and go on fixing
    // around them (serially; they are few), instead of undoing the pass.
    for (int local = 0; local < 16; ++local) {
      const size_t before = held_list_.size();
      if (!serial.waiting.empty()) {
        HoldCulprits(mesh, serial.waiting);
        if (held_list_.size() == before) {
          for (uint32_t t : serial.waiting) {
            for (uint32_t e = 3 * t; e < 3 * t + 3; ++e) {
              const uint32_t v = m.origin[e];
              if (v < held_.size() && !held_[v] && (*cur_)[v] != (*from_)[v]) {
                Hold(v, e);
              }
            }
          }
        }
        if (held_list_.size() == before) {
          // Every vertex of the stuck triangles is held or never moved: a
          // triangle made by this pass's flips that turned over when its
          // vertices were held (1M points, σ 0.1: about one step in ten).
          // Their moving neighbours are held too, here, as a repeated
          // attempt would do after undoing the whole pass.
          std::vector<uint32_t> vertices;
          for (uint32_t t : serial.waiting) {
            for (uint32_t e = 3 * t; e < 3 * t + 3; ++e) {
              vertices.push_back(m.origin[e]);
            }
          }
          HoldMovingNeighbours(mesh, vertices, &around);
          held_around_stuck |= held_list_.size() > before;
        }
      } else if (HullWindsOnceFrom(mesh, *cur_, &hull_hint_)) {
        break;
      } else {
        HoldMovingHullVertices(m);
      }
      if (held_list_.size() == before) break;
      serial.stack.swap(serial.waiting);
      serial.waiting.clear();
      for (size_t i = before; i < held_list_.size(); ++i) {
        around.clear();
        AppendStarAndHullRingFrom(m, held_edge_[i], &around);
        for (uint32_t t : around) {
          serial.stack.push_back(t);
          tri_mark_[t] = 1;
        }
      }
      FixLoop<false>(m, p, Bounds{}, serial.stack, serial.waiting,
                     serial.deferred, &serial.log, &serial.counts,
                     tri_mark_.data(), ve, across);
    }
    const bool stuck = !serial.waiting.empty();
    if (!stuck && HullWindsOnceFrom(mesh, *cur_, &hull_hint_)) {
      for (Region& g : regions_) {
        stats->flips += g.counts;
        g.fix_log.swap(g.log);
      }
      stats->flips += serial.counts;
      fix_serial_log_.swap(serial.log);
      ++stats->flips.fix_rounds;
      return true;
    }
    // Stuck (or a hull that winds twice): hold the moving vertices of the
    // stuck triangles (or of the hull) too, undo everything and repeat.
    std::vector<uint32_t> culprits;
    if (stuck) {
      for (uint32_t t : serial.waiting) {
        for (uint32_t e = 3 * t; e < 3 * t + 3; ++e) {
          culprits.push_back(m.origin[e]);
        }
      }
    } else {
      for (uint32_t t = 0; t < nt; ++t) {
        if (m.IsFree(t) || !m.IsGhost(t)) continue;
        for (uint32_t e = 3 * t; e < 3 * t + 3; ++e) {
          culprits.push_back(m.origin[e]);
        }
      }
    }
    Undo(m, serial.log, ve, across);
    for (auto it = regions_.rbegin(); it != regions_.rend(); ++it) {
      Undo(m, it->log, ve, across);
    }
    // Hold the culprits; if they are all held already, their moving
    // neighbours too (in the restored mesh). An attempt that held the
    // neighbours of triangles stuck with every vertex held is repeated even
    // if no more can be held: undone, its holds change the flips that made
    // those triangles.
    const size_t held_before = held_list_.size();
    for (uint32_t v : culprits) {
      if (v >= held_.size() || held_[v] || (*cur_)[v] == (*from_)[v]) continue;
      Hold(v, mesh.vertex_edge()[v]);
    }
    if (held_list_.size() == held_before) {
      HoldMovingNeighbours(mesh, culprits, &around);
    }
    const bool held_any = held_list_.size() > held_before;
    // Every held vertex's star is repaired afresh (the undo moved some).
    for (uint32_t v : held_list_) {
      around.clear();
      AppendStarAndHullRing(mesh, v, &around);
      for (uint32_t t : around) {
        regions_[t / rt].invalid.push_back(t);
        tri_mark_[t] = 1;
      }
    }
    if (!held_any && !held_around_stuck) {
      *reason = stuck ? "fixing stuck with every culprit held"
                      : "hull winds twice with every hull vertex held";
      return false;
    }
  }
  *reason = absl::StrCat("fixing still stuck after ", policy.max_passes,
                         " dense attempts");
  return false;
}

bool RegionExecutor::MoveHeldInRegion(
    Mesh& mesh, uint32_t v, const Vec2& target, const RegionStepPolicy& policy,
    uint32_t lo, uint32_t hi, RegionStepStats* stats,
    std::vector<uint32_t>* late_edges, std::vector<uint32_t>* kept) {
  const MeshView m = mesh.view();
  uint32_t* ve = mesh.mutable_vertex_edge().data();
  uint32_t* const across = LiveAcross();
  const Bounds b{lo, hi};
  thread_local std::vector<uint32_t> around, stack, waiting, deferred, log,
      flipped;
  // Only this region writes v's vertex_edge while v's star lies in it.
  const uint32_t e0 =
      std::atomic_ref<uint32_t>(ve[v]).load(std::memory_order_relaxed);
  if (e0 == kNoEdge || !b.In(TriangleOf(e0)) || !StarIn(m, e0, b)) {
    return false;
  }
  around.clear();
  AppendStarFrom(m, e0, &around);
  for (uint32_t t : around) {
    if (m.IsGhost(t)) return false;  // near the hull: the serial pass
  }
  FlipCounts counts;
  Vec2 goal = target;
  int halvings = 0;
  while (true) {
    const Vec2 old = (*cur_)[v];
    (*cur_)[v] = goal;
    const Vec2* p = cur_->data();
    around.clear();
    AppendStarFrom(m, mesh.vertex_edge()[v], &around);
    stack.clear();
    for (uint32_t t : around) {
      if (!rules::TriangleOk(m, p, t)) stack.push_back(t);
    }
    waiting.clear();
    deferred.clear();
    log.clear();
    flipped.clear();
    FlipCounts c;
    FixLoop<true>(m, p, b, stack, waiting, deferred, &log, &c, tri_mark_.data(),
                  ve, across, &flipped);
    if (!deferred.empty() || c.hull_absorb + c.hull_release > 0) {
      // Reaches out of the region or changes the hull: the serial pass.
      Undo(m, log, ve, across);
      (*cur_)[v] = old;
      stats->flips += counts;
      return false;
    }
    if (waiting.empty()) {
      counts += c;
      kept->insert(kept->end(), log.begin(), log.end());
      SeedLegalizeAfterMove(m, mesh.vertex_edge()[v], flipped, &around, &stack);
      // Edges that cross the region are legalized in the serial pass.
      LegalizeLoop<true>(m, p, b, stack, *late_edges, &counts, tri_mark_.data(),
                         ve, across, kept);
      if (goal == target) {
        stats->flips += counts;
        return true;
      }
      goal = target;
      continue;
    }
    Undo(m, log, ve, across);
    (*cur_)[v] = old;
    if (!Bisect(old, policy, &goal, &halvings, stats)) {
      stats->flips += counts;
      return false;
    }
  }
}

bool RegionExecutor::MoveHeld(Mesh& mesh, uint32_t v, const Vec2& target,
                              const RegionStepPolicy& policy,
                              RegionStepStats* stats,
                              std::vector<uint32_t>* kept) {
  const MeshView m = mesh.view();
  uint32_t* ve = mesh.mutable_vertex_edge().data();
  uint32_t* const across = LiveAcross();
  std::vector<uint32_t> around, stack, waiting, deferred, log, flipped;
  FlipCounts counts;
  Vec2 goal = target;
  int halvings = 0;
  while (true) {
    const Vec2 old = (*cur_)[v];
    (*cur_)[v] = goal;
    const Vec2* p = cur_->data();
    around.clear();
    AppendStarAndHullRing(mesh, v, &around);
    bool hull_near = false;
    stack.clear();
    for (uint32_t t : around) {
      if (m.IsGhost(t)) hull_near = true;
      if (!rules::TriangleOk(m, p, t)) stack.push_back(t);
    }
    waiting.clear();
    log.clear();
    flipped.clear();
    FlipCounts c;
    FixLoop<false>(m, p, Bounds{}, stack, waiting, deferred, &log, &c,
                   tri_mark_.data(), ve, across, &flipped);
    const bool hull_changed = c.hull_absorb + c.hull_release > 0;
    const bool ok =
        waiting.empty() && (!(hull_near || hull_changed) ||
                            HullWindsOnceFrom(mesh, *cur_, &hull_hint_));
    if (ok) {
      counts += c;
      kept->insert(kept->end(), log.begin(), log.end());
      // Legalize around v and wherever fixing flipped.
      SeedLegalizeAfterMove(m, mesh.vertex_edge()[v], flipped, &around, &stack);
      LegalizeLoop<false>(m, p, Bounds{}, stack, deferred, &counts,
                          tri_mark_.data(), ve, across, kept);
      if (goal == target) {
        stats->flips += counts;
        return true;
      }
      goal = target;
      continue;
    }
    Undo(m, log, ve, across);
    (*cur_)[v] = old;
    if (!Bisect(old, policy, &goal, &halvings, stats)) {
      stats->flips += counts;
      return false;
    }
  }
}

bool RegionExecutor::Step(Mesh& mesh, const std::vector<Vec2>& from,
                          std::vector<Vec2>& to,
                          const std::vector<uint32_t>& moved,
                          const RegionStepPolicy& policy,
                          RegionStepStats* stats,
                          std::vector<uint32_t>* removed,
                          std::vector<uint32_t>* hints, std::string* reason,
                          const CancelToken* cancel) {
  cancel_ = cancel;
  from_ = &from;
  cur_ = &to;
  held_list_.clear();
  held_edge_.clear();
  held_target_.clear();
  for (Region& g : regions_) g.holds.clear();
  // Every held vertex's entry back to its target, however the step ends
  // (an exception included; the regions' holds not yet gathered into
  // held_list_ too).
  struct PutBack {
    RegionExecutor* x;
    std::vector<Vec2>& to;
    ~PutBack() {
      for (size_t i = 0; i < x->held_list_.size(); ++i) {
        to[x->held_list_[i]] = x->held_target_[i];
      }
      for (const Region& g : x->regions_) {
        for (const HeldVertex& h : g.holds) to[h.v] = h.target;
      }
      x->cur_ = nullptr;
      x->from_ = nullptr;
      x->cancel_ = nullptr;
    }
  } put_back{this, to};
  const bool ok =
      StepInPlace(mesh, moved, policy, stats, removed, hints, reason);
  if (ok) {
    // Keep the across entries when this step flipped little (the next is
    // likely to as well); those kept through the step name this mesh now
    // (until anything else touches it).
    const FlipCounts& f = stats->flips;
    const uint64_t flips =
        f.interior_fix + f.hull_absorb + f.hull_release + f.delaunay;
    across_wanted_ = double(flips) <=
                     policy.keep_across_flips * double(mesh.num_triangles());
    if (across_live_ && across_wanted_) {
      across_version_ = mesh.content_version();
    }
  }
  return ok;
}

bool RegionExecutor::StepInPlace(Mesh& mesh, const std::vector<uint32_t>& moved,
                                 const RegionStepPolicy& policy,
                                 RegionStepStats* stats,
                                 std::vector<uint32_t>* removed,
                                 std::vector<uint32_t>* hints,
                                 std::string* reason) {
  auto t0 = std::chrono::steady_clock::now();
  // A stop once fixing began undoes every flip (and vertex_edge change) of
  // the step; before it, nothing changed.
  auto stop = [&](bool changed) {
    if (changed) UndoStep(mesh);
    stats->cancelled = true;
    *reason = "cancelled";
    return false;
  };
  const uint32_t n = static_cast<uint32_t>(cur_->size());
  const uint32_t nt = mesh.num_triangles();
  const bool dense = moved.size() > policy.sparse_fraction * n;
  // The across entries: still those of this mesh when nothing touched it
  // since the last step that kept them (read before view() below renews
  // the number); a dense scan fills them when not, region by region; a
  // sparse step keeps them only when they are current (a fill would cost
  // what the step does).
  const bool keep = policy.keep_across_flips > 0;
  const bool across_current = keep && KeepsAcross(mesh);
  across_version_ = 0;
  host_change_ = false;
  across_live_ = keep && (across_current || (dense && across_wanted_));
  stats->across_kept = dense && across_current;
  if (across_live_ && !across_current) {
    across_.resize(mesh.num_half_edges());
  }
  const uint32_t rt = std::max<uint32_t>(policy.region_triangles, 1);
  const size_t num_regions = (size_t{nt} + rt - 1) / rt;
  regions_.resize(num_regions);
  for (Region& g : regions_) {
    g.invalid.clear();
    g.illegal.clear();
    g.log.clear();
    g.fix_log.clear();
    g.held_log.clear();
  }
  serial_.log.clear();
  for (Region& cg : coarse_) cg.log.clear();
  fix_serial_log_.clear();
  held_log_.clear();
  removals_.clear();
  saved_.clear();
  held_.assign(n, 0);
  tri_mark_.assign(nt, 0);
  RegionStepPolicy pol = policy;
  pol.region_triangles = rt;
  const MeshView m = mesh.view();
  // fn(r, lo, hi) for every region r in parallel; [lo, hi): its slots.
  auto for_each_region = [&](auto&& fn) {
    tbb::parallel_for(tbb::blocked_range<size_t>(0, num_regions, 1),
                      [&](const tbb::blocked_range<size_t>& range) {
                        for (size_t r = range.begin(); r != range.end(); ++r) {
                          fn(r, static_cast<uint32_t>(r * rt),
                             static_cast<uint32_t>(
                                 std::min<size_t>(nt, (r + 1) * size_t{rt})));
                        }
                      });
  };

  // 1. Scan: invalid triangles and illegal edges for `to`.
  const double rebuild_cost =
      policy.rebuild_fixed_cost + policy.rebuild_point_cost * double(n);
  if (dense && policy.held_vertex_cost > 0 && nt >= 4 * kRebuildSamples) {
    // Large motion: a sample of the triangles (evenly spaced slots, the
    // same for any thread count) that clearly predicts a rebuild saves the
    // scan the rebuild would follow.
    const Vec2* p = cur_->data();
    uint32_t hopeless = 0;
    for (uint32_t i = 0; i < kRebuildSamples; ++i) {
      const uint32_t t =
          static_cast<uint32_t>(uint64_t{i} * nt / kRebuildSamples);
      if (!rules::TriangleOk(m, p, t) &&
          rules::ProposeFixFlip(m, p, t).edge == kNoEdge) {
        ++hopeless;
      }
    }
    const double expected = double(hopeless) * nt / kRebuildSamples;
    if (policy.held_vertex_cost * expected > 2.0 * rebuild_cost) {
      *reason = absl::StrCat(
          "about ", static_cast<uint64_t>(expected),
          " triangles cannot be repaired by flips (",
          static_cast<int>(100.0 * hopeless / kRebuildSamples),
          "% of a sample of ", kRebuildSamples, "): rebuilding is cheaper");
      stats->scan_seconds += SecondsSince(t0);
      return false;
    }
  }
  // 2. (run after the scan below) Hold back the culprits of the triangles
  //    no flip can repair: each region holds what it can by itself
  //    (vertices whose star it holds) once every region has classified its
  //    invalid triangles (`classify`, core/flip_rules.h's bounded proposal,
  //    right after its scan); the rest is done serially afterwards. The
  //    held vertices' stars are repaired again.
  std::vector<uint32_t> hopeless_in(num_regions, 0);
  auto hold_back = [&](size_t r, uint32_t lo, uint32_t hi) {
    Region& g = regions_[r];
    const Bounds b{lo, hi};
    g.deferred.clear();
    g.holds.clear();
    hopeless_in[r] = static_cast<uint32_t>(g.stack.size());
    if (g.stack.empty()) return;
    HoldCulpritsIn<true>(m, b, g.stack, &g.deferred, &g.holds);
    // A held vertex's star lies in the region, off the hull.
    std::vector<uint32_t> around;
    for (const HeldVertex& h : g.holds) {
      around.clear();
      AppendStarFrom(m, h.edge, &around);
      for (uint32_t t : around) {
        tri_mark_[t] = 1;
        g.invalid.push_back(t);
      }
    }
  };
  // Which invalid triangles of a region no flip can repair (g.stack), and
  // which a region cannot decide by itself (g.waiting): right after the
  // region's scan, while its triangles are in cache. Nothing is held back
  // before every region has been classified, so every proposal reads the
  // positions of `to`.
  auto classify = [&](Region& g, Bounds b) {
    const Vec2* p = cur_->data();
    g.stack.clear();
    g.waiting.clear();
    for (uint32_t t : g.invalid) {
      bool outside = false;
      const rules::FixProposal prop =
          rules::ProposeFixFlip(m, p, t, InBounds{b}, &outside);
      if (outside) {
        g.waiting.push_back(t);  // decided serially
      } else if (prop.edge == kNoEdge) {
        g.stack.push_back(t);
      }
    }
  };
  if (dense) {
    const Vec2* p = cur_->data();
    for_each_region([&](size_t r, uint32_t lo, uint32_t hi) {
      if (Cancelled()) return;
      Region& g = regions_[r];
      if (!across_live_) {
        ScanTriangles(m, p, lo, hi, &g.invalid, &g.illegal);
      } else {
        if (!across_current) FillAcross(m, lo, hi, across_.data());
        ScanTriangles(m, p, across_.data(), lo, hi, &g.invalid, &g.illegal);
      }
      classify(g, Bounds{lo, hi});
    });
  } else {
    // Mark the triangles around the moved vertices (every edge of a marked
    // triangle is re-tested by legalizing), then each region tests its
    // marked triangles: in parallel, no sort.
    const uint32_t* ve = mesh.vertex_edge().data();
    uint8_t* mark = tri_mark_.data();
    tbb::parallel_for(tbb::blocked_range<size_t>(0, moved.size(), 256),
                      [&](const tbb::blocked_range<size_t>& range) {
                        std::vector<uint32_t> around;
                        for (size_t i = range.begin(); i != range.end(); ++i) {
                          around.clear();
                          AppendStarAndHullRingFrom(m, ve[moved[i]], &around);
                          for (uint32_t t : around) {
                            std::atomic_ref<uint8_t>(mark[t]).store(
                                1, std::memory_order_relaxed);
                          }
                        }
                      });
    const Vec2* p = cur_->data();
    for_each_region([&](size_t r, uint32_t lo, uint32_t hi) {
      Region& g = regions_[r];
      for (uint32_t t = lo; t < hi; ++t) {
        if (mark[t] && !rules::TriangleOk(m, p, t)) g.invalid.push_back(t);
      }
      classify(g, Bounds{lo, hi});
    });
  }
  if (Cancelled()) return stop(false);
  // After every region's scan: a scan reads the positions of apexes
  // across its boundary, which holding back may change.
  for_each_region(hold_back);
  {
    // What regions left: triangles whose repair reads other regions
    // (decided here), and hopeless ones a region could not hold back.
    const Vec2* p = cur_->data();
    uint64_t hopeless = 0;
    std::vector<uint32_t> rest;
    for (size_t r = 0; r < num_regions; ++r) {
      const Region& g = regions_[r];
      hopeless += hopeless_in[r];
      rest.insert(rest.end(), g.deferred.begin(), g.deferred.end());
      for (uint32_t t : g.waiting) {
        if (rules::ProposeFixFlip(m, p, t).edge == kNoEdge) {
          rest.push_back(t);
          ++hopeless;
        }
      }
    }
    const double local_cost = policy.held_vertex_cost * double(hopeless);
    if (policy.held_vertex_cost > 0 && local_cost > rebuild_cost) {
      *reason =
          absl::StrCat(hopeless, " triangles cannot be repaired by flips (",
                       static_cast<int>(100.0 * hopeless / std::max(1u, nt)),
                       "% of all): rebuilding is cheaper");
      stats->scan_seconds += SecondsSince(t0);
      return false;
    }
    for (const Region& g : regions_) {
      for (const HeldVertex& h : g.holds) {
        held_list_.push_back(h.v);
        held_edge_.push_back(h.edge);
        held_target_.push_back(h.target);
      }
    }
    const size_t serial_begin = held_list_.size();
    HoldCulprits(mesh, std::move(rest));
    std::vector<uint32_t> around;
    for (size_t i = serial_begin; i < held_list_.size(); ++i) {
      around.clear();
      AppendStarAndHullRingFrom(m, held_edge_[i], &around);
      for (uint32_t t : around) {
        tri_mark_[t] = 1;
        regions_[t / rt].invalid.push_back(t);
      }
    }
  }
  stats->scan_seconds += SecondsSince(t0);
  t0 = std::chrono::steady_clock::now();

  if (Cancelled()) return stop(false);
  // 3. Fix. A failed or stopped fix has undone its flips.
  if (!DenseFix(mesh, moved, pol, stats, reason)) {
    stats->fix_seconds += SecondsSince(t0);
    if (Cancelled()) return stop(false);
    return false;
  }
  stats->fix_seconds += SecondsSince(t0);
  t0 = std::chrono::steady_clock::now();

  // 4. Legalize: the illegal edges of the scan plus every edge of a triangle
  //    that changed (flips, held vertices, sparse motion). vertex_edge stays
  //    valid throughout (RepairVertexEdges).
  // 5. Held vertices move alone: each region moves those whose star it
  //    holds right after legalizing (its slots still in cache), when
  //    everything the move touches stays in the region; the edges that
  //    leave it join the serial pass of legalizing. Then, serially, the
  //    rest (near the hull, across regions, stuck); the ones that cannot
  //    move are removed.
  stats->held = static_cast<uint32_t>(held_list_.size());
  // Held vertices by their index in held_list_ (held_target_[i]: where
  // held_list_[i] goes).
  std::vector<uint32_t> left;
  std::vector<RegionStepStats> rstats(num_regions);
  {
    const Vec2* p = cur_->data();
    uint32_t* ve = mesh.mutable_vertex_edge().data();
    uint32_t* const across = LiveAcross();
    for (Region& g : regions_) g.held.clear();
    for (uint32_t i = 0; i < held_list_.size(); ++i) {
      const uint32_t e = ve[held_list_[i]];
      if (e == kNoEdge) {
        left.push_back(i);
      } else {
        regions_[TriangleOf(e) / rt].held.push_back(i);
      }
    }
    for_each_region([&](size_t r, uint32_t lo, uint32_t hi) {
      Region& g = regions_[r];
      g.ClearWork();  // before the poll: a stop undoes every log
      if (Cancelled()) return;
      g.stack.assign(g.illegal.rbegin(), g.illegal.rend());
      const uint8_t* mark = tri_mark_.data();
      uint32_t t = hi;
      while (t > lo) {
        // Eight unmarked slots at once (most are).
        if (t % 8 == 0 && t - 8 >= lo) {
          uint64_t word;
          std::memcpy(&word, mark + t - 8, 8);
          if (word == 0) {
            t -= 8;
            continue;
          }
        }
        --t;
        if (!mark[t]) continue;
        for (uint32_t e = 3 * t + 3; e-- > 3 * t;) g.stack.push_back(e);
      }
      LegalizeLoop<true>(m, p, Bounds{lo, hi}, g.stack, g.deferred, &g.counts,
                         tri_mark_.data(), ve, across, &g.log,
                         g.illegal.size());
      for (uint32_t i : g.held) {
        if (Cancelled() ||
            !MoveHeldInRegion(mesh, held_list_[i], held_target_[i], pol, lo, hi,
                              &rstats[r], &g.deferred, &g.held_log)) {
          g.waiting.push_back(i);
        }
      }
    });
    if (Cancelled()) return stop(true);
    // What crossed region boundaries: first coarse regions (kCoarse
    // regions each) in parallel, each taking its regions' deferred edges
    // and then the held vertices they could not move; then serially what
    // crosses those.
    // (In 64 bits: in 32, regions of 2^29 triangles or more wrapped it, to
    // 0 for multiples of 2^29.)
    const size_t crt = size_t{rt} * kCoarse;
    const size_t num_coarse = (size_t{nt} + crt - 1) / crt;
    coarse_.resize(num_coarse);
    std::vector<RegionStepStats> cstats(num_coarse);
    for (const Region& g : regions_) {
      stats->deferred += static_cast<uint32_t>(g.deferred.size());
      stats->flips += g.counts;
    }
    tbb::parallel_for(
        tbb::blocked_range<size_t>(0, coarse_.size(), 1),
        [&](const tbb::blocked_range<size_t>& range) {
          for (size_t c = range.begin(); c != range.end(); ++c) {
            Region& cg = coarse_[c];
            cg.ClearWork();
            const size_t last = std::min(num_regions, (c + 1) * kCoarse);
            for (size_t r = c * kCoarse; r < last; ++r) {
              const Region& g = regions_[r];
              cg.stack.insert(cg.stack.end(), g.deferred.rbegin(),
                              g.deferred.rend());
            }
            const Bounds b{
                static_cast<uint32_t>(c * crt),
                static_cast<uint32_t>(std::min<size_t>(nt, (c + 1) * crt))};
            LegalizeLoop<true>(m, p, b, cg.stack, cg.deferred, &cg.counts,
                               tri_mark_.data(), ve, across, &cg.log);
            // The held vertices its regions could not move.
            for (size_t r = c * kCoarse; r < last; ++r) {
              for (uint32_t i : regions_[r].waiting) {
                if (Cancelled() ||
                    !MoveHeldInRegion(mesh, held_list_[i], held_target_[i], pol,
                                      b.lo, b.hi, &cstats[c], &cg.deferred,
                                      &cg.log)) {
                  cg.waiting.push_back(i);
                }
              }
            }
          }
        });
    if (Cancelled()) return stop(true);
    Region& serial = serial_;
    serial.ClearWork();
    for (size_t c = 0; c < coarse_.size(); ++c) {
      const Region& cg = coarse_[c];
      serial.stack.insert(serial.stack.end(), cg.deferred.rbegin(),
                          cg.deferred.rend());
      stats->flips += cg.counts;
      stats->flips += cstats[c].flips;
      stats->halvings += cstats[c].halvings;
      left.insert(left.end(), cg.waiting.begin(), cg.waiting.end());
    }
    for (size_t r = 0; r < num_regions; ++r) {
      stats->flips += rstats[r].flips;
      stats->halvings += rstats[r].halvings;
    }
    LegalizeLoop<false>(m, p, Bounds{}, serial.stack, serial.deferred,
                        &serial.counts, tri_mark_.data(), ve, across,
                        &serial.log);
    stats->flips += serial.counts;
    ++stats->flips.legalize_rounds;
    stats->held_serial = static_cast<uint32_t>(left.size());
  }
  stats->legalize_seconds += SecondsSince(t0);
  t0 = std::chrono::steady_clock::now();
  if (Cancelled()) return stop(true);
  for (size_t i = 0; i < left.size(); ++i) {
    if (i % 16 == 15 && Cancelled()) {
      stats->held_seconds += SecondsSince(t0);
      return stop(true);
    }
    const uint32_t v = held_list_[left[i]];
    if (MoveHeld(mesh, v, held_target_[left[i]], pol, stats, &held_log_)) {
      continue;
    }
    const uint32_t e = mesh.vertex_edge()[v];
    const uint32_t hint = mesh.view().Dest(e);
    if (!RemoveHeld(mesh, v, stats)) {
      *reason = "could not remove a vertex for re-insertion";
      UndoStep(mesh);
      removed->clear();
      stats->held_seconds += SecondsSince(t0);
      return false;
    }
    (*hints)[v] = hint;
    removed->push_back(v);
  }
  stats->held_seconds += SecondsSince(t0);
  return true;
}

bool RegionExecutor::RemoveHeld(Mesh& mesh, uint32_t v,
                                RegionStepStats* stats) {
  const MeshView m = mesh.view();
  // The triangles VertexOps::Remove may rewrite: v's star (origins and
  // twins) and the star's neighbours (the twins of the outer edges).
  const size_t first = saved_.size();
  removals_.push_back({held_log_.size(), first, mesh.num_free_triangles()});
  const uint32_t e0 = mesh.vertex_edge()[v];
  auto save = [&](uint32_t t) {
    SavedTriangle st{t, {}, {}};
    for (int k = 0; k < 3; ++k) {
      st.origin[k] = m.origin[3 * t + k];
      st.twin[k] = m.twin[3 * t + k];
    }
    saved_.push_back(st);
  };
  uint32_t e = e0;
  size_t steps = 0;
  do {
    if (++steps > (1u << 16)) return false;  // as Remove: not a star
    const uint32_t t = TriangleOf(e);
    save(t);
    save(TriangleOf(m.twin[Next(e)]));
    e = m.twin[Prev(e)];
  } while (e != e0);
  std::vector<uint32_t> touched;
  if (!VertexOps::Remove(mesh, *cur_, v, &touched, nullptr)) return false;
  uint32_t* const across = LiveAcross();
  if (across) {
    // Every slot the removal rewrote or freed is a star slot; the star's
    // neighbours' entries across it are refreshed with it.
    for (size_t i = first; i < saved_.size(); ++i) {
      RefreshAcross(m, saved_[i].slot, across);
    }
  }
  LegalizeSerial(mesh, *cur_, touched, &stats->flips, &held_log_, across);
  return true;
}

void RegionExecutor::UndoStep(Mesh& mesh) {
  // Restored removals rewrite slots wholesale: the next step fills the
  // across entries afresh.
  across_live_ = false;
  const MeshView m = mesh.view();
  uint32_t* ve = mesh.mutable_vertex_edge().data();
  // The serial held moves and removals, newest first.
  size_t end = held_log_.size();
  for (size_t r = removals_.size() + 1; r-- > 0;) {
    const size_t begin = r > 0 ? removals_[r - 1].log_size : 0;
    for (size_t i = end; i-- > begin;) m.Unflip(held_log_[i]);
    end = begin;
    if (r == 0) break;
    const Removal& rm = removals_[r - 1];
    const size_t last =
        r < removals_.size() ? removals_[r].saved : saved_.size();
    // Saved in star order; a triangle saved twice holds the same image.
    for (size_t i = rm.saved; i < last; ++i) {
      const SavedTriangle& st = saved_[i];
      for (int k = 0; k < 3; ++k) {
        m.origin[3 * st.slot + k] = st.origin[k];
        m.twin[3 * st.slot + k] = st.twin[k];
      }
    }
    mesh.TakeBackFreed(rm.free_slots);
  }
  // Legalizing's serial pass; the coarse regions'; each region's held moves
  // and legalizing; fixing (the serial pass, then the regions'). Regions'
  // flips lie in their own slots, so they are undone in parallel.
  auto undo_each = [&](const std::vector<Region>& list, auto&& undo) {
    tbb::parallel_for(tbb::blocked_range<size_t>(0, list.size(), 1),
                      [&](const tbb::blocked_range<size_t>& range) {
                        for (size_t r = range.begin(); r != range.end(); ++r) {
                          undo(list[r]);
                        }
                      });
  };
  Undo(m, serial_.log, ve, nullptr);
  undo_each(coarse_, [&](const Region& g) { Undo(m, g.log, ve, nullptr); });
  undo_each(regions_, [&](const Region& g) {
    Undo(m, g.held_log, ve, nullptr);
    Undo(m, g.log, ve, nullptr);
  });
  Undo(m, fix_serial_log_, ve, nullptr);
  undo_each(regions_,
            [&](const Region& g) { Undo(m, g.fix_log, ve, nullptr); });
  held_log_.clear();
  removals_.clear();
  saved_.clear();
  // The restored removals' stars.
  mesh.RebuildVertexEdges();
}

bool RegionExecutor::FixSerial(Mesh& mesh, const std::vector<Vec2>& pos,
                               const std::vector<uint32_t>& invalid,
                               FlipCounts* counts,
                               std::vector<uint32_t>* touched,
                               std::vector<uint32_t>* log,
                               std::vector<uint32_t>* stuck, uint32_t* across) {
  const MeshView m = mesh.view();
  std::vector<uint32_t> stack(invalid.rbegin(), invalid.rend());
  std::vector<uint32_t> waiting, deferred, own_log;
  FlipCounts c;
  std::vector<uint32_t>* lg = log ? log : &own_log;
  // (Both triangles of each flip are taken as it runs: read from the log
  // afterwards, a half-edge's twin may have moved on with a later flip.)
  FixLoop<false>(m, pos.data(), Bounds{}, stack, waiting, deferred, lg, &c,
                 nullptr, mesh.mutable_vertex_edge().data(), across, touched);
  if (counts) *counts += c;
  if (!waiting.empty()) {
    if (stuck) stuck->insert(stuck->end(), waiting.begin(), waiting.end());
    return false;
  }
  uint32_t hint = 0;
  return HullWindsOnceFrom(mesh, pos, &hint);
}

void RegionExecutor::LegalizeSerial(Mesh& mesh, const std::vector<Vec2>& pos,
                                    const std::vector<uint32_t>& seeds,
                                    FlipCounts* counts,
                                    std::vector<uint32_t>* log,
                                    uint32_t* across) {
  const MeshView m = mesh.view();
  std::vector<uint32_t> stack, deferred;
  stack.reserve(3 * seeds.size());
  for (auto it = seeds.rbegin(); it != seeds.rend(); ++it) {
    for (uint32_t e = 3 * *it + 3; e-- > 3 * *it;) stack.push_back(e);
  }
  FlipCounts c;
  LegalizeLoop<false>(m, pos.data(), Bounds{}, stack, deferred, &c, nullptr,
                      mesh.mutable_vertex_edge().data(), across, log);
  if (counts) *counts += c;
}

bool RegionExecutor::BeginHostChange(const Mesh& mesh) {
  host_change_ = KeepsAcross(mesh);
  across_version_ = 0;
  return host_change_;
}

uint32_t* RegionExecutor::HostChangeAcross(const Mesh& mesh) {
  if (!host_change_) return nullptr;
  if (across_.size() < mesh.num_half_edges()) {
    across_.resize(mesh.num_half_edges(), kNoVertex);
  }
  return across_.data();
}

void RegionExecutor::EndHostChange(const Mesh& mesh) {
  if (host_change_ && across_.size() == mesh.num_half_edges()) {
    across_version_ = mesh.content_version();
  }
  host_change_ = false;
}

absl::Status RegionExecutor::CheckAcross(const Mesh& mesh) const {
  if (!KeepsAcross(mesh)) return absl::OkStatus();
  const MeshView m = mesh.view();
  for (uint32_t e = 0; e < m.num_half_edges; ++e) {
    const uint32_t want = m.origin[e] == kNoVertex ? kNoVertex : m.Across(e);
    if (across_[e] != want) {
      return absl::InternalError(absl::StrCat("kept apex across half-edge ", e,
                                              " is ", across_[e], ", not ",
                                              want, " (region executor)"));
    }
  }
  return absl::OkStatus();
}

}  // namespace kinetri::core
