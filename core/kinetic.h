// CPU executor of the kinetic update: parallel fixing and legalizing rounds.
//
// Both phases run in rounds over a sorted worklist. In a round every element
// proposes at most one flip (core/flip_rules.h); a proposal wins when it holds
// the smallest edge id on all six triangles of its footprint (and, for a hull
// absorption, on the joining vertex), claimed with atomic min. Winners have
// disjoint footprints and flip concurrently. Because proposals, claims and
// worklists are pure functions of the mesh state, the result, including
// triangle numbering, is identical for any number of threads.
#ifndef KINETRI_CORE_KINETIC_H_
#define KINETRI_CORE_KINETIC_H_

#include <cstdint>
#include <utility>
#include <vector>

#include "core/mesh.h"
#include "core/vec2.h"

namespace kinetri::core {

struct FlipCounts {
  uint64_t interior_fix = 0;  // flips repairing inverted triangles
  uint64_t hull_absorb = 0;   // vertices that crossed a hull edge
  uint64_t hull_release = 0;  // hull vertices that became reflex
  uint64_t delaunay = 0;      // legalizing flips
  uint32_t fix_rounds = 0;
  uint32_t legalize_rounds = 0;

  FlipCounts& operator+=(const FlipCounts& o);
};

// Every knob of the round executor's update (Triangulation::LocalUpdate);
// validated by Triangulation::Create. Nothing in the round path is a
// hard-coded threshold.
struct RoundStepPolicy {
  // Whole-step splitting: a step whose fixing gets stuck is split into at
  // most 2^depth sub-steps for all points. 0 leaves splitting to the cheaper
  // local sub-steps (only the stuck vertices' motion is halved).
  int max_subdivision_depth = 0;
  // How often a stuck vertex's own motion may be halved before it is
  // removed and re-inserted instead.
  int max_halvings = 4;
  // Rebuild at once when more than this fraction of all triangles is
  // invalid after moving (local repair would cost more than CGAL).
  double rebuild_fraction = 0.04;
  // Rebuild when the kinetic passes of one step exceed this number.
  int max_passes = 64;
  // A pass is sparse (seeded from the moved vertices' stars instead of a
  // scan of every triangle) when fewer than this fraction of points move.
  double sparse_fraction = 0.25;
  // Re-insertion budget per step: at most max(reinsert_min,
  // reinsert_fraction * sites) removed vertices, and at least
  // min_sites_left sites must stay in the mesh; beyond that, rebuild.
  uint32_t reinsert_min = 64;
  double reinsert_fraction = 0.125;
  uint32_t min_sites_left = 8;
  // Hold-back inside fixing: when a fixing round finds no flip for the
  // invalid triangles left, their culprits (rules::Culprits) go back to
  // their old positions and fixing goes on around them (KineticExecutor::
  // HoldBack), instead of the attempt ending stuck; they then finish their
  // motion in later passes, halved first. false: a stalled attempt ends
  // stuck and its stuck vertices and their neighbours are held for the
  // next one (the behaviour before hold-back).
  bool hold_culprits = true;
};

// What Fix changed, so that Undo can restore the mesh exactly (vertex_edge
// included): the flipped edges in order and the vertex_edge entries they
// overwrote.
struct FixLog {
  std::vector<uint32_t> flips;
  std::vector<std::pair<uint32_t, uint32_t>> vertex_edges;  // (v, old edge)
};

// Claim arrays reused across rounds and calls (all entries kNoEdge between
// uses).
struct FlipScratch {
  std::vector<uint32_t> tri_claim;
  std::vector<uint32_t> vert_claim;
  void Ensure(const Mesh& mesh);
};

class KineticExecutor {
 public:
  // Triangles of the mesh that are invalid for `pos`. If `moved` is non-null,
  // only triangles around those vertices are examined (vertex_edge must be
  // valid).
  static std::vector<uint32_t> FindInvalidTriangles(
      const Mesh& mesh, const std::vector<Vec2>& pos,
      const std::vector<uint32_t>* moved);

  // The triangles a sparse pass examines for the moved vertices: their
  // stars plus the ghost triangles next to ghosts among them (hull turns of
  // their neighbours change too). Sorted, unique.
  static std::vector<uint32_t> CandidateTriangles(
      const Mesh& mesh, const std::vector<uint32_t>& moved);

  // Repairs the given invalid triangles by flips. Returns true iff the mesh
  // is afterwards a valid triangulation of pos (embedding, convex hull).
  // `touched` receives the triangles changed by flips, `log` the flipped
  // edges in order (for Undo) and, on failure, `stuck` the triangles left
  // invalid. vertex_edge is kept valid (after each round's flips, as
  // Mesh::UpdateVertexEdgesAfterFlip sets it in winner order).
  //
  // With `hold` (RoundStepPolicy::hold_culprits), a round that finds no flip
  // for the invalid triangles left holds back their culprits instead of
  // failing: each goes back to hold->from in *hold->to (which must be
  // `pos`), is listed in hold->held, and the triangles whose validity reads
  // it join the worklist. Fixing fails only when a stalled round has no
  // moving culprit left (or the hull winds twice).
  struct HoldBack {
    const std::vector<Vec2>* from = nullptr;  // the mesh is Delaunay for it
    std::vector<Vec2>* to = nullptr;          // == &pos; held entries reset
    std::vector<uint32_t> held;               // in the order they were held
  };
  static bool Fix(Mesh& mesh, const std::vector<Vec2>& pos,
                  std::vector<uint32_t> invalid, FlipScratch& scratch,
                  FlipCounts* counts, std::vector<uint32_t>* touched,
                  FixLog* log, std::vector<uint32_t>* stuck,
                  HoldBack* hold = nullptr);

  // Reverts the flips recorded by Fix (a flip applied four times is the
  // identity, so each logged flip is undone by three more, newest first)
  // and restores vertex_edge: the mesh is then exactly as before Fix.
  static void Undo(Mesh& mesh, const FixLog& log);

  // Delaunay flips until every edge is locally Delaunay. Starts from all
  // edges of the triangles in `seed_triangles`, or from all edges if null.
  // `flipped` (optional) receives the two triangles of every flip (with
  // repeats).
  static void Legalize(Mesh& mesh, const std::vector<Vec2>& pos,
                       const std::vector<uint32_t>* seed_triangles,
                       FlipScratch& scratch, FlipCounts* counts,
                       std::vector<uint32_t>* flipped = nullptr);

  // Triangles incident to the given vertices (sorted, unique).
  static std::vector<uint32_t> TrianglesAround(
      const Mesh& mesh, const std::vector<uint32_t>& vertices);

  // Does the hull polygon wind exactly once (one topmost vertex)?
  static bool HullWindsOnce(const Mesh& mesh, const std::vector<Vec2>& pos);
};

}  // namespace kinetri::core

#endif  // KINETRI_CORE_KINETIC_H_
