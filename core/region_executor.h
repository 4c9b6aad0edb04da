// CPU executor of the kinetic update, shaped for the CPU: per-region stacks.
//
// The triangle slots, kept in spatial (Hilbert) order, are cut into regions
// of a fixed number of triangles (an option, never the thread count, so the
// result is the same for 1 and N threads). Each region repairs and then
// legalizes its own triangles with a LIFO stack, one thread per region, no
// atomics: an element is processed in its region only when everything the
// per-element rule reads or the flip writes lies in that region (reads are
// checked before they happen, so a region never reads a slot another region
// may be writing). Anything that crosses a boundary is deferred to one short
// serial pass. The per-element rules (core/flip_rules.h), the flip
// (core/mesh.h) and the vertex operations (core/vertex_ops.h) are the same as
// the round executor's (core/kinetic.h); only the scheduling differs.
//
// A step (Step below), for a mesh that is Delaunay for `from`:
//   1. one fused dense scan (or a scan around the moved vertices for sparse
//      motion) finds the invalid triangles and the illegal edges for `to`,
//      reading the apex across each edge from an array kept since the last
//      step where that step flipped little (CheckAcross below);
//   2. hold-back: an invalid triangle that no flip can repair right after
//      the move has its culprit vertex (one whose old position makes the
//      triangle valid again) held at its old position;
//   3. fix by regions, then the serial pass; a hull that winds twice or a
//      triangle still stuck undoes the flips, holds the stuck triangles'
//      moving vertices too and repeats (rare);
//   4. legalize by regions; each region then moves the held vertices whose
//      stars it holds (step 5, while its slots are in cache); then the
//      serial pass of legalizing;
//   5. every held vertex moves alone: fix + legalize around it; if that gets
//      stuck, its motion is bisected (up to max_halvings times); if that
//      fails too it is removed and returned to the caller for re-insertion.
#ifndef KINETRI_CORE_REGION_EXECUTOR_H_
#define KINETRI_CORE_REGION_EXECUTOR_H_

#include <cstdint>
#include <string>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "core/cancel.h"
#include "core/hull.h"
#include "core/kinetic.h"
#include "core/mesh.h"
#include "core/vec2.h"

