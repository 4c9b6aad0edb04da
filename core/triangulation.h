// Kinetic Delaunay triangulation of a set of moving 2D points.
//
// Triangulation owns the points, their mesh and their numbering. After
// Create() and after every successful ApplyDisplacements() it holds the exact
// Delaunay triangulation of the current positions (with the symbolic
// perturbation of core/predicates.h for cocircular points).
//
//  * Points keep the caller's ids 0..n-1 ("external"). Internally they are
//    numbered along a Hilbert curve for locality; the numbering is refreshed
//    when edges stretch too far in it.
//  * Exactly coincident points form one "site": one of them (rep) is the
//    mesh vertex, the others hang off it (dup_next chain) and are still
//    returned by queries. Sites separate again when the points move apart.
//  * Fewer than three sites, or all sites collinear, is the "line" mode: the
//    Delaunay graph is then the path through the sites in (x, y) order.
//
// An update moves the points and repairs the mesh locally with one of two
// CPU executors (TriangulationOptions::executor):
//  * the region executor (default, core/region_executor.h): one dense scan,
//    per-region stacks of fixing and legalizing flips, culprit vertices of
//    triangles no flip can repair held back and then moved alone (bisection
//    of their own motion, re-insertion as the last resort, core/vertex_ops.h);
//    a measured cost model rebuilds with CGAL when that is cheaper;
//  * the round executor (core/kinetic.h): global parallel rounds; when fixing
//    gets stuck the stuck vertices are held back, then their motion is
//    halved, and they finish it in further sparse passes (optionally the
//    whole step is split too); a vertex stuck more than max_halvings times
//    is removed and re-inserted. CGAL rebuilds the mesh when more than
//    rebuild_fraction of the triangles invert, when re-insertion would
//    exceed its budget, or when max_passes run out (RoundStepPolicy).
//  * the device executor (core/device/device_executor.h): the round
//    executor's schedule written once in CCCL/Thrust and run on a device
//    backend (a GPU, or CPU threads for the emulated backend); the same
//    hold-back, halving, re-insertion and rebuild decisions as the round
//    executor, taken on the host between device attempts.
// StepReport tells which path was taken.
#ifndef KINETRI_CORE_TRIANGULATION_H_
#define KINETRI_CORE_TRIANGULATION_H_

#include <tbb/task_arena.h>

#include <array>
#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "absl/functional/function_ref.h"
#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/types/span.h"
#include "core/cancel.h"
#include "core/device/device_executor.h"
#include "core/kinetic.h"
#include "core/mesh.h"
#include "core/motion_filter.h"
#include "core/region_executor.h"
#include "core/triangulation_view.h"
#include "core/vec2.h"

namespace kinetri::core {

class CellIndex;
class HintGrid;

// Which CPU executor repairs the mesh after a move.
enum class Executor {
  kRegions,  // per-region stacks, one dense pass (core/region_executor.h)
  kRounds,   // global rounds with atomic claims (core/kinetic.h): the
             // GPU-shaped schedule, kept as an option and a test oracle
  kDevice,   // the round schedule on a device backend
             // (core/device/device_executor.h); RoundStepPolicy applies
};
const char* ExecutorName(Executor executor);

struct TriangulationOptions {
  int num_threads = 0;  // 0: all cores
  Executor executor = Executor::kRegions;
  // Knobs of each executor (num_threads and the renumbering ones below
  // apply to both).
  RegionStepPolicy region;
  RoundStepPolicy round;
  // Where the device executor runs (executor == kDevice); Create fails
  // with FAILED_PRECONDITION when this build or machine lacks it.
  device::DeviceBackend device_backend = device::DeviceBackend::kEmulated;
  // Every renumber_check_interval steps (0: never), the points are
  // renumbered along a Hilbert curve (and the triangles sorted by them)
  // when the mean id span of an edge has grown renumber_stretch times since
  // the last numbering; otherwise the triangles alone are sorted again when
  // the mean slot span between neighbouring triangles has grown
  // triangle_sort_stretch times since the last sort. (Flips keep their two
  // slots, so over many steps the slots of neighbouring triangles drift
  // apart: the region executor defers more edges across its regions and
  // every pass reads the mesh less in order. A sort costs about 90 ms at
  // 1M points on 2 cores; docs/BENCHMARKS.md.)
  double renumber_stretch = 2.0;
  double triangle_sort_stretch = 4.0;
  int renumber_check_interval = 8;
};

// A batch of motion, and of points that leave and join. `ids` empty means
// dense (one value per point, in id order); otherwise values[i] applies to
// point ids[i] (ids must be distinct). A batch with no ids and no values
// but with points that leave or join moves nothing.
//
// The moves apply first (ids as before the step), then the points in
// `remove` leave (ids as before the step, distinct; their values in a
// dense batch are not used; a sparse batch must not name them), then the
// points of `add` join. Afterwards the remaining points keep their order
// and are numbered 0.. again, and the joining points follow in the order
// given: ids n - remove.size() .. n - remove.size() + add.size() - 1.
struct DisplacementBatch {
  enum class Mode { kDelta, kAbsolute };
  Mode mode = Mode::kDelta;
  std::vector<uint32_t> ids;
  std::vector<Vec2> values;
  std::vector<uint32_t> remove;
  std::vector<Vec2> add;

