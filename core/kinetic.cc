// CPU executor of the kinetic update: parallel fixing and legalizing rounds.
#include "core/kinetic.h"

#include <tbb/parallel_sort.h>

#include <algorithm>
#include <atomic>
#include <numeric>

#include "core/flip_rules.h"
#include "core/hull.h"
#include "core/parallel.h"

namespace kinetri::core {
namespace {

constexpr size_t kBlock = 4096;

template <typename Pred>
std::vector<uint32_t> Filter(size_t n, Pred&& pred) {
  return FilterIndices(n, std::forward<Pred>(pred));
}

void SortUnique(std::vector<uint32_t>& v) {
  tbb::parallel_sort(v.begin(), v.end());
  v.erase(std::unique(v.begin(), v.end()), v.end());
}

inline uint32_t Canonical(const MeshView& m, uint32_t e) {
  return std::min(e, m.twin[e]);
}

// Resolves conflicts among `edges` (sorted, unique): returns the winners.
// `vertex_of` (optional) holds two vertices per proposal that it must also
// claim (kNoVertex: none).
std::vector<uint32_t> SelectIndependent(const MeshView& m,
                                        const std::vector<uint32_t>& edges,
                                        const std::vector<uint32_t>* vertex_of,
                                        std::vector<uint32_t>& tri_claim,
                                        std::vector<uint32_t>& vert_claim) {
  const size_t n = edges.size();
  ParallelFor(0, n, [&](size_t i) {
    uint32_t fp[6];
    rules::FlipFootprint(m, edges[i], fp);
    for (uint32_t t : fp) AtomicMin(&tri_claim[t], edges[i]);
    if (vertex_of) {
      for (int k = 0; k < 2; ++k) {
        const uint32_t v = (*vertex_of)[2 * i + k];
        if (v < vert_claim.size()) AtomicMin(&vert_claim[v], edges[i]);
      }
    }
  });
  std::vector<uint32_t> win_idx = Filter(n, [&](size_t i) {
    uint32_t fp[6];
    rules::FlipFootprint(m, edges[i], fp);
    for (uint32_t t : fp) {
      if (tri_claim[t] != edges[i]) return false;
    }
    if (vertex_of) {
      for (int k = 0; k < 2; ++k) {
        const uint32_t v = (*vertex_of)[2 * i + k];
        if (v < vert_claim.size() && vert_claim[v] != edges[i]) return false;
      }
    }
    return true;
  });
  ParallelFor(0, n, [&](size_t i) {
    uint32_t fp[6];
    rules::FlipFootprint(m, edges[i], fp);
    // (Several claimants may reset one slot at once.)
    for (uint32_t t : fp) AtomicStore(&tri_claim[t], kNoEdge);
    if (vertex_of) {
      for (int k = 0; k < 2; ++k) {
        const uint32_t v = (*vertex_of)[2 * i + k];
        if (v < vert_claim.size()) AtomicStore(&vert_claim[v], kNoEdge);
      }
    }
  });
  std::vector<uint32_t> winners(win_idx.size());
  for (size_t i = 0; i < win_idx.size(); ++i) winners[i] = win_idx[i];
  return winners;  // indices into edges
}

}  // namespace

FlipCounts& FlipCounts::operator+=(const FlipCounts& o) {
  interior_fix += o.interior_fix;
  hull_absorb += o.hull_absorb;
  hull_release += o.hull_release;
  delaunay += o.delaunay;
  fix_rounds += o.fix_rounds;
  legalize_rounds += o.legalize_rounds;
  return *this;
}

std::vector<uint32_t> KineticExecutor::TrianglesAround(
    const Mesh& mesh, const std::vector<uint32_t>& vertices) {
  const MeshView m = mesh.view();
  const auto& ve = mesh.vertex_edge();
  std::vector<std::vector<uint32_t>> parts((vertices.size() + kBlock - 1) /
                                           kBlock);
  ParallelFor(
      0, parts.size(),
      [&](size_t b) {
        const size_t end = std::min(vertices.size(), (b + 1) * kBlock);
        for (size_t i = b * kBlock; i < end; ++i) {
          const uint32_t e0 = ve[vertices[i]];
          if (e0 == kNoEdge) continue;
          uint32_t e = e0;
          do {
            parts[b].push_back(TriangleOf(e));
            e = m.twin[Prev(e)];
          } while (e != e0);
        }
      },
      1);
  std::vector<uint32_t> out;
  for (auto& p : parts) out.insert(out.end(), p.begin(), p.end());
  SortUnique(out);
  return out;
}

std::vector<uint32_t> KineticExecutor::CandidateTriangles(
    const Mesh& mesh, const std::vector<uint32_t>& moved) {
  const MeshView m = mesh.view();
  // Hull turns of neighbours of moved vertices change too: include the
  // triangles around the moved vertices' neighbours' spokes by taking the
  // two-ring of ghost triangles (cheap: only ghosts are re-examined).
  std::vector<uint32_t> around = TrianglesAround(mesh, moved);
  std::vector<uint32_t> extra;
  for (uint32_t t : around) {
    if (!m.IsGhost(t)) continue;
    for (uint32_t e = 3 * t; e < 3 * t + 3; ++e) {
      extra.push_back(TriangleOf(m.twin[e]));
    }
  }
  around.insert(around.end(), extra.begin(), extra.end());
  SortUnique(around);
  return around;
}

std::vector<uint32_t> KineticExecutor::FindInvalidTriangles(
    const Mesh& mesh, const std::vector<Vec2>& pos,
    const std::vector<uint32_t>* moved) {
  const MeshView m = mesh.view();
  const Vec2* p = pos.data();
  if (moved == nullptr) {
    return Filter(mesh.num_triangles(), [&](size_t t) {
      return !rules::TriangleOk(m, p, static_cast<uint32_t>(t));
    });
  }
  std::vector<uint32_t> around = CandidateTriangles(mesh, *moved);
  std::vector<uint32_t> idx = Filter(around.size(), [&](size_t i) {
    return !rules::TriangleOk(m, p, around[i]);
  });
  for (uint32_t& i : idx) i = around[i];
  return idx;
}

namespace {

// One hold-back of fixing rounds (KineticExecutor::Fix): the culprits of the
// stalled triangles `bad` (rules::Culprits; a vertex once, with the smallest
// of its half-edges found) go back to `from` in `to` and are appended to
// *held; *next becomes `bad` plus every triangle whose validity reads a
// held vertex, sorted and unique. False when no triangle has a culprit.
// The device executor's hold-back (core/device/round_executor.inl) is the
// same, step for step, so that both give the same mesh.
bool HoldCulprits(const MeshView& m, Vec2* to, const Vec2* from,
                  const std::vector<uint32_t>& bad, std::vector<uint32_t>* held,
                  std::vector<uint32_t>* next) {
  auto moving = [&](uint32_t u) { return to[u] != from[u]; };
  std::vector<std::pair<uint32_t, uint32_t>> culprits;  // (vertex, edge)
  for (uint32_t t : bad) {
    uint32_t v[3], e[3];
    const int n = rules::Culprits(m, to, from, t, moving, v, e);
    for (int k = 0; k < n; ++k) culprits.emplace_back(v[k], e[k]);
  }
  std::sort(culprits.begin(), culprits.end());
  culprits.erase(std::unique(culprits.begin(), culprits.end(),
                             [](const auto& a, const auto& b) {
                               return a.first == b.first;
                             }),
                 culprits.end());
  if (culprits.empty()) return false;
  *next = bad;
  for (const auto& [v, e] : culprits) {
    to[v] = from[v];
    held->push_back(v);
  }
  for (const auto& [v, e] : culprits) {
    rules::ForEachStarAndHullRing(m, e,
                                  [next](uint32_t t) { next->push_back(t); });
  }
  SortUnique(*next);
  return true;
}

}  // namespace

void FlipScratch::Ensure(const Mesh& mesh) {
  if (tri_claim.size() < mesh.num_triangles()) {
    tri_claim.resize(mesh.num_triangles(), kNoEdge);
  }
  if (vert_claim.size() < mesh.num_vertices()) {
    vert_claim.resize(mesh.num_vertices(), kNoEdge);
  }
}

bool KineticExecutor::Fix(Mesh& mesh, const std::vector<Vec2>& pos,
                          std::vector<uint32_t> invalid, FlipScratch& scratch,
                          FlipCounts* counts, std::vector<uint32_t>* touched,
                          FixLog* log, std::vector<uint32_t>* stuck,
                          HoldBack* hold) {
  const MeshView m = mesh.view();
  const Vec2* p = pos.data();
  scratch.Ensure(mesh);
  std::vector<uint32_t>& tri_claim = scratch.tri_claim;
  std::vector<uint32_t>& vert_claim = scratch.vert_claim;
  std::vector<uint32_t> work = std::move(invalid);
  SortUnique(work);
  while (true) {
    // Keep only invalid triangles; propose one flip each.
    std::vector<uint32_t> bad_idx = Filter(work.size(), [&](size_t i) {
      return !rules::TriangleOk(m, p, work[i]);
    });
    if (bad_idx.empty()) break;
    std::vector<rules::FixProposal> props(bad_idx.size());
    ParallelFor(0, bad_idx.size(), [&](size_t i) {
      props[i] = rules::ProposeFixFlip(m, p, work[bad_idx[i]]);
      if (props[i].edge != kNoEdge) {
        props[i].edge = Canonical(m, props[i].edge);
      }
    });
    std::vector<rules::FixProposal> valid;
    for (const auto& pr : props) {
      if (pr.edge != kNoEdge) valid.push_back(pr);
    }
    if (valid.empty() && hold != nullptr) {
      // Stalled: hold the culprits back and go on around them.
      std::vector<uint32_t> bad(bad_idx.size());
      for (size_t i = 0; i < bad_idx.size(); ++i) bad[i] = work[bad_idx[i]];
      std::vector<uint32_t> next;
      if (HoldCulprits(m, hold->to->data(), hold->from->data(), bad,
                       &hold->held, &next)) {
        work = std::move(next);
        continue;
      }
    }
    if (valid.empty()) {
      if (stuck) {
        for (uint32_t i : bad_idx) stuck->push_back(work[i]);
      }
      return false;  // stuck: caller splits the step
    }
    std::sort(valid.begin(), valid.end(),
              [](const rules::FixProposal& x, const rules::FixProposal& y) {
                return x.edge < y.edge;
              });
    valid.erase(std::unique(valid.begin(), valid.end(),
                            [](const rules::FixProposal& x,
                               const rules::FixProposal& y) {
                              return x.edge == y.edge;
                            }),
                valid.end());
    std::vector<uint32_t> edges(valid.size()), joining(2 * valid.size());
    for (size_t i = 0; i < valid.size(); ++i) {
      edges[i] = valid[i].edge;
      joining[2 * i] = valid[i].new_u;
      joining[2 * i + 1] = valid[i].new_w;
    }
    const std::vector<uint32_t> winners =
        SelectIndependent(m, edges, &joining, tri_claim, vert_claim);
    // Next worklist: still-invalid triangles plus every winner footprint
    // (computed before flipping; flips keep triangle ids).
    std::vector<uint32_t> next;
    next.reserve(bad_idx.size() + 6 * winners.size());
    for (uint32_t i : bad_idx) next.push_back(work[i]);
    for (uint32_t w : winners) {
      uint32_t fp[6];
      rules::FlipFootprint(m, edges[w], fp);
      next.insert(next.end(), fp, fp + 6);
      if (touched) touched->insert(touched->end(), fp, fp + 2);
    }
    ParallelFor(0, winners.size(),
                [&](size_t i) { m.Flip(edges[winners[i]]); });
    if (log) {
      const auto& ve = mesh.vertex_edge();
      for (uint32_t w : winners) {
        const uint32_t e = edges[w], f = m.twin[e];
        for (uint32_t h : {e, Prev(e), f, Prev(f)}) {  // the quad's corners
          const uint32_t v = m.origin[h];
          if (v != kInfiniteVertex) log->vertex_edges.emplace_back(v, ve[v]);
        }
        log->flips.push_back(e);
      }
    }
    for (uint32_t w : winners) mesh.UpdateVertexEdgesAfterFlip(edges[w]);
    if (counts) {
      ++counts->fix_rounds;
      for (uint32_t w : winners) {
        switch (valid[w].kind) {
          case rules::kInteriorFlip:
            ++counts->interior_fix;
            break;
          case rules::kHullAbsorb:
            ++counts->hull_absorb;
            break;
          case rules::kHullRelease:
            ++counts->hull_release;
            break;
          default:
            break;
        }
      }
    }
    SortUnique(next);
    work = std::move(next);
  }
  if (HullWindsOnce(mesh, pos)) return true;
  // Every triangle is valid but the hull winds more than once: report the
  // ghost triangles, whose vertices are the ones to hold back.
  if (stuck) {
    const std::vector<uint32_t> ghosts =
        Filter(mesh.num_triangles(),
               [&](size_t t) { return m.IsGhost(static_cast<uint32_t>(t)); });
    stuck->insert(stuck->end(), ghosts.begin(), ghosts.end());
  }
  return false;
}

void KineticExecutor::Undo(Mesh& mesh, const FixLog& log) {
  const MeshView m = mesh.view();
  for (auto it = log.flips.rbegin(); it != log.flips.rend(); ++it) {
    m.Unflip(*it);
  }
  auto& ve = mesh.mutable_vertex_edge();
  for (auto it = log.vertex_edges.rbegin(); it != log.vertex_edges.rend();
       ++it) {
    ve[it->first] = it->second;
  }
}

void KineticExecutor::Legalize(Mesh& mesh, const std::vector<Vec2>& pos,
                               const std::vector<uint32_t>* seed_triangles,
                               FlipScratch& scratch, FlipCounts* counts,
                               std::vector<uint32_t>* flipped) {
  const MeshView m = mesh.view();
  const Vec2* p = pos.data();
  std::vector<uint32_t> work;
  if (seed_triangles == nullptr) {
    work =
        Filter(mesh.num_half_edges(), [&](size_t e) { return e < m.twin[e]; });
  } else {
    work.reserve(seed_triangles->size() * 3);
    for (uint32_t t : *seed_triangles) {
      for (uint32_t e = 3 * t; e < 3 * t + 3; ++e) {
        work.push_back(Canonical(m, e));
      }
    }
    SortUnique(work);
  }
  scratch.Ensure(mesh);
  std::vector<uint32_t>& tri_claim = scratch.tri_claim;
  std::vector<uint32_t> no_vertices;
  // Each predicate is evaluated once per change: `work` holds the edges to
  // test; `known` the illegal edges that lost their claim while neither of
  // their triangles changed (still illegal, not tested again). Both sorted;
  // they are disjoint (an edge of an unchanged triangle pair is no outer
  // edge of a flipped quad). The winners are those of re-testing every
  // loser: a loser whose triangle flipped reappears as an outer edge of
  // that quad.
  std::vector<uint32_t> known;
  while (true) {
    std::vector<uint32_t> idx = Filter(
        work.size(), [&](size_t i) { return rules::IsIllegal(m, p, work[i]); });
    std::vector<uint32_t> edges(known.size() + idx.size());
    {
      std::vector<uint32_t> tested(idx.size());
      for (size_t i = 0; i < idx.size(); ++i) tested[i] = work[idx[i]];
      std::merge(known.begin(), known.end(), tested.begin(), tested.end(),
                 edges.begin());
    }
    if (edges.empty()) break;
    const std::vector<uint32_t> winners =
        SelectIndependent(m, edges, nullptr, tri_claim, no_vertices);
    ParallelFor(0, winners.size(),
                [&](size_t i) { m.Flip(edges[winners[i]]); });
    for (uint32_t w : winners) mesh.UpdateVertexEdgesAfterFlip(edges[w]);
    if (flipped != nullptr) {
      for (uint32_t w : winners) {
        flipped->push_back(TriangleOf(edges[w]));
        flipped->push_back(TriangleOf(m.twin[edges[w]]));
      }
    }
    // The flipped triangles (flips keep triangle ids) are marked in
    // tri_claim (kNoEdge between rounds) while the losers are sorted out.
    ParallelFor(0, winners.size(), [&](size_t i) {
      const uint32_t e = edges[winners[i]];
      tri_claim[TriangleOf(e)] = 0;
      tri_claim[TriangleOf(m.twin[e])] = 0;
    });
    std::vector<uint32_t> next_known;
    next_known.reserve(edges.size() - winners.size());
    {
      size_t w = 0;
      for (size_t i = 0; i < edges.size(); ++i) {
        if (w < winners.size() && winners[w] == i) {
          ++w;
          continue;
        }
        const uint32_t e = edges[i];
        if (tri_claim[TriangleOf(e)] != 0 &&
            tri_claim[TriangleOf(m.twin[e])] != 0) {
          next_known.push_back(e);
        }
      }
    }
    ParallelFor(0, winners.size(), [&](size_t i) {
      const uint32_t e = edges[winners[i]];
      tri_claim[TriangleOf(e)] = kNoEdge;
      tri_claim[TriangleOf(m.twin[e])] = kNoEdge;
    });
    // Next worklist: the four outer edges of each flipped quad.
    std::vector<uint32_t> next(4 * winners.size());
    ParallelFor(0, winners.size(), [&](size_t i) {
      const uint32_t e = edges[winners[i]], f = m.twin[e];
      next[4 * i + 0] = Canonical(m, Next(e));
      next[4 * i + 1] = Canonical(m, Prev(e));
      next[4 * i + 2] = Canonical(m, Next(f));
      next[4 * i + 3] = Canonical(m, Prev(f));
    });
    if (counts) {
      ++counts->legalize_rounds;
      counts->delaunay += winners.size();
    }
    SortUnique(next);
    work = std::move(next);
    known = std::move(next_known);
  }
}

bool KineticExecutor::HullWindsOnce(const Mesh& mesh,
                                    const std::vector<Vec2>& pos) {
  uint32_t ghost = 0;
  return HullWindsOnceFrom(mesh, pos, &ghost);
}

}  // namespace kinetri::core