namespace kinetri::core {

// Every knob of a region step (owned by the step policy in
// TriangulationOptions).
struct RegionStepPolicy {
  uint32_t region_triangles = 8192;  // triangles per region
  int max_halvings = 8;              // bisections of a held vertex's own motion
  int max_passes = 8;                // dense fixing attempts before giving up
  // Moved vertices below this fraction of all vertices: the scan looks only
  // around them (sparse step); above it, one dense scan of every triangle.
  double sparse_fraction = 0.25;
  // Cost model for "rebuild instead" (microseconds, measured on the 2-core
  // reference machine at 1M points, see docs/BENCHMARKS.md): each triangle
  // that no flip can repair after the move costs about this much in
  // hold-back, moving alone and bisection; a rebuild costs about
  // rebuild_fixed_cost plus rebuild_point_cost per point. The step is
  // rebuilt when the first exceeds the second. held_vertex_cost = 0: never
  // rebuild by cost.
  double held_vertex_cost = 8.0;
  double rebuild_point_cost = 1.5;
  double rebuild_fixed_cost = 200.0;
  // Vertex tolerances (core/motion_filter.h): the step looks only around
  // the vertices that leave theirs. It pays while few do: a certification
  // of the whole mesh costs about two dense scans, and past a few percent
  // of loud vertices the sparse step costs what the dense scan does
  // (docs/BENCHMARKS.md). The driver certifies when a sample of the moving
  // vertices predicts at most filter_estimate loud, keeps the filter while
  // at most filter_fraction of all vertices are loud, and after a step
  // where more are waits filter_backoff steps (doubling, to 256) before
  // sampling again.
  bool filter_motion = true;
  double filter_estimate = 0.003;
  double filter_fraction = 0.01;
  uint32_t filter_samples = 1024;
  int filter_backoff = 4;
  // Keep the apex across each half-edge from one step to the next
  // (RegionExecutor::CheckAcross): the dense scan then reads it beside each
  // triangle instead of in the neighbours' slots, and every flip refreshes
  // the entries it changes. That pays while steps flip little: the array is
  // kept after a step that flipped at most this fraction of the triangle
  // slots, and dropped after one that flipped more (about a fifth at
  // Brownian 0.1, where the upkeep costs more than the scan saves; 2 % at
  // 0.01, docs/BENCHMARKS.md); a dense step after a dropping one reads the
  // mesh, one after a keeping one fills the array as it scans. 0: never
  // kept (the same meshes; kinetri_quick_bench --keep_across_flips
  // compares).
  double keep_across_flips = 0.05;
};

// What a region step did (added to the caller's StepReport).
struct RegionStepStats {
  FlipCounts flips;
  uint32_t held = 0;          // vertices held back and moved alone
  uint32_t held_serial = 0;   // of those, moved in the serial pass
  uint32_t halvings = 0;      // bisections of held vertices' motion
  uint32_t fix_attempts = 0;  // dense fixing attempts (1 = no repeat)
  uint32_t deferred = 0;      // elements left to the serial pass
  double scan_seconds = 0.0;
  double fix_seconds = 0.0;
  double legalize_seconds = 0.0;  // with the held vertices regions move
  double held_seconds = 0.0;      // the held vertices of the serial pass
  // The dense scan read the apexes across kept from the last step (false:
  // it filled them, or read the mesh, or the step was sparse).
  bool across_kept = false;
  // The step stopped because its cancellation token fired. A step that
  // stops or fails leaves the mesh exactly as it was, whatever phase it is
  // in: every flip and vertex removal it made is logged and undone.
  bool cancelled = false;
};

// A contiguous range of triangle slots (a region); the default admits
// every slot.
struct RegionSlots {
  uint32_t lo = 0;
  uint32_t hi = 0xFFFFFFFFu;
  bool In(uint32_t t) const { return t - lo < hi - lo; }
};

class RegionExecutor {
 public:
  // A vertex held back at its old position: a half-edge leaving it (for
  // its star) and where it is to go (its entry of `to`).
  struct HeldVertex {
    uint32_t v;
    uint32_t edge;
    Vec2 target;
  };

  // Moves the vertices in `moved` (finite mesh vertices, ascending) from
  // their positions in `from` to those in `to` (both indexed by vertex;
  // entries of other vertices are equal in both). The mesh must be the
  // Delaunay triangulation of `from`. On success it is the Delaunay
  // triangulation of `to` over all vertices except `removed`: vertices taken
  // out because their motion could not be repaired locally, each with a
  // neighbour in `hints` (indexed by vertex) to start locating it. Returns
  // false (with `reason`) when the step should be rebuilt instead. `cancel`
  // (optional) is polled per region and per held vertex (every 16 in the
  // serial pass); when it fires the step returns false with
  // stats->cancelled set. A step that returns false has undone all it did:
  // the mesh is again the Delaunay triangulation of `from` (vertex_edge
  // may differ). `to` is worked on in place (no copy of every position per
  // step): while the step runs a held vertex's entry is where it stands;
  // every entry is as given again when Step returns.
  bool Step(Mesh& mesh, const std::vector<Vec2>& from, std::vector<Vec2>& to,
            const std::vector<uint32_t>& moved, const RegionStepPolicy& policy,
            RegionStepStats* stats, std::vector<uint32_t>* removed,
            std::vector<uint32_t>* hints, std::string* reason,
            const CancelToken* cancel = nullptr);

  // Serial stack versions of the fixing and legalizing loops (same contract
  // as KineticExecutor::Fix / Legalize, hull check included), for small
  // local changes such as vertex insertion. `across` (optional): an array
  // of the apexes across each half-edge (FillAcross) kept valid through
  // every flip.
  static bool FixSerial(Mesh& mesh, const std::vector<Vec2>& pos,
                        const std::vector<uint32_t>& invalid,
                        FlipCounts* counts, std::vector<uint32_t>* touched,
                        std::vector<uint32_t>* log,
                        std::vector<uint32_t>* stuck,
                        uint32_t* across = nullptr);
  static void LegalizeSerial(Mesh& mesh, const std::vector<Vec2>& pos,
                             const std::vector<uint32_t>& seed_triangles,
                             FlipCounts* counts,
                             std::vector<uint32_t>* log = nullptr,
                             uint32_t* across = nullptr);