  static DisplacementBatch Dense(std::vector<Vec2> deltas);
  static DisplacementBatch Sparse(std::vector<uint32_t> ids,
                                  std::vector<Vec2> deltas);
  static DisplacementBatch Absolute(std::vector<Vec2> positions);
  static DisplacementBatch AbsoluteSparse(std::vector<uint32_t> ids,
                                          std::vector<Vec2> positions);
};

enum class UpdatePath { kNoop, kLocal, kSubdivided, kReinserted, kRebuilt };
const char* UpdatePathName(UpdatePath path);

struct StepReport {
  UpdatePath path = UpdatePath::kNoop;
  uint32_t moved_points = 0;
  uint32_t substeps = 0;         // local sub-steps taken (1 = not split)
  uint32_t failed_attempts = 0;  // fixing attempts that got stuck
  uint32_t reinserted = 0;       // vertices removed and inserted again locally
  uint32_t local_halvings = 0;   // rounds that halved stuck vertices' motion
  // Vertices held back by fixing (the region executor moves them alone;
  // the round and device executors in later passes, RoundStepPolicy::
  // hold_culprits).
  uint32_t held_vertices = 0;
  uint32_t deferred = 0;  // region executor: boundary elements
  // Region executor with vertex tolerances (core/motion_filter.h): moved
  // points that stayed within theirs and were not looked at.
  uint32_t quiet_points = 0;
  uint32_t removed_points = 0;  // points that left with this step
  uint32_t added_points = 0;    // points that joined with this step
  FlipCounts flips;
  std::string fallback_reason;  // why the step was rebuilt, if it was
  bool renumbered = false;
  // The triangles alone were sorted again (triangle_sort_stretch); the
  // points kept their numbering.
  bool triangles_sorted = false;
  uint32_t num_sites = 0;   // distinct positions after the step
  uint32_t num_points = 0;  // points after the step
  double seconds = 0.0;
  // Where the time went (wall clock): fixing attempts, legalizing, removing
  // and inserting vertices again.
  double fix_seconds = 0.0;
  double legalize_seconds = 0.0;
  double reinsert_seconds = 0.0;
  double scan_seconds = 0.0;  // region executor: scan and hold-back
  // Region executor: the dense scan read the apexes across each edge kept
  // from the last step (RegionStepPolicy::keep_across_flips).
  bool across_kept = false;
  // Region executor: held vertices moved alone in the serial pass (those
  // moved by regions count in legalize_seconds).
  double held_seconds = 0.0;
  double filter_seconds = 0.0;  // vertex tolerances: checks and upkeep
  // Device executor: host<->device copies (included in fix/legalize time
  // of nothing else) and their volume.
  double transfer_seconds = 0.0;
  uint64_t transfer_bytes = 0;
  // Device executor: device algorithms (Thrust calls) its attempts ran,
  // and how many of them the host waited for (DeviceAttempt).
  uint64_t device_calls = 0;
  uint64_t device_waits = 0;
  // Device executor: legalizing rounds run in device loops without the
  // host (device::LoopControl; counted in flips.legalize_rounds too).
  uint64_t device_loop_rounds = 0;
  // ... and how often a loop handed a worklist that outgrew it back.
  uint64_t device_loop_returns = 0;
  // Device executor: attempts that found the host mesh changed behind its
  // back (DeviceAttempt::resyncs; always 0 unless the update driver forgot
  // an Invalidate(): tests check it).
  uint64_t device_resyncs = 0;
  // Device executor: attempts that checked the host mesh by a pass over it
  // (DeviceAttempt::fingerprint_passes): the first of a session, and those
  // after a change on the host that it did not name or named beyond a
  // patch (rebuild, renumbering, the compaction after removals; re-
  // insertions' named changes too with KINETRI_DEVICE_CHECK=1).
  uint64_t device_fingerprint_passes = 0;
  // Device executor: attempts that sent the host's changes (re-insertion)
  // alone, not the whole mesh (DeviceAttempt::patched_uploads).
  uint64_t device_patched_uploads = 0;
};

class Triangulation {
 public:
  // Builds the Delaunay triangulation of `points` (id = index). `cancel`
  // (optional) is polled while it validates and builds (CANCELLED /
  // DEADLINE_EXCEEDED within tens of milliseconds; the sort into spatial
  // order, about 0.1 s per 1M points, is not interrupted).
  static absl::StatusOr<Triangulation> Create(
      absl::Span<const Vec2> points, const TriangulationOptions& options = {},
      const CancelToken* cancel = nullptr);

  Triangulation(Triangulation&&) noexcept;
  Triangulation& operator=(Triangulation&&) noexcept;
  ~Triangulation();

  // Moves the points. On error nothing changes. `cancel` (optional) is
  // polled while the step runs; when it fires the step stops and returns
  // CANCELLED / DEADLINE_EXCEEDED with the triangulation exactly as before
  // the call (same positions, same Delaunay triangulation, same step
  // count). The region executor (the default) undoes what the step did,
  // in milliseconds, in any phase; the round and device executors, once
  // flips have begun, rebuild the previous triangulation from the
  // unchanged positions.
  absl::StatusOr<StepReport> ApplyDisplacements(
      const DisplacementBatch& batch, const CancelToken* cancel = nullptr);
  // An independent copy (same points, ids, mesh, options and step count;
  // its own thread arena and scratch). Costs a copy of the arrays: about
  // 100 bytes per point. Lets readers keep an immutable snapshot while a
  // writer moves a copy.
  Triangulation Clone() const;
  // Device memory held by the device executor (0 for the CPU executors).
  uint64_t device_bytes() const;
  // Host memory the device executor holds beside the mesh (0 for the CPU
  // executors).
  uint64_t device_host_bytes() const;
  // The device executor (executor == kDevice), else null. Queries
  // (core/queries.h) run on it, over the view of the current step.
  device::DeviceExecutor* device_executor() const { return device_.get(); }
  // Steps applied so far (successful ApplyDisplacements calls).
  uint64_t steps() const { return steps_; }

  // Checks topology, orientation, hull and the empty-circle property of every
  // edge exactly; also the point/site bookkeeping.
  absl::Status Validate() const;

  uint32_t size() const { return static_cast<uint32_t>(pos_.size()); }
  uint32_t num_sites() const { return static_cast<uint32_t>(sites_.size()); }
  bool is_planar() const { return !mesh_.empty(); }
  int num_threads() const;
  const TriangulationOptions& options() const { return options_; }

  Vec2 Position(uint32_t id) const { return pos_[int_of_ext_[id]]; }
  std::vector<Vec2> Positions() const;  // by external id

  // Delaunay edges as pairs of external ids (of each site's smallest-id
  // point), each pair ordered, the list sorted.
  std::vector<std::pair<uint32_t, uint32_t>> Edges() const;