  // Per triangle slot, after a successful Step: nonzero for every triangle
  // the step changed or looked at around a moved vertex (on the sparse
  // path: each moved vertex's star and the ghosts next to it).
  const std::vector<uint8_t>& changed_triangles() const { return tri_mark_; }

  // The apex across every half-edge (core/mesh_scan.h's FillAcross), kept
  // from one step to the next so that the dense scan reads it beside each
  // triangle's own vertices instead of in its neighbours' slots: filled by
  // a dense scan, refreshed by every flip, unflip and removal of the step,
  // and trusted by the next step only while the mesh's content_version()
  // is the one the last step ended with (anything else that touches the
  // mesh makes the next dense scan fill it again). Ok when it is not kept
  // for `mesh`; an error naming the first half-edge where a kept entry is
  // not the mesh's (Triangulation::Validate checks this).
  absl::Status CheckAcross(const Mesh& mesh) const;
  // Whether the next step reads kept across entries for `mesh`.
  bool KeepsAcross(const Mesh& mesh) const {
    return across_version_ != 0 && across_.size() == mesh.num_half_edges() &&
           across_version_ == mesh.content_version();
  }
  // The caller's own changes to the mesh between steps (re-insertion) keep
  // the entries when it names every triangle it writes:
  // BeginHostChange(mesh) before the first change (false: nothing is kept
  // for this mesh, nothing to do); HostChangeAcross(mesh) for the entries,
  // sized for the mesh as it is then (null when not kept), to refresh by
  // RefreshAcross (core/mesh_scan.h) for every triangle a change writes
  // and to hand to FixSerial / LegalizeSerial; EndHostChange(mesh) after
  // the last change. A change that does not end keeps nothing.
  bool BeginHostChange(const Mesh& mesh);
  uint32_t* HostChangeAcross(const Mesh& mesh);
  void EndHostChange(const Mesh& mesh);

 private:
  struct Region {
    std::vector<uint32_t> invalid;  // triangles to repair (scan + holds)
    std::vector<uint32_t> illegal;  // canonical half-edges found illegal
    std::vector<uint32_t> stack;
    std::vector<uint32_t> waiting;   // invalid, no repairing flip yet
    std::vector<uint32_t> deferred;  // crosses the region boundary
    std::vector<uint32_t> log;       // flipped edges, in order
    // The region's flips of the successful fixing attempt, kept while
    // legalizing so that a stop then can undo the whole step.
    std::vector<uint32_t> fix_log;
    // The region's flips while moving held vertices (kept: undone on stop).
    std::vector<uint32_t> held_log;
    // Held vertices whose vertex_edge lies here (indices into held_list_).
    std::vector<uint32_t> held;
    std::vector<HeldVertex> holds;  // held back by the region
    FlipCounts counts;
    void ClearWork();
  };
  bool DenseFix(Mesh& mesh, const std::vector<uint32_t>& moved,
                const RegionStepPolicy& policy, RegionStepStats* stats,
                std::string* reason);
  void HoldCulprits(const Mesh& mesh, std::vector<uint32_t> suspects);
  // Holds every moving vertex of the hull (walked from hull_hint_).
  void HoldMovingHullVertices(const MeshView& m);
  // Holds every moving vertex that is not held yet in the stars of
  // `vertices` (from vertex_edge, which must be valid for them; others are
  // skipped). `around` is scratch.
  void HoldMovingNeighbours(const Mesh& mesh,
                            const std::vector<uint32_t>& vertices,
                            std::vector<uint32_t>* around);
  template <bool kBounded>
  void HoldCulpritsIn(const MeshView& m, RegionSlots b,
                      std::vector<uint32_t>& queue,
                      std::vector<uint32_t>* deferred,
                      std::vector<HeldVertex>* holds);
  // Holds v at its old position; `edge` leaves v (for its star). It goes
  // to *to (a region's list) if given, else to the held lists, with its
  // target.
  void Hold(uint32_t v, uint32_t edge, std::vector<HeldVertex>* to = nullptr);
  // The step's body (Step puts the held vertices' targets back after it).
  bool StepInPlace(Mesh& mesh, const std::vector<uint32_t>& moved,
                   const RegionStepPolicy& policy, RegionStepStats* stats,
                   std::vector<uint32_t>* removed, std::vector<uint32_t>* hints,
                   std::string* reason);
  // Moves held vertex v (serially) towards `target`, bisecting its motion
  // when stuck; the flips it keeps are appended to *log. False: v stays at
  // its old or last bisected position.
  bool MoveHeld(Mesh& mesh, uint32_t v, const Vec2& target,
                const RegionStepPolicy& policy, RegionStepStats* stats,
                std::vector<uint32_t>* log);
  // MoveHeld for the parallel pass: v's star and everything its fixing and
  // legalizing read and write lie in triangle slots [lo, hi) (legalizing
  // edges that would leave it are appended to late_edges). False: v was
  // left where it was (its original or a bisected position) for the
  // serial pass.
  bool MoveHeldInRegion(Mesh& mesh, uint32_t v, const Vec2& target,
                        const RegionStepPolicy& policy, uint32_t lo,
                        uint32_t hi, RegionStepStats* stats,
                        std::vector<uint32_t>* late_edges,
                        std::vector<uint32_t>* log);
  // Removes held vertex v (for re-insertion by the caller) and legalizes
  // around the hole, recording in removals_ the triangles it rewrites as
  // they were and logging the flips in held_log_.
  bool RemoveHeld(Mesh& mesh, uint32_t v, RegionStepStats* stats);
  // Undoes everything the step did to the mesh, in reverse: the held
  // vertices' flips and removals, legalizing, fixing; vertex_edge is
  // recomputed afterwards.
  void UndoStep(Mesh& mesh);