  // Finite Delaunay triangles, counter-clockwise, as external ids (each
  // corner the smallest id of its coincident points). Empty in line mode.
  std::vector<std::array<uint32_t, 3>> Triangles() const;
  // Triangles() in pieces, for streaming: the triangle slots are
  // [0, num_triangle_slots()); AppendTriangles appends the triangles of
  // the slots from *slot on until `max` are appended or the slots run out,
  // advancing *slot (calls from slot 0 on list Triangles() in order), and
  // CountTriangles counts those of slots [lo, hi).
  uint32_t num_triangle_slots() const { return mesh_.num_triangles(); }
  void AppendTriangles(uint32_t* slot, size_t max,
                       std::vector<std::array<uint32_t, 3>>* out) const;
  uint64_t CountTriangles(uint32_t lo, uint32_t hi) const;

  // Read-only view for the executors (mesh only).
  TriangulationView view() const;

  // view() plus contiguous neighbour rows for graph searches. The rows are
  // built on the first call after a change (in parallel, inside the arena)
  // and reused until the next step; concurrent callers wait for one build.
  TriangulationView query_view() const;
  // What a cached cell index is for, each with its own slots.
  enum class CellIndexUse { kRadius = 0, kNearest = 1 };
  // A cell index over this step's sites (core/cell_index.h) for one use:
  // radius queries (key: the radius, which is the cell side) or k-nearest
  // queries (key: k). Made by `make` on the first call of a step for this
  // use and key, and kept for later batches of the same step and key (two
  // radii and one k at a time, the least recently asked for replaced;
  // `make` may return null: the graph is used, and that decision is kept
  // too). Concurrent callers wait for one build.
  std::shared_ptr<const CellIndex> CachedCellIndex(
      CellIndexUse use, double key,
      const std::function<std::shared_ptr<const CellIndex>()>& make) const;
  // Whether CachedCellIndex holds a decision for (use, key) in this step.
  bool HasCachedCellIndex(CellIndexUse use, double key) const;
  // The hint grid that starts position queries' walks (core/hint_grid.h),
  // built on the first call of a step. Hints only start walks, so a grid
  // serves up to 4 steps after the one it was built for (renumbered with
  // the points when a step renumbers them), while every point is a site
  // of its own and none joined or left; it may lie a little behind the
  // positions.
  std::shared_ptr<const HintGrid> CachedHintGrid() const;
  // query_view() when its rows are already built, else view(): for a
  // search that walks each fan once anyway (all-points NN), building the
  // rows first would cost two more walks of every fan.
  TriangulationView view_with_cached_rows() const;

  // Runs fn inside this triangulation's thread arena.
  template <typename Fn>
  void Run(Fn&& fn) const;

 private:
  Triangulation() = default;
  void RunImpl(const std::function<void()>& fn) const;