  // The across entries the step keeps valid, or null when it does not.
  uint32_t* LiveAcross() { return across_live_ ? across_.data() : nullptr; }

  // The token fired (polled at most once per region or held vertex).
  bool Cancelled() const { return cancel_ != nullptr && cancel_->Cancelled(); }

  const CancelToken* cancel_ = nullptr;
  const std::vector<Vec2>* from_ = nullptr;
  // Positions the mesh is repaired for: the caller's `to`, in place.
  std::vector<Vec2>* cur_ = nullptr;
  std::vector<uint8_t> held_;  // per vertex
  std::vector<uint32_t> held_list_;
  std::vector<uint32_t> held_edge_;  // a half-edge leaving each, when held
  std::vector<Vec2> held_target_;    // its position in `to`
  std::vector<uint8_t> tri_mark_;    // per triangle: changed by a region flip
  std::vector<Region> regions_;
  // Legalizing's pass over what crossed region boundaries: coarse regions
  // (several regions each) in parallel, then serially.
  std::vector<Region> coarse_;
  Region serial_;
  std::vector<uint32_t> fix_serial_log_;  // the serial fix's flips (fix_log)
  // The serial part of moving held vertices, in order: flips (held_log_)
  // and removals, each with the triangles it rewrote as they were.
  struct SavedTriangle {
    uint32_t slot;
    uint32_t origin[3];
    uint32_t twin[3];
  };
  struct Removal {
    size_t log_size;    // held_log_.size() when it happened
    size_t saved;       // its triangles: saved_[saved, next removal's)
    size_t free_slots;  // mesh free-list length before it
  };
  std::vector<uint32_t> held_log_;
  std::vector<Removal> removals_;
  std::vector<SavedTriangle> saved_;
  uint32_t hull_hint_ = 0;  // a ghost triangle, remembered
  // Per half-edge, the apex across it (CheckAcross above); the mesh's
  // content_version() it was last right for (0: none); whether the step
  // running keeps it valid.
  std::vector<uint32_t> across_;
  uint64_t across_version_ = 0;
  bool across_live_ = false;
  bool host_change_ = false;  // between BeginHostChange and EndHostChange
  // The last step flipped few enough to keep the array
  // (RegionStepPolicy::keep_across_flips).
  bool across_wanted_ = true;
};

}  // namespace kinetri::core

#endif  // KINETRI_CORE_REGION_EXECUTOR_H_