  // Full construction from positions in external order, on all the arena's
  // threads (Hilbert order by a parallel radix sort, the triangulation in
  // strips: core/strip_builder.h). All or nothing: false when `cancel`
  // fired, and then nothing of the object changed.
  bool Rebuild(const std::vector<Vec2>& positions_by_ext,
               const CancelToken* cancel = nullptr);
  // Local update attempt from pos_ to `to`; false if it must fall back.
  // On failure the mesh is back to a valid state for pos_ and
  // stuck_vertices lists vertices of the triangles that could not be fixed.
  // Vertices that fixing held back (RoundStepPolicy::hold_culprits) get
  // their old positions in `to` (their whole site) and are appended to
  // *held, whether or not the attempt passed.
  //
  // What the update loop wrote to its goal (`to`) and to pos_ between two
  // device attempts (DeviceExecutor::PositionsWrittenAt): the writes of
  // TryStep are added to it. `known` false: not tracked (the next attempt
  // compares the whole arrays).
  struct PositionWrites {
    bool known = false;
    std::vector<uint32_t> to, from;
  };
  bool TryStep(std::vector<Vec2>& to, const std::vector<uint32_t>* moved,
               const std::vector<uint32_t>* seeds, int depth,
               const CancelToken* cancel, StepReport* report,
               std::vector<uint32_t>* stuck_vertices,
               std::vector<uint32_t>* held, PositionWrites* writes);
  // TryStep's second half: the step split in two halves (depth + 1).
  bool SplitStep(std::vector<Vec2>& to, const std::vector<uint32_t>* moved,
                 const std::vector<uint32_t>* seeds, int depth,
                 const CancelToken* cancel, StepReport* report,
                 std::vector<uint32_t>* stuck_vertices,
                 std::vector<uint32_t>* held);
  // TryStep's attempt on the device executor: *result 1 fixed, 0 stuck
  // (stuck_vertices filled), -1 cancelled, -2 too tangled (rebuild); held
  // and writes as TryStep's.
  absl::Status AttemptOnDevice(std::vector<Vec2>& to,
                               const std::vector<uint32_t>* moved,
                               const std::vector<uint32_t>* seeds,
                               const CancelToken* cancel, StepReport* report,
                               std::vector<uint32_t>* stuck_vertices,
                               std::vector<uint32_t>* held,
                               PositionWrites* writes, int* result);
  // The vertices fixing held back go back to pos_ in `to`, with their
  // coincident points, and are appended to *out; the entries of `to` it
  // wrote are appended to *written when it is not null.
  void KeepHeldBack(const std::vector<uint32_t>& held, std::vector<Vec2>& to,
                    std::vector<uint32_t>* out,
                    std::vector<uint32_t>* written) const;
  // The host changed mesh_ (the device copy must be uploaded again).
  void MeshChangedOnHost();
  // The host changed only the half-edges of `triangles` (vertex operations,
  // flips) and the vertex_edge entries of `vertices` (removed ones): the
  // device's copy takes those triangles with their neighbours and the
  // vertex_edge of their corners (DeviceExecutor::ChangedOnHost). Called
  // after the change (a free slot is taken as it is), or before it with
  // every triangle it will write (a removal: the star); what an operation
  // changes lies there: a half-edge outside `triangles` whose twin changed
  // last pointed into one of them, a vertex whose vertex_edge changed is
  // a corner of one.
  void MeshChangedOnHostAt(const std::vector<uint32_t>& triangles,
                           const std::vector<uint32_t>& vertices);
  // Coincident points whose positions in `next` leave their site: detached
  // from it (they are inserted again at the end of the step).
  std::vector<uint32_t> DetachPartingPoints(const std::vector<Vec2>& next);
  // What DetachPartingPoints changed (rep_ and dup_next_ entries, as they
  // were, in order), so that a step stopped afterwards can put the
  // coincident-point chains back: UndoDetach.
  std::vector<std::pair<uint32_t*, uint32_t>> detach_log_;
  void UndoDetach();
  // Moves to `next` (swapped into pos_; `next` keeps the old positions on
  // success, the new ones on failure) and inserts the vertices in
  // `reinsert` (removed from the mesh or detached) at their new positions;
  // refreshes the site list.
  bool FinishLocalStep(std::vector<Vec2>& next, std::vector<uint32_t> reinsert,
                       std::vector<uint32_t>& hints, StepReport* report,
                       std::string* reason);
  // Kinetic path of the region executor; false (with reason): rebuild.
  // *cancelled: 0 ran to the end, 1 stopped by `cancel` with nothing
  // changed, 2 stopped after changing the mesh (restore it).
  // *untouched (optional): on failure, the attempt changed nothing (the
  // cost model chose a rebuild before any flip).
  bool RegionUpdate(std::vector<Vec2>& next,
                    const std::vector<uint32_t>& moved_points,
                    const CancelToken* cancel, StepReport* report,
                    std::string* reason, int* cancelled,
                    bool* untouched = nullptr);
  // Kinetic path of the round executor; false (with reason): rebuild.
  bool LocalUpdate(std::vector<Vec2>& next,
                   const std::vector<uint32_t>& moved_points,
                   const CancelToken* cancel, StepReport* report,
                   std::string* reason, int* cancelled);
  // Inserts the points (at pos_) into the mesh in rounds: locate all in
  // parallel, split one point per triangle, fix and legalize together.
  bool InsertBatch(std::vector<uint32_t> pending,
                   const std::vector<uint32_t>& hints, StepReport* report);
  // Joins and leaves of at most this many points are always made locally
  // (past it, only while they are at most 1/8 of the points).
  static constexpr uint64_t kLocalChangesMin = 4096;
  // Removes the points `leaving` (external ids) and inserts `joining` into
  // the mesh locally (planar mode), then renumbers the points (see
  // DisplacementBatch). False (with reason) when the mesh cannot be
  // updated locally (degenerate leftovers: JoinsByRebuild() has taken the
  // rest); the caller then rebuilds with JoinedPositions().
  bool JoinAndLeave(const std::vector<uint32_t>& leaving,
                    const std::vector<Vec2>& joining, StepReport* report,
                    std::string* reason);
  // True (with reason) when `leaving` points leaving and `joining` joining
  // are cheaper to make by a rebuild than locally, or cannot be made
  // locally (line mode).
  bool JoinsByRebuild(uint64_t leaving, uint64_t joining,
                      std::string* reason) const;
  // Positions after `leaving` leave and `joining` join, in the new order;
  // the points that stay are at by_int (internal order: pos_ or a step's
  // next positions).
  std::vector<Vec2> JoinedPositions(const std::vector<uint32_t>& leaving,
                                    const std::vector<Vec2>& joining,
                                    const std::vector<Vec2>& by_int) const;
  // sites_ and has_duplicates_ from rep_ and dup_next_.
  void RefreshSites();
  double MeanEdgeSpan() const;
  // The mean distance between the slots of neighbouring triangles.
  double MeanTriangleSpan() const;
  // The locality check after a step (renumber_stretch and
  // triangle_sort_stretch): renumbers, or sorts the triangles again, when
  // their order has spread; says which in report.
  void KeepLocality(StepReport* report);
  // Smallest external id among the points of the site of vertex v.
  uint32_t SiteId(uint32_t v) const;
  void Renumber();
  // Renumbers the sites of the hint grid a step carries (Rebuild and
  // Renumber, before they swap in the new numbering).
  void RenumberCarriedHints(absl::FunctionRef<uint32_t(uint32_t)> new_of_old);

  TriangulationOptions options_;
  std::unique_ptr<tbb::task_arena> arena_;

  std::vector<Vec2> pos_;   // by internal id
  std::vector<Vec2> next_;  // the step's new positions (kept: no page faults)
  std::vector<uint32_t> ext_of_int_;
  std::vector<uint32_t> int_of_ext_;
  std::vector<uint32_t> rep_;       // site representative, internal id
  std::vector<uint32_t> dup_next_;  // next point of the same site
  bool has_duplicates_ = false;
  // Per point: moved by the dense batch being applied (scratch).
  std::vector<uint8_t> moved_flag_;
  std::vector<uint32_t> sites_;  // representatives, ascending

  Mesh mesh_;                        // empty in line mode
  std::vector<uint32_t> line_;       // line mode: sites in (x, y) order
  std::vector<uint32_t> line_rank_;  // line mode: rank of each site

  struct AdjacencyCache;
  std::unique_ptr<AdjacencyCache> adjacency_;

  FlipScratch scratch_;
  std::unique_ptr<device::DeviceExecutor> device_;  // executor == kDevice
  std::string device_failure_;  // why the device failed this step, if it did
  RegionExecutor region_executor_;
  // Vertex tolerances for the region executor; valid only while they
  // certify mesh_ at pos_ (every other change of either invalidates them).
  MotionFilter motion_filter_;
  int filter_wait_ = 0;     // steps before sampling again
  int filter_backoff_ = 0;  // the current wait after a failed filter
  bool too_tangled_ = false;
  std::vector<uint32_t> removal_touched_;
  std::vector<uint32_t> reinsert_hints_;  // RegionUpdate's walk starts
  double baseline_span_ = 0.0;            // MeanEdgeSpan at the last numbering
  double baseline_triangle_span_ = 0.0;   // MeanTriangleSpan at the last sort
  uint64_t steps_ = 0;
};

template <typename Fn>
void Triangulation::Run(Fn&& fn) const {
  RunImpl(std::function<void()>(std::forward<Fn>(fn)));
}

}  // namespace kinetri::core

#endif  // KINETRI_CORE_TRIANGULATION_H_
