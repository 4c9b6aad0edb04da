// Kinetic Delaunay triangulation of a set of moving 2D points.
#include "core/triangulation.h"

#include <tbb/global_control.h>
#include <tbb/parallel_reduce.h>
#include <tbb/parallel_sort.h>
#include <tbb/task_arena.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <mutex>
#include <numeric>
#include <optional>
#include <utility>

#include "absl/strings/str_cat.h"
#include "core/cell_index.h"
#include "core/flip_rules.h"
#include "core/hint_grid.h"
#include "core/mesh_scan.h"
#include "core/parallel.h"
#include "core/predicates.h"
#include "core/site_adjacency.h"
#include "core/spatial_order.h"
#include "core/strip_builder.h"
#include "core/vertex_ops.h"

namespace kinetri::core {
namespace {

double SecondsSince(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0)
      .count();
}

absl::Status CheckCoordinate(double v, absl::string_view field, size_t index,
                             const char* axis) {
  if (std::isnan(v)) {
    return absl::InvalidArgumentError(
        absl::StrCat(field, "[", index, "].", axis, " is NaN"));
  }
  if (std::isinf(v)) {
    return absl::InvalidArgumentError(
        absl::StrCat(field, "[", index, "].", axis, " is infinite"));
  }
  if (!InExactDomain(v)) {
    return absl::InvalidArgumentError(absl::StrCat(
        field, "[", index, "].", axis, " = ", v,
        " is outside the exact range: 0 or magnitude in [2^-100, 2^100]"));
  }
  return absl::OkStatus();
}

absl::Status CheckPosition(const Vec2& p, absl::string_view field,
                           size_t index) {
  absl::Status s = CheckCoordinate(p.x, field, index, "x");
  if (!s.ok()) return s;
  return CheckCoordinate(p.y, field, index, "y");
}

// ids[i] < seen.size() and pairwise distinct (errors name `field`); marks
// each in `seen`.
absl::Status MarkDistinctIds(absl::Span<const uint32_t> ids, const char* field,
                             std::vector<uint8_t>& seen) {
  const size_t n = seen.size();
  for (size_t i = 0; i < ids.size(); ++i) {
    const uint32_t ext = ids[i];
    if (ext >= n) {
      return absl::NotFoundError(absl::StrCat(
          field, "[", i, "] = ", ext, ": no such point (size ", n, ")"));
    }
    if (seen[ext]) {
      return absl::InvalidArgumentError(
          absl::StrCat(field, "[", i, "] = ", ext, " appears twice"));
    }
    seen[ext] = 1;
  }
  return absl::OkStatus();
}

Vec2 Midpoint(const Vec2& a, const Vec2& b) {
  return {a.x + 0.5 * (b.x - a.x), a.y + 0.5 * (b.y - a.y)};
}

// The midpoint of a vertex's motion a -> b as a sub-step goal, when there is
// one: inside the exact domain and strictly between the two ends.
std::optional<Vec2> HalfwayGoal(const Vec2& a, const Vec2& b) {
  const Vec2 h = Midpoint(a, b);
  if (!InExactDomain(h.x) || !InExactDomain(h.y) || h == a || h == b) {
    return std::nullopt;
  }
  return h;
}

// Every point at site v (v and the duplicates chained after it, all at
// one position) gets the goal g; the entries written are appended to
// *written when it is not null.
void SetSiteGoal(const std::vector<uint32_t>& dup_next, uint32_t v,
                 const Vec2& g, std::vector<Vec2>& goal,
                 std::vector<uint32_t>* written) {
  for (uint32_t p = v; p != kNoVertex; p = dup_next[p]) {
    goal[p] = g;
    if (written != nullptr) written->push_back(p);
  }
}

}  // namespace

DisplacementBatch DisplacementBatch::Dense(std::vector<Vec2> deltas) {
  return {Mode::kDelta, {}, std::move(deltas), {}, {}};
}
DisplacementBatch DisplacementBatch::Sparse(std::vector<uint32_t> ids,
                                            std::vector<Vec2> deltas) {
  return {Mode::kDelta, std::move(ids), std::move(deltas), {}, {}};
}
DisplacementBatch DisplacementBatch::Absolute(std::vector<Vec2> positions) {
  return {Mode::kAbsolute, {}, std::move(positions), {}, {}};
}
DisplacementBatch DisplacementBatch::AbsoluteSparse(
    std::vector<uint32_t> ids, std::vector<Vec2> positions) {
  return {Mode::kAbsolute, std::move(ids), std::move(positions), {}, {}};
}

const char* ExecutorName(Executor executor) {
  switch (executor) {
    case Executor::kRegions:
      return "regions";
    case Executor::kRounds:
      return "rounds";
    case Executor::kDevice:
      return "device";
  }
  return "unknown";
}

const char* UpdatePathName(UpdatePath path) {
  switch (path) {
    case UpdatePath::kNoop:
      return "noop";
    case UpdatePath::kLocal:
      return "local";
    case UpdatePath::kSubdivided:
      return "subdivided";
    case UpdatePath::kReinserted:
      return "reinserted";
    case UpdatePath::kRebuilt:
      return "rebuilt";
  }
  return "unknown";
}

// The thread arena of a triangulation (0 threads: all cores).
static std::unique_ptr<tbb::task_arena> MakeArena(int num_threads) {
  return num_threads > 0 ? std::make_unique<tbb::task_arena>(num_threads)
                         : std::make_unique<tbb::task_arena>();
}

struct Triangulation::AdjacencyCache {
  std::mutex mu;
  bool valid = false;
  SiteAdjacency rows;
  // The queries' cell indexes of this step (CachedCellIndex): two radii
  // (a simulation often asks two cut-offs per step), one k-nearest index.
  struct CellsSlot {
    bool valid = false;
    double key = 0.0;
    uint64_t used = 0;  // when it was last asked for (the oldest goes)
    std::shared_ptr<const CellIndex> cells;
  };
  static constexpr int kRadiusSlots = 2;
  CellsSlot cells[kRadiusSlots + 1];
  uint64_t cells_clock = 0;
  // The slots of a use: [first, first + count).
  static std::pair<int, int> SlotsOf(CellIndexUse use) {
    return use == CellIndexUse::kRadius ? std::pair{0, kRadiusSlots}
                                        : std::pair{kRadiusSlots, 1};
  }
  // The slot holding (use, key), or null.
  CellsSlot* Find(CellIndexUse use, double key) {
    const auto [first, count] = SlotsOf(use);
    for (int i = first; i < first + count; ++i) {
      if (cells[i].valid && cells[i].key == key) return &cells[i];
    }
    return nullptr;
  }
  // Position queries' walk starts of this step (CachedHintGrid).
  std::shared_ptr<const HintGrid> hints;
  // A grid of an earlier step (built at step `stale_step`), kept while
  // every point keeps its internal id and is a site of its own (local
  // steps without renumbering, joins or coincident points): a hint is only
  // where a walk starts (answers do not depend on it), and one a few steps
  // old still lies next to its query. Its build was 7-10 ms of every step's
  // first position batch at 1M points.
  std::shared_ptr<const HintGrid> stale_hints;
  uint64_t stale_step = 0;
  uint64_t hints_step = 0;  // when `hints` was built
  // While a step runs: the grid it may pass on. Rebuild() and Renumber()
  // renumber its sites with the points (or drop it when points join or
  // leave); the step sets it as `stale_hints` where it ends with every
  // point a site of its own.
  std::shared_ptr<const HintGrid> carried;
  uint64_t carried_step = 0;
};

// A hint grid serves at most this many steps after the one it was built
// for.
constexpr uint64_t kMaxHintGridAge = 4;

Triangulation::Triangulation(Triangulation&&) noexcept = default;
Triangulation& Triangulation::operator=(Triangulation&&) noexcept = default;
Triangulation::~Triangulation() = default;

int Triangulation::num_threads() const {
  return arena_ ? arena_->max_concurrency() : 1;
}

void Triangulation::RunImpl(const std::function<void()>& fn) const {
  arena_->execute(fn);
}

absl::StatusOr<Triangulation> Triangulation::Create(
    absl::Span<const Vec2> points, const TriangulationOptions& options,
    const CancelToken* cancel) {
  if (points.size() >= (size_t{1} << 29)) {
    return absl::ResourceExhaustedError(absl::StrCat(
        "points: ", points.size(), " points exceed the limit of 2^29"));
  }
  if (options.num_threads < 0) {
    return absl::InvalidArgumentError("num_threads must be >= 0");
  }
  const RoundStepPolicy& ro = options.round;
  if (ro.max_halvings < 0 || ro.max_halvings > 30 || ro.max_passes < 1 ||
      ro.max_passes > 4096 || ro.max_subdivision_depth < 0 ||
      ro.max_subdivision_depth > 16 ||
      !(ro.rebuild_fraction >= 0.0 && ro.rebuild_fraction <= 1.0) ||
      !(ro.sparse_fraction >= 0.0 && ro.sparse_fraction <= 1.0) ||
      !(ro.reinsert_fraction >= 0.0 && ro.reinsert_fraction <= 1.0)) {
    return absl::InvalidArgumentError(
        "round policy: max_halvings must be in [0, 30], max_passes in [1, "
        "4096], max_subdivision_depth in [0, 16], rebuild_fraction, "
        "sparse_fraction and reinsert_fraction in [0, 1]");
  }
  const RegionStepPolicy& rp = options.region;
  if (rp.region_triangles < 16 || rp.max_halvings < 0 || rp.max_halvings > 60 ||
      rp.max_passes < 1 || rp.max_passes > 1024 ||
      !(rp.sparse_fraction >= 0.0 && rp.sparse_fraction <= 1.0) ||
      !(rp.held_vertex_cost >= 0.0 && rp.held_vertex_cost < 1e9) ||
      !(rp.rebuild_point_cost >= 0.0 && rp.rebuild_point_cost < 1e9) ||
      !(rp.rebuild_fixed_cost >= 0.0 && rp.rebuild_fixed_cost < 1e12) ||
      !(rp.keep_across_flips >= 0.0 && rp.keep_across_flips <= 1.0)) {
    return absl::InvalidArgumentError(
        "region policy: region_triangles must be >= 16, max_halvings in "
        "[0, 60], max_passes in [1, 1024], sparse_fraction and "
        "keep_across_flips in [0, 1], costs finite and >= 0");
  }
  for (size_t i = 0; i < points.size(); ++i) {
    absl::Status s = CheckPosition(points[i], "points", i);
    if (!s.ok()) return s;
    if (cancel != nullptr && i % (size_t{1} << 20) == 0) {
      if (absl::Status c = cancel->Check("creation"); !c.ok()) return c;
    }
  }
  Triangulation t;
  t.options_ = options;
  t.adjacency_ = std::make_unique<AdjacencyCache>();
  t.arena_ = MakeArena(options.num_threads);
  if (options.executor == Executor::kDevice) {
    absl::StatusOr<std::unique_ptr<device::DeviceExecutor>> d =
        device::MakeDeviceExecutor(options.device_backend);
    if (!d.ok()) return d.status();
    t.device_ = *std::move(d);
  }
  std::vector<Vec2> copy(points.begin(), points.end());
  bool built = true;
  t.Run([&] { built = t.Rebuild(copy, cancel); });
  if (!built) return cancel->Check("creation");
  return t;
}

Triangulation Triangulation::Clone() const {
  Triangulation t;
  t.options_ = options_;
  t.adjacency_ = std::make_unique<AdjacencyCache>();
  t.arena_ = MakeArena(options_.num_threads);
  t.pos_ = pos_;
  t.ext_of_int_ = ext_of_int_;
  t.int_of_ext_ = int_of_ext_;
  t.rep_ = rep_;
  t.dup_next_ = dup_next_;
  t.has_duplicates_ = has_duplicates_;
  t.sites_ = sites_;
  t.mesh_ = mesh_;
  t.line_ = line_;
  t.line_rank_ = line_rank_;
  t.baseline_span_ = baseline_span_;
  t.baseline_triangle_span_ = baseline_triangle_span_;
  t.steps_ = steps_;
  if (motion_filter_.valid()) t.motion_filter_ = motion_filter_;
  t.filter_wait_ = filter_wait_;
  t.filter_backoff_ = filter_backoff_;
  if (device_ != nullptr) {
    // Its own device copy (uploaded by its first step). The backend was
    // available when this triangulation was made; should it be gone (a GPU
    // lost), the copy continues on the round executor.
    absl::StatusOr<std::unique_ptr<device::DeviceExecutor>> d =
        device::MakeDeviceExecutor(device_->backend());
    if (d.ok()) {
      t.device_ = *std::move(d);
    } else {
      t.options_.executor = Executor::kRounds;
    }
  }
  return t;
}

void Triangulation::MeshChangedOnHost() {
  if (device_ != nullptr) device_->Invalidate();
}

void Triangulation::MeshChangedOnHostAt(const std::vector<uint32_t>& triangles,
                                        const std::vector<uint32_t>& vertices) {
  if (device_ == nullptr) return;
  const MeshView m = std::as_const(mesh_).view();
  const uint32_t nt = mesh_.num_triangles();
  const uint32_t nv = mesh_.num_vertices();
  std::vector<uint32_t> tris, verts(vertices);
  tris.reserve(4 * triangles.size());
  verts.reserve(vertices.size() + 3 * triangles.size());
  for (uint32_t t : triangles) {
    if (t >= nt) continue;
    tris.push_back(t);
    if (m.IsFree(t)) continue;
    for (uint32_t e = 3 * t; e < 3 * t + 3; ++e) {
      if (m.twin[e] != kNoEdge) tris.push_back(TriangleOf(m.twin[e]));
      if (m.origin[e] < nv) verts.push_back(m.origin[e]);
    }
  }
  device_->ChangedOnHost(tris, verts);
}

uint64_t Triangulation::device_bytes() const {
  return device_ != nullptr ? device_->device_bytes() : 0;
}

uint64_t Triangulation::device_host_bytes() const {
  return device_ != nullptr ? device_->host_bytes() : 0;
}

std::vector<Vec2> Triangulation::Positions() const {
  std::vector<Vec2> out(pos_.size());
  for (size_t i = 0; i < pos_.size(); ++i) out[ext_of_int_[i]] = pos_[i];
  return out;
}

TriangulationView Triangulation::view() const {
  TriangulationView v;
  v.pos = pos_.data();
  v.ext_of_int = ext_of_int_.data();
  v.int_of_ext = int_of_ext_.data();
  v.rep = rep_.data();
  v.dup_next = dup_next_.data();
  v.sites = sites_.data();
  v.num_points = size();
  v.num_sites = num_sites();
  v.mesh = mesh_.view();
  if (mesh_.empty()) v.mesh.num_half_edges = 0;
  v.vertex_edge = mesh_.vertex_edge().data();
  v.line = line_.data();
  v.line_rank = line_rank_.data();
  return v;
}

std::shared_ptr<const CellIndex> Triangulation::CachedCellIndex(
    CellIndexUse use, double key,
    const std::function<std::shared_ptr<const CellIndex>()>& make) const {
  std::lock_guard<std::mutex> lock(adjacency_->mu);
  AdjacencyCache& cache = *adjacency_;
  AdjacencyCache::CellsSlot* slot = cache.Find(use, key);
  if (slot == nullptr) {
    // An empty slot of the use, else its least recently asked for.
    const auto [first, count] = AdjacencyCache::SlotsOf(use);
    slot = &cache.cells[first];
    for (int i = first; i < first + count; ++i) {
      AdjacencyCache::CellsSlot& c = cache.cells[i];
      if (!c.valid) {
        slot = &c;
        break;
      }
      if (c.used < slot->used) slot = &c;
    }
    slot->cells.reset();
    slot->valid = false;
    slot->cells = make();
    slot->key = key;
    slot->valid = true;
  }
  slot->used = ++cache.cells_clock;
  return slot->cells;
}

std::shared_ptr<const HintGrid> Triangulation::CachedHintGrid() const {
  const TriangulationView v = view();
  std::lock_guard<std::mutex> lock(adjacency_->mu);
  AdjacencyCache& cache = *adjacency_;
  if (cache.hints == nullptr) {
    if (cache.stale_hints != nullptr &&
        steps_ - cache.stale_step <= kMaxHintGridAge) {
      cache.hints = cache.stale_hints;
      cache.hints_step = cache.stale_step;
    } else {
      cache.hints = std::make_shared<const HintGrid>(v);
      cache.hints_step = steps_;
    }
    cache.stale_hints.reset();
  }
  return cache.hints;
}

bool Triangulation::HasCachedCellIndex(CellIndexUse use, double key) const {
  std::lock_guard<std::mutex> lock(adjacency_->mu);
  return adjacency_->Find(use, key) != nullptr;
}

TriangulationView Triangulation::query_view() const {
  TriangulationView v = view();
  std::lock_guard<std::mutex> lock(adjacency_->mu);
  if (!adjacency_->valid) {
    Run([&] { BuildSiteAdjacency(v, &adjacency_->rows); });
    adjacency_->valid = true;
  }
  v.adj_offsets = adjacency_->rows.offsets.data();
  v.adj = adjacency_->rows.neighbours.data();
  if (!adjacency_->rows.member_offsets.empty()) {
    v.site_member_offsets = adjacency_->rows.member_offsets.data();
    v.site_members = adjacency_->rows.members.data();
  }
  return v;
}

TriangulationView Triangulation::view_with_cached_rows() const {
  {
    std::lock_guard<std::mutex> lock(adjacency_->mu);
    if (!adjacency_->valid) return view();
  }
  return query_view();  // built: returns at once
}

bool Triangulation::Rebuild(const std::vector<Vec2>& positions_by_ext,
                            const CancelToken* cancel) {
  motion_filter_.Invalidate();
  // Built aside and swapped in at the end, so that a cancelled rebuild
  // leaves the previous triangulation as it was.
  const uint32_t n = static_cast<uint32_t>(positions_by_ext.size());
  std::vector<uint64_t> keys;  // Hilbert keys, in internal order
  std::vector<uint32_t> ext_of_int = HilbertOrder(positions_by_ext, &keys);
  std::vector<uint32_t> int_of_ext(n, 0);
  std::vector<Vec2> pos(n);
  ParallelFor(0, n, [&](size_t i) {
    int_of_ext[ext_of_int[i]] = static_cast<uint32_t>(i);
    pos[i] = positions_by_ext[ext_of_int[i]];
  });
  // Group coincident points (each group's representative is its smallest
  // id, its chain in increasing id). Equal positions have equal Hilbert
  // keys, so every group lies in one run of equal keys of the internal
  // order: only runs longer than one point (rare) are sorted, by position
  // with id as tie-break.
  std::vector<uint32_t> rep(n, kNoVertex), dup_next(n, kNoVertex);
  bool has_duplicates = false;
  std::vector<uint32_t> run;
  for (uint32_t k = 0; k < n;) {
    uint32_t j = k + 1;
    while (j < n && keys[j] == keys[k]) ++j;
    if (j - k == 1) {
      rep[k] = k;
      k = j;
      continue;
    }
    run.resize(j - k);
    std::iota(run.begin(), run.end(), k);
    std::sort(run.begin(), run.end(), [&](uint32_t a, uint32_t b) {
      if (pos[a] != pos[b]) return LexLess(pos[a], pos[b]);
      return a < b;
    });
    for (size_t g = 0; g < run.size();) {
      size_t h = g + 1;
      while (h < run.size() && pos[run[h]] == pos[run[g]]) ++h;
      for (size_t m = g; m < h; ++m) {
        rep[run[m]] = run[g];
        if (m + 1 < h) dup_next[run[m]] = run[m + 1];
      }
      if (h - g > 1) has_duplicates = true;
      g = h;
    }
    k = j;
  }
  std::vector<uint32_t> sites =
      has_duplicates ? FilterIndices(n, [&](size_t i) { return rep[i] == i; })
                     : std::vector<uint32_t>(n);
  if (!has_duplicates) std::iota(sites.begin(), sites.end(), 0u);
  if (cancel != nullptr && cancel->Cancelled()) return false;
  bool cancelled = false;
  Mesh mesh = BuildDelaunayInStrips(pos, sites, DefaultStripCount(sites.size()),
                                    cancel, &cancelled);
  if (cancelled || (cancel != nullptr && cancel->Cancelled())) return false;
  if (n == size()) {
    RenumberCarriedHints(
        [&](uint32_t s) { return int_of_ext[ext_of_int_[s]]; });
  } else {
    std::lock_guard<std::mutex> lock(adjacency_->mu);
    adjacency_->carried.reset();
  }
  ext_of_int_ = std::move(ext_of_int);
  int_of_ext_ = std::move(int_of_ext);
  pos_ = std::move(pos);
  rep_ = std::move(rep);
  dup_next_ = std::move(dup_next);
  has_duplicates_ = has_duplicates;
  sites_ = std::move(sites);
  mesh_ = std::move(mesh);
  MeshChangedOnHost();
  removal_touched_.clear();
  line_.clear();
  line_rank_.clear();
  if (mesh_.empty()) {
    line_ = sites_;
    std::sort(line_.begin(), line_.end(), [&](uint32_t a, uint32_t b) {
      return LexLess(pos_[a], pos_[b]);
    });
    line_rank_.assign(n, kNoVertex);
    for (uint32_t r = 0; r < line_.size(); ++r) line_rank_[line_[r]] = r;
  }
  baseline_span_ = MeanEdgeSpan();
  baseline_triangle_span_ = MeanTriangleSpan();
  return true;
}

void Triangulation::RefreshSites() {
  sites_.clear();
  has_duplicates_ = false;
  for (uint32_t i = 0; i < size(); ++i) {
    if (rep_[i] == i) sites_.push_back(i);
    if (dup_next_[i] != kNoVertex) has_duplicates_ = true;
  }
}

namespace {

// The mean of span(e) over a sample of the mesh's half-edges: every
// kStride-th one (a prime, so the sample does not follow the three
// half-edges of a triangle), those for which span(e) is a number (>= 0;
// -1 leaves e out). The statistics only decide when to renumber or sort;
// a full pass cost 14 ms per check at 1M points. The spans are whole
// numbers and their sum stays far below 2^53, so it is exact in any order:
// the decisions are the same for any number of threads.
template <typename Span>
double MeanSampledSpan(const Mesh& mesh, Span&& span) {
  if (mesh.empty()) return 0.0;
  struct Acc {
    double sum = 0.0;
    uint64_t count = 0;
  };
  constexpr size_t kStride = 31;
  const size_t samples = (mesh.num_half_edges() + kStride - 1) / kStride;
  const Acc acc = tbb::parallel_reduce(
      tbb::blocked_range<size_t>(0, samples, 1 << 12), Acc{},
      [&](const tbb::blocked_range<size_t>& r, Acc a) {
        for (size_t i = r.begin(); i != r.end(); ++i) {
          const int64_t d = span(static_cast<uint32_t>(i * kStride));
          if (d < 0) continue;
          a.sum += static_cast<double>(d);
          ++a.count;
        }
        return a;
      },
      [](Acc a, const Acc& b) {
        a.sum += b.sum;
        a.count += b.count;
        return a;
      });
  return acc.count ? acc.sum / static_cast<double>(acc.count) : 0.0;
}

}  // namespace

double Triangulation::MeanEdgeSpan() const {
  const MeshView m = mesh_.view();
  return MeanSampledSpan(mesh_, [m](uint32_t e) -> int64_t {
    const uint32_t u = m.origin[e], v = m.Dest(e);
    if (u == kInfiniteVertex || v == kInfiniteVertex || u > v) return -1;
    return int64_t{v} - u;
  });
}

double Triangulation::MeanTriangleSpan() const {
  const MeshView m = mesh_.view();
  return MeanSampledSpan(mesh_, [m](uint32_t e) -> int64_t {
    const uint32_t f = m.twin[e];
    if (m.origin[e] == kNoVertex || f >= m.num_half_edges) return -1;
    const int64_t t = TriangleOf(e), u = TriangleOf(f);
    return t > u ? t - u : u - t;
  });
}

void Triangulation::KeepLocality(StepReport* report) {
  if (MeanEdgeSpan() > options_.renumber_stretch * baseline_span_ + 1.0) {
    Renumber();
    report->renumbered = true;
    return;
  }
  const double limit =
      options_.triangle_sort_stretch * baseline_triangle_span_ + 1.0;
  // (Steps end with no free slots; SortTriangles keys every slot by a
  // vertex.)
  if (mesh_.has_free_triangles() || !(MeanTriangleSpan() > limit)) return;
  // The same triangles in new slots: what refers to slots goes (the region
  // executor's kept apexes, by the mesh's content version; the device
  // copy); what refers to points stays (the numbering, the hint grids, the
  // vertex tolerances: they certify triangles, wherever they are kept).
  mesh_.SortTrianglesByVertex();
  MeshChangedOnHost();
  baseline_triangle_span_ = MeanTriangleSpan();
  report->triangles_sorted = true;
}

void Triangulation::RenumberCarriedHints(
    absl::FunctionRef<uint32_t(uint32_t)> new_of_old) {
  std::lock_guard<std::mutex> lock(adjacency_->mu);
  if (adjacency_->carried != nullptr) {
    adjacency_->carried = adjacency_->carried->Renumbered(new_of_old);
  }
}

void Triangulation::Renumber() {
  motion_filter_.Invalidate();
  const uint32_t n = size();
  const std::vector<uint32_t> old_of_new = HilbertOrder(pos_);
  std::vector<uint32_t> new_of_old(n);
  for (uint32_t i = 0; i < n; ++i) new_of_old[old_of_new[i]] = i;
  RenumberCarriedHints([&](uint32_t s) { return new_of_old[s]; });
  std::vector<Vec2> pos(n);
  std::vector<uint32_t> ext(n), rep(n), dup(n);
  ParallelFor(0, n, [&](size_t i) {
    const uint32_t o = old_of_new[i];
    pos[i] = pos_[o];
    ext[i] = ext_of_int_[o];
    rep[i] = new_of_old[rep_[o]];
    dup[i] = dup_next_[o] == kNoVertex ? kNoVertex : new_of_old[dup_next_[o]];
  });
  pos_ = std::move(pos);
  ext_of_int_ = std::move(ext);
  rep_ = std::move(rep);
  dup_next_ = std::move(dup);
  for (uint32_t i = 0; i < n; ++i) int_of_ext_[ext_of_int_[i]] = i;
  // Coincident points share a Hilbert key and keep their relative order, so
  // each site's representative is still its smallest id and chains stay
  // ascending.
  sites_.clear();
  for (uint32_t i = 0; i < n; ++i) {
    if (rep_[i] == i) sites_.push_back(i);
  }
  if (!mesh_.empty()) {
    mesh_.RenumberVertices(new_of_old);
    mesh_.SortTrianglesByVertex();
    MeshChangedOnHost();
  } else {
    for (uint32_t& v : line_) v = new_of_old[v];
    line_rank_.assign(n, kNoVertex);
    for (uint32_t r = 0; r < line_.size(); ++r) line_rank_[line_[r]] = r;
  }
  baseline_span_ = MeanEdgeSpan();
  baseline_triangle_span_ = MeanTriangleSpan();
}

void Triangulation::KeepHeldBack(const std::vector<uint32_t>& held,
                                 std::vector<Vec2>& to,
                                 std::vector<uint32_t>* out,
                                 std::vector<uint32_t>* written) const {
  for (uint32_t v : held) {
    SetSiteGoal(dup_next_, v, pos_[v], to, written);
    out->push_back(v);
  }
}

absl::Status Triangulation::AttemptOnDevice(
    std::vector<Vec2>& to, const std::vector<uint32_t>* moved,
    const std::vector<uint32_t>* seeds, const CancelToken* cancel,
    StepReport* report, std::vector<uint32_t>* stuck_vertices,
    std::vector<uint32_t>* held, PositionWrites* writes, int* result) {
  motion_filter_.Invalidate();
  std::vector<uint32_t> candidates;
  if (moved != nullptr) {
    candidates = KineticExecutor::CandidateTriangles(mesh_, *moved);
  }
  // What changed in `to` and pos_ since the last attempt, when the caller
  // followed it: the attempt looks for positions to send there alone.
  if (writes != nullptr) {
    if (writes->known) device_->PositionsWrittenAt(writes->to, writes->from);
    writes->to.clear();
    writes->from.clear();
    writes->known = true;
  }
  absl::StatusOr<device::DeviceAttempt> a =
      device_->Attempt(mesh_, to,
                       options_.round.hold_culprits ? absl::MakeConstSpan(pos_)
                                                    : absl::Span<const Vec2>(),
                       moved != nullptr ? &candidates : nullptr, seeds,
                       options_.round.rebuild_fraction, cancel);
  if (!a.ok()) return a.status();
  KeepHeldBack(a->held, to, held, writes != nullptr ? &writes->to : nullptr);
  report->fix_seconds += a->fix_seconds;
  report->legalize_seconds += a->legalize_seconds;
  report->transfer_seconds += a->transfer_seconds;
  report->transfer_bytes += a->bytes_uploaded + a->bytes_downloaded;
  report->device_calls += a->device_calls;
  report->device_waits += a->host_waits;
  report->device_loop_rounds += a->loop_rounds;
  report->device_loop_returns += a->loop_returns;
  report->device_resyncs += a->resyncs;
  report->device_fingerprint_passes += a->fingerprint_passes;
  report->device_patched_uploads += a->patched_uploads;
  if (a->cancelled) {
    *result = -1;
  } else if (a->tangled) {
    *result = -2;
  } else if (a->fixed) {
    report->flips += a->counts;
    *result = 1;
  } else {
    stuck_vertices->insert(stuck_vertices->end(), a->stuck_corners.begin(),
                           a->stuck_corners.end());
    *result = 0;
  }
  return absl::OkStatus();
}

bool Triangulation::TryStep(std::vector<Vec2>& to,
                            const std::vector<uint32_t>* moved,
                            const std::vector<uint32_t>* seeds, int depth,
                            const CancelToken* cancel, StepReport* report,
                            std::vector<uint32_t>* stuck_vertices,
                            std::vector<uint32_t>* held,
                            PositionWrites* writes) {
  if (device_ != nullptr) {
    int result = 0;
    const absl::Status st =
        AttemptOnDevice(to, moved, seeds, cancel, report, stuck_vertices, held,
                        writes, &result);
    if (!st.ok()) device_failure_ = std::string(st.message());
    if (!st.ok() || result == -2) {
      too_tangled_ = true;  // device error or tangled: rebuild on the host
      return false;
    }
    if (result < 0) return false;  // cancelled: the caller checks the token
    if (result == 1) {
      if (moved == nullptr) {
        pos_ = to;
        if (writes != nullptr) writes->known = false;  // (every entry)
      } else {
        for (uint32_t v : *moved) {
          for (uint32_t p = v; p != kNoVertex; p = dup_next_[p]) {
            pos_[p] = to[p];
            if (writes != nullptr) writes->from.push_back(p);
          }
        }
      }
      ++report->substeps;
      return true;
    }
    ++report->failed_attempts;
    if (depth >= options_.round.max_subdivision_depth) return false;
    // The halves' attempts send other arrays: the next one compares all.
    if (writes != nullptr) writes->known = false;
    return SplitStep(to, moved, seeds, depth, cancel, report, stuck_vertices,
                     held);
  }
  auto t0 = std::chrono::steady_clock::now();
  std::vector<uint32_t> invalid =
      KineticExecutor::FindInvalidTriangles(mesh_, to, moved);
  std::vector<uint32_t> touched, stuck;
  FixLog log;
  FlipCounts counts;
  if (moved == nullptr && invalid.size() > options_.round.rebuild_fraction *
                                               mesh_.num_triangles()) {
    // So much of the mesh is tangled that a rebuild is cheaper.
    report->fix_seconds += SecondsSince(t0);
    too_tangled_ = true;
    return false;
  }
  KineticExecutor::HoldBack hold{&pos_, &to, {}};
  const bool fixed = KineticExecutor::Fix(
      mesh_, to, std::move(invalid), scratch_, &counts, &touched, &log, &stuck,
      options_.round.hold_culprits ? &hold : nullptr);
  KeepHeldBack(hold.held, to, held, nullptr);
  report->fix_seconds += SecondsSince(t0);
  t0 = std::chrono::steady_clock::now();
  if (fixed) {
    report->flips += counts;
    if (seeds == nullptr) {
      KineticExecutor::Legalize(mesh_, to, nullptr, scratch_, &report->flips);
    } else {
      touched.insert(touched.end(), seeds->begin(), seeds->end());
      std::sort(touched.begin(), touched.end());
      touched.erase(std::unique(touched.begin(), touched.end()), touched.end());
      KineticExecutor::Legalize(mesh_, to, &touched, scratch_, &report->flips);
    }
    if (moved == nullptr) {
      pos_ = to;
    } else {  // sparse: only the moved sites (and their coincident points)
      for (uint32_t v : *moved) {
        for (uint32_t p = v; p != kNoVertex; p = dup_next_[p]) pos_[p] = to[p];
      }
    }
    ++report->substeps;
    report->legalize_seconds += SecondsSince(t0);
    return true;
  }
  ++report->failed_attempts;
  // Vertices of the triangles fixing could not repair: candidates for
  // re-insertion if splitting the step does not help.
  {
    const MeshView m = std::as_const(mesh_).view();
    for (uint32_t t : stuck) {
      for (uint32_t e = 3 * t; e < 3 * t + 3; ++e) {
        const uint32_t v = m.origin[e];
        stuck_vertices->push_back(
            (v != kInfiniteVertex && v != kNoVertex) ? v : kNoVertex);
      }
    }
  }
  KineticExecutor::Undo(mesh_, log);
  report->fix_seconds += SecondsSince(t0);
  if (depth >= options_.round.max_subdivision_depth) return false;
  return SplitStep(to, moved, seeds, depth, cancel, report, stuck_vertices,
                   held);
}

bool Triangulation::SplitStep(std::vector<Vec2>& to,
                              const std::vector<uint32_t>* moved,
                              const std::vector<uint32_t>* seeds, int depth,
                              const CancelToken* cancel, StepReport* report,
                              std::vector<uint32_t>* stuck_vertices,
                              std::vector<uint32_t>* held) {
  // Move halfway, then the rest.
  std::vector<Vec2> mid = pos_;
  auto halfway = [&](size_t i) {
    const Vec2 h = Midpoint(pos_[i], to[i]);
    mid[i] = InExactDomain(h.x) && InExactDomain(h.y) ? h : to[i];
  };
  ParallelFor(0, mid.size(), halfway);
  // Coincident points of one site move together.
  if (has_duplicates_) {
    for (uint32_t i = 0; i < mid.size(); ++i) {
      if (rep_[i] != i) mid[i] = mid[rep_[i]];
    }
  }
  // Each half's seeds: the stars of the moved vertices now, plus the
  // caller's seeds (the holes of vertices removed before the step, which
  // the stars do not cover; flips keep triangle ids).
  std::vector<uint32_t> seeds_now;
  auto seed = [&] {
    seeds_now = KineticExecutor::TrianglesAround(mesh_, *moved);
    seeds_now.insert(seeds_now.end(), seeds->begin(), seeds->end());
    std::sort(seeds_now.begin(), seeds_now.end());
    seeds_now.erase(std::unique(seeds_now.begin(), seeds_now.end()),
                    seeds_now.end());
  };
  if (seeds != nullptr) seed();
  if (!TryStep(mid, moved, seeds ? &seeds_now : nullptr, depth + 1, cancel,
               report, stuck_vertices, held, nullptr)) {
    return false;
  }
  if (seeds != nullptr) seed();
  return TryStep(to, moved, seeds ? &seeds_now : nullptr, depth + 1, cancel,
                 report, stuck_vertices, held, nullptr);
}

bool Triangulation::InsertBatch(std::vector<uint32_t> pending,
                                const std::vector<uint32_t>& hints,
                                StepReport* report) {
  std::sort(pending.begin(), pending.end());
  std::vector<uint32_t> owner;  // per triangle: inserting vertex this round
  const bool regions = options_.executor == Executor::kRegions;
  // The region executor's apexes across each edge stay kept through the
  // insertions: every triangle they write is refreshed (the splits' here,
  // the flips' in FixSerial and LegalizeSerial).
  const bool keep_across =
      regions && !pending.empty() && region_executor_.BeginHostChange(mesh_);
  while (!pending.empty()) {
    // Locate every pending point (read-only, parallel).
    uint32_t fallback = 0;
    while (fallback < mesh_.num_triangles() && mesh_.view().IsFree(fallback)) {
      ++fallback;
    }
    const auto& ve = mesh_.vertex_edge();
    std::vector<VertexOps::Location> loc(pending.size());
    ParallelFor(
        0, pending.size(),
        [&](size_t i) {
          const uint32_t v = pending[i];
          const uint32_t h = hints[v];
          const uint32_t start = (h < ve.size() && ve[h] != kNoEdge)
                                     ? TriangleOf(ve[h])
                                     : fallback;
          loc[i] = VertexOps::Locate(mesh_, pos_, pos_[v], start);
        },
        16);
    // Coincident points join sites; one new vertex per triangle per round.
    // (Slots taken last round are cleared; the array only grows.)
    if (owner.size() < mesh_.num_triangles()) {
      owner.resize(mesh_.num_triangles(), kNoVertex);
    }
    std::vector<uint32_t> split, deferred;
    bool outside_taken = false;
    for (size_t i = 0; i < pending.size(); ++i) {
      const uint32_t v = pending[i];
      if (loc[i].triangle == kNoEdge) return false;
      if (loc[i].coincident != kNoVertex) {
        const uint32_t w = loc[i].coincident;
        uint32_t tail = v;
        for (uint32_t p = v; p != kNoVertex; p = dup_next_[p]) {
          rep_[p] = w;
          tail = p;
        }
        dup_next_[tail] = dup_next_[w];
        dup_next_[w] = v;
        has_duplicates_ = true;
        continue;
      }
      // Points outside the hull go one per round: two of them split into
      // neighbouring ghost triangles at once can leave a hull that turns
      // left everywhere yet winds twice (caught by HullWindsOnce, but then
      // the whole step is rebuilt).
      if (mesh_.view().IsGhost(loc[i].triangle)) {
        if (outside_taken) {
          deferred.push_back(v);
          continue;
        }
        outside_taken = true;
      }
      uint32_t& o = owner[loc[i].triangle];
      if (o == kNoVertex) {
        o = v;
        split.push_back(static_cast<uint32_t>(i));
      } else {
        deferred.push_back(v);
      }
    }
    for (uint32_t i : split) owner[loc[i].triangle] = kNoVertex;
    if (split.empty()) break;
    std::vector<uint32_t> inserted, touched;
    for (uint32_t i : split) {
      const auto tris = VertexOps::Split(mesh_, loc[i].triangle, pending[i]);
      inserted.push_back(pending[i]);
      touched.insert(touched.end(), tris.begin(), tris.end());
    }
    uint32_t* across =
        keep_across ? region_executor_.HostChangeAcross(mesh_) : nullptr;
    if (across != nullptr) {
      const MeshView mv = std::as_const(mesh_).view();
      for (uint32_t t : touched) RefreshAcross(mv, t, across);
    }
    std::vector<uint32_t> invalid =
        KineticExecutor::FindInvalidTriangles(mesh_, pos_, &inserted);
    const bool fixed =
        regions
            ? RegionExecutor::FixSerial(mesh_, pos_, invalid, &report->flips,
                                        &touched, nullptr, nullptr, across)
            : KineticExecutor::Fix(mesh_, pos_, std::move(invalid), scratch_,
                                   &report->flips, &touched, nullptr, nullptr);
    if (!fixed) {
      MeshChangedOnHost();
      return false;
    }
    std::vector<uint32_t> seeds =
        KineticExecutor::TrianglesAround(mesh_, inserted);
    seeds.insert(seeds.end(), touched.begin(), touched.end());
    std::sort(seeds.begin(), seeds.end());
    seeds.erase(std::unique(seeds.begin(), seeds.end()), seeds.end());
    if (regions) {
      RegionExecutor::LegalizeSerial(mesh_, pos_, seeds, &report->flips,
                                     nullptr, across);
    } else {
      // The splits, fixing's and legalizing's flips: what the round
      // changed (the device's copy takes only that).
      KineticExecutor::Legalize(mesh_, pos_, &seeds, scratch_, &report->flips,
                                &touched);
      MeshChangedOnHostAt(touched, {});
    }
    pending = std::move(deferred);
  }
  if (keep_across) region_executor_.EndHostChange(mesh_);
  return true;
}

bool Triangulation::LocalUpdate(std::vector<Vec2>& next,
                                const std::vector<uint32_t>& moved_points,
                                const CancelToken* cancel, StepReport* report,
                                std::string* reason, int* cancelled) {
  motion_filter_.Invalidate();
  const uint32_t n = size();
  // 1. Coincident points that part from their site are detached and
  //    inserted again at the end.
  std::vector<uint32_t> reinsert = DetachPartingPoints(next);
  // 2. Kinetic step. Vertices of triangles that fixing cannot repair have
  //    their own motion halved (a local sub-step) and finish it in later
  //    sub-steps; after kMaxHalvings they are removed and re-inserted.
  const RoundStepPolicy& policy = options_.round;
  const int kMaxHalvings = policy.max_halvings;
  const uint32_t max_removed = std::max<uint32_t>(
      policy.reinsert_min,
      static_cast<uint32_t>(policy.reinsert_fraction * sites_.size()));
  std::vector<uint32_t> removed;
  std::vector<uint32_t> hints(n, kNoVertex);
  std::vector<uint8_t> level(n, 0);
  // Vertices whose motion stuck a dense pass: when they resume, they first
  // take half of their remaining motion (they would stick again otherwise).
  std::vector<uint8_t> halve_on_resume(n, 0);
  // How often fixing held each vertex back in this step (hold_culprits).
  std::vector<uint8_t> held_in_fix_count(n, 0);
  // Vertices held with their motion halved kMaxHalvings times: they stay at
  // pos_ and are removed for re-insertion once the others are done.
  std::vector<uint8_t> parked(n, 0);
  std::vector<uint32_t> parked_list;
  const auto& ve = mesh_.vertex_edge();
  std::vector<Vec2> goal = next;
  std::vector<uint32_t> active = moved_points;  // candidates still to move
  // The device executor is told what changes in `goal` and pos_ between
  // its attempts (from the second one on), so that a sparse attempt does
  // not compare both arrays whole on the host.
  PositionWrites device_writes;
  PositionWrites* const writes = device_ != nullptr ? &device_writes : nullptr;
  auto set_goal = [&](uint32_t v, const Vec2& g) {
    SetSiteGoal(dup_next_, v, g, goal,
                writes != nullptr ? &writes->to : nullptr);
  };
  // The points not at `next` yet, ascending: a pass over every point the
  // first time, then over the last list (a point that arrived stays: its
  // goal is `next`, which it never leaves in this step), so that a stuck
  // attempt late in the step does not pass over the whole array.
  std::vector<uint32_t> unarrived;
  bool unarrived_known = false;
  auto all_unarrived = [&] {
    if (!unarrived_known) {
      for (uint32_t i = 0; i < n; ++i) {
        if (next[i] != pos_[i]) unarrived.push_back(i);
      }
      unarrived_known = true;
    } else {
      unarrived.erase(
          std::remove_if(unarrived.begin(), unarrived.end(),
                         [&](uint32_t i) { return next[i] == pos_[i]; }),
          unarrived.end());
    }
    return unarrived;
  };
  // Removes vertices (sorted, unique) for re-insertion at the end of the
  // step, within the re-insertion budget; false (with *reason) when it is
  // exceeded or a removal fails.
  auto remove_for_reinsertion = [&](const std::vector<uint32_t>& to_remove) {
    if (removed.size() + to_remove.size() > max_removed ||
        sites_.size() <
            removed.size() + to_remove.size() + policy.min_sites_left) {
      *reason =
          absl::StrCat("fixing stuck; ", removed.size() + to_remove.size(),
                       " vertices to re-insert exceed the local budget");
      return false;
    }
    const auto t_remove = std::chrono::steady_clock::now();
    for (uint32_t v : to_remove) {
      if (ve[v] == kNoEdge) continue;
      hints[v] = std::as_const(mesh_).view().Dest(ve[v]);
      // The star's slots, the triangles around it and its vertices are all
      // that the removal changes.
      MeshChangedOnHostAt(KineticExecutor::TrianglesAround(mesh_, {v}), {v});
      if (!VertexOps::Remove(mesh_, pos_, v, &removal_touched_, nullptr)) {
        *reason = "could not remove a vertex for re-insertion";
        return false;
      }
      removed.push_back(v);
    }
    report->reinsert_seconds += SecondsSince(t_remove);
    return true;
  };
  for (int attempt = 0;; ++attempt) {
    if (cancel != nullptr && cancel->Cancelled()) {
      *cancelled = attempt == 0 && reinsert.empty() ? 1 : 2;
      *reason = "cancelled";
      return false;
    }
    std::vector<uint32_t> moved;
    for (uint32_t i : active) {
      if (rep_[i] == i && ve[i] != kNoEdge && goal[i] != pos_[i]) {
        moved.push_back(i);
      }
    }
    const bool sparse = moved.size() < policy.sparse_fraction * n;
    std::vector<uint32_t> seeds;
    if (sparse) {
      seeds = KineticExecutor::TrianglesAround(mesh_, moved);
      seeds.insert(seeds.end(), removal_touched_.begin(),
                   removal_touched_.end());
    }
    std::vector<uint32_t> stuck, held_in_fix;
    too_tangled_ = false;
    const bool passed =
        TryStep(goal, sparse ? &moved : nullptr, sparse ? &seeds : nullptr, 0,
                cancel, report, &stuck, &held_in_fix, writes);
    report->held_vertices += static_cast<uint32_t>(held_in_fix.size());
    // Vertices fixing held back (hold_culprits), whether or not the attempt
    // passed, take half of their remaining motion when they resume (a
    // vertex held k times: 1 / 2^k of it).
    std::vector<uint32_t> held_exhausted;
    for (uint32_t v : held_in_fix) {
      if (level[v] >= kMaxHalvings) {
        held_exhausted.push_back(v);
      } else {
        halve_on_resume[v] = 1;
        if (held_in_fix_count[v] < 255) ++held_in_fix_count[v];
      }
    }
    if (cancel != nullptr && cancel->Cancelled()) {
      // A device attempt stopped by the token leaves the host mesh as it
      // was; on the first attempt nothing has changed at all.
      *cancelled = device_ != nullptr && !passed && attempt == 0 &&
                           reinsert.empty() && report->substeps == 0
                       ? 1
                       : 2;
      *reason = "cancelled";
      return false;
    }
    if (too_tangled_) {
      *reason =
          !device_failure_.empty()
              ? absl::StrCat("device executor failed: ", device_failure_)
              : absl::StrCat("over ", options_.round.rebuild_fraction * 100,
                             "% of the triangles inverted: rebuilding "
                             "is cheaper");
      device_failure_.clear();
      return false;
    }
    if (attempt >= options_.round.max_passes) {
      *reason = absl::StrCat("still stuck after ", attempt,
                             " passes: rebuilding is cheaper");
      return false;
    }
    // (A pass legalized the holes of earlier removals.)
    if (passed) removal_touched_.clear();
    // A vertex fixing held back after its motion was halved too often
    // stays at pos_ (the mesh is valid for it there) until the other
    // vertices are done, and is then removed and re-inserted: the host
    // changes the mesh once per step for all of them, not after every
    // attempt (on the device each host change costs an upload of the whole
    // mesh).
    for (uint32_t v : held_exhausted) {
      if (!parked[v]) {
        parked[v] = 1;
        parked_list.push_back(v);
        set_goal(v, pos_[v]);
      }
    }
    if (passed) {
      // Held-back vertices now finish their motion.
      std::vector<uint32_t> held;
      for (uint32_t v : active) {
        if (rep_[v] == v && ve[v] != kNoEdge && goal[v] != next[v] &&
            !parked[v]) {
          held.push_back(v);
        }
      }
      // (A passed attempt legalized every earlier hole: see above.)
      if (held.empty()) {
        std::vector<uint32_t> to_remove;
        for (uint32_t v : parked_list) {
          if (ve[v] != kNoEdge) to_remove.push_back(v);
        }
        parked_list.clear();
        if (to_remove.empty()) break;
        std::sort(to_remove.begin(), to_remove.end());
        if (!remove_for_reinsertion(to_remove)) return false;
        // Their holes are legalized here, on the host, which changed the
        // mesh anyway (for the device executor, an attempt would upload
        // the whole mesh for a few hundred triangles).
        std::vector<uint32_t> holes = std::move(removal_touched_);
        removal_touched_.clear();
        std::sort(holes.begin(), holes.end());
        holes.erase(std::unique(holes.begin(), holes.end()), holes.end());
        const auto t_legalize = std::chrono::steady_clock::now();
        std::vector<uint32_t> flipped;
        KineticExecutor::Legalize(mesh_, pos_, &holes, scratch_, &report->flips,
                                  &flipped);
        MeshChangedOnHostAt(flipped, {});
        report->legalize_seconds += SecondsSince(t_legalize);
        break;
      }
      for (uint32_t v : held) {
        if (halve_on_resume[v] && level[v] < kMaxHalvings) {
          halve_on_resume[v] = 0;
          // Half of the remaining motion; a vertex fixing held back k times
          // takes 1 / 2^k of it (it was held at each larger part).
          // (Halving stops at the last point strictly between the ends.)
          std::optional<Vec2> h;
          for (int k = 0; k < std::max(1, int{held_in_fix_count[v]}); ++k) {
            const std::optional<Vec2> m =
                HalfwayGoal(pos_[v], h.value_or(next[v]));
            if (!m) break;
            h = m;
          }
          if (h) {
            set_goal(v, *h);
            ++level[v];
            continue;
          }
        }
        set_goal(v, next[v]);
      }
      active = std::move(held);
      continue;
    }
    // A pass got stuck: hold the stuck vertices and their neighbours at their
    // old positions so that the next pass succeeds for everyone else; they
    // then finish their motion in later (sparse) passes, the stuck ones
    // taking half of it first. A stuck vertex whose motion was halved too
    // often is removed and re-inserted instead (below).
    bool exhausted = false;
    for (uint32_t v : stuck) {
      if (v != kNoVertex && ve[v] != kNoEdge && goal[v] != pos_[v] &&
          level[v] >= kMaxHalvings) {
        exhausted = true;
      }
    }
    if (!exhausted) {
      const MeshView mv = std::as_const(mesh_).view();
      bool held_any = false;
      for (uint32_t v : stuck) {
        if (v == kNoVertex || ve[v] == kNoEdge) continue;
        halve_on_resume[v] = 1;
        uint32_t e = ve[v];
        const uint32_t e0 = e;
        std::vector<uint32_t> region = {v};
        do {
          region.push_back(mv.Dest(e));
          e = mv.twin[Prev(e)];
        } while (e != e0);
        for (uint32_t w : region) {
          if (w == kInfiniteVertex || goal[w] == pos_[w]) continue;
          set_goal(w, pos_[w]);
          held_any = true;
        }
      }
      if (held_any) {
        ++report->local_halvings;
        active = all_unarrived();
        continue;
      }
    }
    // Per stuck triangle: halve the motion of its still-moving vertices; if
    // none can be halved any more, remove its moving vertices (or all).
    bool progress = false;
    std::vector<uint32_t> to_remove;
    std::vector<uint8_t> halved(n, 0);
    auto moving = [&](uint32_t v) { return goal[v] != pos_[v]; };
    for (size_t k = 0; k + 2 < stuck.size(); k += 3) {
      bool any_halved = false;
      for (size_t j = k; j < k + 3; ++j) {
        const uint32_t v = stuck[j];
        if (v == kNoVertex || ve[v] == kNoEdge || !moving(v)) continue;
        if (halved[v]) {
          any_halved = true;
          continue;
        }
        if (level[v] >= kMaxHalvings) continue;
        const auto h = HalfwayGoal(pos_[v], goal[v]);
        if (!h) continue;
        set_goal(v, *h);
        ++level[v];
        halved[v] = 1;
        any_halved = progress = true;
      }
      if (any_halved) continue;
      bool any_moving = false;
      for (size_t j = k; j < k + 3; ++j) {
        const uint32_t v = stuck[j];
        if (v != kNoVertex && ve[v] != kNoEdge && moving(v)) {
          to_remove.push_back(v);
          any_moving = true;
        }
      }
      if (!any_moving) {
        for (size_t j = k; j < k + 3; ++j) {
          if (stuck[j] != kNoVertex) to_remove.push_back(stuck[j]);
        }
      }
    }
    std::sort(to_remove.begin(), to_remove.end());
    to_remove.erase(std::unique(to_remove.begin(), to_remove.end()),
                    to_remove.end());
    ++report->local_halvings;
    const size_t removed_before = removed.size();
    if (!remove_for_reinsertion(to_remove)) return false;
    progress |= removed.size() > removed_before;
    if (!progress) {
      *reason = "fixing stuck and no vertex left to hold back or remove";
      return false;
    }
    // The next attempt moves every vertex whose goal is not reached yet.
    active = all_unarrived();
  }
  removal_touched_.clear();
  // 3. Insert removed vertices and detached points at their new positions.
  reinsert.insert(reinsert.end(), removed.begin(), removed.end());
  return FinishLocalStep(next, std::move(reinsert), hints, report, reason);
}

std::vector<uint32_t> Triangulation::DetachPartingPoints(
    const std::vector<Vec2>& next) {
  const uint32_t n = size();
  std::vector<uint32_t> reinsert;
  detach_log_.clear();
  auto set = [&](uint32_t& slot, uint32_t value) {
    detach_log_.emplace_back(&slot, slot);
    slot = value;
  };
  if (has_duplicates_) {
    std::vector<uint8_t> leave(n, 0);
    bool any = false;
    for (uint32_t i = 0; i < n; ++i) {
      if (rep_[i] != i && next[i] != next[rep_[i]]) leave[i] = any = 1;
    }
    if (any) {
      for (uint32_t r : sites_) {
        uint32_t last = r;
        for (uint32_t p = dup_next_[r]; p != kNoVertex;) {
          const uint32_t following = dup_next_[p];
          if (leave[p]) {
            set(dup_next_[p], kNoVertex);
            set(rep_[p], p);
            reinsert.push_back(p);
          } else {
            set(dup_next_[last], p);
            last = p;
          }
          p = following;
        }
        set(dup_next_[last], kNoVertex);
      }
      // Detached points that land together re-form a site on insertion.
    }
  }
  return reinsert;
}

void Triangulation::UndoDetach() {
  for (auto it = detach_log_.rbegin(); it != detach_log_.rend(); ++it) {
    *it->first = it->second;
  }
  detach_log_.clear();
}

bool Triangulation::FinishLocalStep(std::vector<Vec2>& next,
                                    std::vector<uint32_t> reinsert,
                                    std::vector<uint32_t>& hints,
                                    StepReport* report, std::string* reason) {
  const uint32_t n = size();
  pos_.swap(next);
  std::sort(reinsert.begin(), reinsert.end());
  for (uint32_t v : reinsert) {
    if (hints[v] < n && rep_[hints[v]] != hints[v]) hints[v] = kNoVertex;
  }
  const auto t_insert = std::chrono::steady_clock::now();
  if (!InsertBatch(reinsert, hints, report)) {
    pos_.swap(next);
    *reason = "re-insertion failed";
    return false;
  }
  report->reinsert_seconds += SecondsSince(t_insert);
  report->reinserted = static_cast<uint32_t>(reinsert.size());
  for (uint32_t v : reinsert) hints[v] = kNoVertex;
  if (mesh_.has_free_triangles()) {
    mesh_.Compact();
    MeshChangedOnHost();
  }
  // Sites change only when points part from or join a site, and both go
  // through re-insertion: without coincident points before the step and
  // none made by it (InsertBatch sets has_duplicates_ when a point joins a
  // site), sites_ (every point) stays as it is.
  if (has_duplicates_) RefreshSites();
  return true;
}

bool Triangulation::RegionUpdate(std::vector<Vec2>& next,
                                 const std::vector<uint32_t>& moved_points,
                                 const CancelToken* cancel, StepReport* report,
                                 std::string* reason, int* cancelled,
                                 bool* untouched) {
  const uint32_t n = size();
  std::vector<uint32_t> reinsert = DetachPartingPoints(next);
  const auto& ve = mesh_.vertex_edge();
  // The moved sites in the mesh (hidden coincident points move with their
  // site's representative); in parallel, one pass. Without coincident
  // points every point is a site and a vertex of the (planar) mesh: they
  // are the moved points.
  auto moves = [&](uint32_t i) {
    return rep_[i] == i && ve[i] != kNoEdge && next[i] != pos_[i];
  };
  std::vector<uint32_t> moved_sites;
  if (has_duplicates_) {
    moved_sites = FilterIndices(
        moved_points.size(), [&](size_t k) { return moves(moved_points[k]); });
    for (uint32_t& k : moved_sites) k = moved_points[k];
  }
  const std::vector<uint32_t>& moved =
      has_duplicates_ ? moved_sites : moved_points;
  // Vertex tolerances: look only around the moved vertices that leave
  // theirs, while few do.
  const RegionStepPolicy& policy = options_.region;
  const auto t_filter = std::chrono::steady_clock::now();
  std::vector<uint32_t> loud;
  bool filtered = false;
  if (policy.filter_motion && !moved.empty()) {
    auto back_off = [&] {
      motion_filter_.Invalidate();
      filter_backoff_ = std::clamp(2 * filter_backoff_, policy.filter_backoff,
                                   std::max(policy.filter_backoff, 256));
      filter_wait_ = filter_backoff_;
    };
    if (!motion_filter_.valid()) {
      if (filter_wait_ > 0) {
        --filter_wait_;
      } else if (MotionFilter::EstimateLoudFraction(mesh_, pos_, next, moved,
                                                    policy.filter_samples) <=
                 policy.filter_estimate) {
        motion_filter_.Certify(mesh_, pos_);
      } else {
        back_off();
      }
    }
    if (motion_filter_.valid()) {
      loud = motion_filter_.Loud(moved, next);
      if (loud.size() <= policy.filter_fraction * n) {
        filtered = true;
        report->quiet_points =
            static_cast<uint32_t>(moved.size() - loud.size());
      } else {
        back_off();
      }
    }
  }
  report->filter_seconds += SecondsSince(t_filter);
  std::vector<uint32_t> removed;
  // Walk starts of the vertices to re-insert: all kNoVertex between steps
  // (FinishLocalStep resets what it used; a failed step drops them all),
  // so no step fills 4 bytes per point.
  std::vector<uint32_t>& hints = reinsert_hints_;
  if (hints.size() != n) hints.assign(n, kNoVertex);
  RegionStepStats stats;
  const std::vector<uint32_t>& seeds = filtered ? loud : moved;
  const bool ok = seeds.empty() || region_executor_.Step(
                                       mesh_, pos_, next, seeds, policy, &stats,
                                       &removed, &hints, reason, cancel);
  // A stopped or failed executor step has left the mesh as it was; the
  // coincident-point chains go back too, so the step changed nothing.
  if (!ok && !reinsert.empty()) UndoDetach();
  if (stats.cancelled) *cancelled = 1;
  report->flips += stats.flips;
  report->held_vertices = stats.held;
  report->local_halvings = stats.halvings;
  report->failed_attempts = stats.fix_attempts > 0 ? stats.fix_attempts - 1 : 0;
  report->deferred = stats.deferred;
  report->substeps = stats.held > 0 ? 2 : 1;
  report->scan_seconds += stats.scan_seconds;
  report->across_kept = stats.across_kept;
  report->fix_seconds += stats.fix_seconds;
  report->legalize_seconds += stats.legalize_seconds;
  report->held_seconds += stats.held_seconds;
  if (!ok) {
    if (untouched != nullptr) *untouched = true;
    hints.clear();
    return false;
  }
  reinsert.insert(reinsert.end(), removed.begin(), removed.end());
  // The tolerances stay valid when every moved vertex was quiet (nothing
  // changed) and, recertified, after a step that only flipped: re-inserted
  // and held vertices change the mesh in ways the executor does not list
  // (and a failed re-insertion ends in a rebuild, which invalidates them).
  const bool recertify =
      filtered && !seeds.empty() && reinsert.empty() && stats.held == 0;
  if (!filtered || (!seeds.empty() && !recertify)) {
    motion_filter_.Invalidate();
  }
  if (!FinishLocalStep(next, std::move(reinsert), hints, report, reason)) {
    hints.clear();
    return false;
  }
  if (recertify) {
    const auto t_recertify = std::chrono::steady_clock::now();
    motion_filter_.Recertify(mesh_, pos_, loud,
                             region_executor_.changed_triangles());
    report->filter_seconds += SecondsSince(t_recertify);
    filter_backoff_ = 0;
  }
  return true;
}

std::vector<Vec2> Triangulation::JoinedPositions(
    const std::vector<uint32_t>& leaving, const std::vector<Vec2>& joining,
    const std::vector<Vec2>& by_int) const {
  const uint32_t n = size();
  std::vector<uint8_t> gone(n, 0);
  for (uint32_t ext : leaving) gone[ext] = 1;
  std::vector<Vec2> out;
  out.reserve(n - leaving.size() + joining.size());
  for (uint32_t ext = 0; ext < n; ++ext) {
    if (!gone[ext]) out.push_back(by_int[int_of_ext_[ext]]);
  }
  out.insert(out.end(), joining.begin(), joining.end());
  return out;
}

bool Triangulation::JoinsByRebuild(uint64_t leaving, uint64_t joining,
                                   std::string* reason) const {
  if (mesh_.empty()) {
    *reason = "fewer than two dimensions (line mode)";
    return true;
  }
  // Removal and insertion cost about 6 us per point here, a CGAL build
  // about 1 us per point: past an eighth of the points a rebuild is cheaper.
  const uint64_t changes = leaving + joining;
  if (changes > kLocalChangesMin && 8 * changes > uint64_t{size()} + joining) {
    *reason = absl::StrCat(leaving, " points leave and ", joining,
                           " join (over 1/8 of the points): rebuilding is "
                           "cheaper");
    return true;
  }
  return false;
}

bool Triangulation::JoinAndLeave(const std::vector<uint32_t>& leaving,
                                 const std::vector<Vec2>& joining,
                                 StepReport* report, std::string* reason) {
  motion_filter_.Invalidate();
  if (mesh_.empty()) {  // the moves of this step left a line
    *reason = "fewer than two dimensions (line mode)";
    return false;
  }
  const uint32_t n = size();
  const uint32_t m = static_cast<uint32_t>(joining.size());
  MeshChangedOnHost();
  // 1. Leave. A hidden coincident point leaves its chain; a site's
  //    representative hands the mesh vertex to the next point of its site;
  //    a point alone at its position is removed from the mesh (its star
  //    re-triangulated, then legalized).
  const auto t_remove = std::chrono::steady_clock::now();
  std::vector<uint8_t> gone(n, 0);
  uint32_t live_sites = num_sites();
  std::vector<uint32_t> touched;
  for (uint32_t ext : leaving) {
    const uint32_t p = int_of_ext_[ext];
    gone[p] = 1;
    const uint32_t r = rep_[p];
    if (r != p) {
      uint32_t q = r;
      while (dup_next_[q] != p) q = dup_next_[q];
      dup_next_[q] = dup_next_[p];
    } else if (dup_next_[p] != kNoVertex) {
      const uint32_t q = dup_next_[p];
      for (uint32_t x = q; x != kNoVertex; x = dup_next_[x]) rep_[x] = q;
      mesh_.RelabelVertex(p, q);
    } else {
      if (mesh_.vertex_edge()[p] == kNoEdge || live_sites <= 3) {
        *reason = "fewer than three distinct positions would remain";
        return false;
      }
      touched.clear();
      if (!VertexOps::Remove(mesh_, pos_, p, &touched, nullptr)) {
        *reason = "the remaining points are collinear";
        return false;
      }
      RegionExecutor::LegalizeSerial(mesh_, pos_, touched, &report->flips);
      --live_sites;
    }
    dup_next_[p] = kNoVertex;
    rep_[p] = p;
  }
  report->reinsert_seconds += SecondsSince(t_remove);
  // Start sites for locating the joining points: every k-th site still in
  // the mesh, about 16 per joining point (a walk from the hint then takes a
  // few steps, and the grid costs O(m), not O(n)).
  std::optional<HintGrid> grid;
  if (m > 64) {
    const size_t stride = std::max<size_t>(1, sites_.size() / (16 * size_t{m}));
    std::vector<uint32_t> sample;
    const auto& ve = mesh_.vertex_edge();
    for (size_t i = 0; i < sites_.size(); i += stride) {
      if (ve[sites_[i]] != kNoEdge) sample.push_back(sites_[i]);
    }
    TriangulationView v = view();
    v.sites = sample.data();
    v.num_sites = static_cast<uint32_t>(sample.size());
    if (!sample.empty()) grid.emplace(v);
  }
  // 2. Join: new internal ids n.., inserted as re-inserted vertices are
  //    (located from a nearby site, split, fixed, legalized).
  if (m > 0) {
    pos_.insert(pos_.end(), joining.begin(), joining.end());
    for (uint32_t j = 0; j < m; ++j) {
      rep_.push_back(n + j);
      dup_next_.push_back(kNoVertex);
      ext_of_int_.push_back(kNoVertex);
    }
    mesh_.ResizeVertices(n + m);
    std::vector<uint32_t> hints(n + m, kNoVertex);
    if (grid) {
      const HintGridView g = grid->view();
      for (uint32_t j = 0; j < m; ++j) hints[n + j] = g.Hint(joining[j]);
    }
    std::vector<uint32_t> pending(m);
    std::iota(pending.begin(), pending.end(), n);
    const auto t_insert = std::chrono::steady_clock::now();
    const bool inserted = InsertBatch(std::move(pending), hints, report);
    report->reinsert_seconds += SecondsSince(t_insert);
    if (!inserted) {
      // Back to n points (pos_ of the old points is unchanged).
      pos_.resize(n);
      rep_.resize(n);
      dup_next_.resize(n);
      ext_of_int_.resize(n);
      *reason = "inserting the joining points failed";
      return false;
    }
  }
  if (mesh_.has_free_triangles()) mesh_.Compact();
  // 3. Renumber. Internally the last points fill the holes the leaving ones
  //    left (their mesh vertices relabelled; the periodic renumbering
  //    restores the spatial order); externally the remaining points keep
  //    their order and close the gaps, the joining ones follow.
  const uint32_t total = n + m;
  const uint32_t n_new = total - static_cast<uint32_t>(leaving.size());
  std::vector<uint32_t> holes;
  for (uint32_t ext : leaving) holes.push_back(int_of_ext_[ext]);
  std::sort(holes.begin(), holes.end());
  std::vector<uint32_t> sorted_leaving = leaving;
  std::sort(sorted_leaving.begin(), sorted_leaving.end());
  // External ids: old id minus the leaving ids below it; joining points
  // n - r + j.
  ParallelFor(0, total, [&](size_t i) {
    if (i < n && gone[i]) return;
    const uint32_t e = ext_of_int_[i];
    ext_of_int_[i] = i >= n
                         ? n_new - m + static_cast<uint32_t>(i - n)
                         : e - static_cast<uint32_t>(
                                   std::lower_bound(sorted_leaving.begin(),
                                                    sorted_leaving.end(), e) -
                                   sorted_leaving.begin());
  });
  // Fill holes below n_new with the last live points.
  uint32_t last = total;
  auto live = [&](uint32_t i) { return i >= n || !gone[i]; };
  for (uint32_t h : holes) {
    if (h >= n_new) break;
    do {
      --last;
    } while (!live(last));
    if (last < h) break;
    const uint32_t src = last;
    pos_[h] = pos_[src];
    ext_of_int_[h] = ext_of_int_[src];
    dup_next_[h] = dup_next_[src];
    if (rep_[src] == src) {
      for (uint32_t x = h; x != kNoVertex; x = dup_next_[x]) rep_[x] = h;
      mesh_.RelabelVertex(src, h);
    } else {
      rep_[h] = rep_[src];
      uint32_t q = rep_[src];
      while (dup_next_[q] != src) q = dup_next_[q];
      dup_next_[q] = h;
    }
  }
  pos_.resize(n_new);
  ext_of_int_.resize(n_new);
  rep_.resize(n_new);
  dup_next_.resize(n_new);
  int_of_ext_.resize(n_new);
  ParallelFor(0, n_new, [&](size_t i) {
    int_of_ext_[ext_of_int_[i]] = static_cast<uint32_t>(i);
  });
  mesh_.ResizeVertices(n_new);
  // (Triangle slots are not re-sorted here: the periodic renumbering
  // restores their spatial order.)
  RefreshSites();
  report->removed_points = static_cast<uint32_t>(leaving.size());
  report->added_points = m;
  return true;
}

absl::StatusOr<StepReport> Triangulation::ApplyDisplacements(
    const DisplacementBatch& batch, const CancelToken* cancel) {
  const auto start = std::chrono::steady_clock::now();
  const uint32_t n = size();
  const bool dense = batch.ids.empty();
  const char* field =
      batch.mode == DisplacementBatch::Mode::kDelta ? "deltas" : "positions";
  const bool changes = !batch.remove.empty() || !batch.add.empty();
  // A batch with only points that leave or join moves nothing.
  const bool no_moves = dense && changes && batch.values.empty();
  if (dense && !no_moves && batch.values.size() != n) {
    return absl::InvalidArgumentError(
        absl::StrCat(field, ": expected ", n, " values (one per point), got ",
                     batch.values.size()));
  }
  if (!dense && batch.values.size() != batch.ids.size()) {
    return absl::InvalidArgumentError(
        absl::StrCat(field, ": ", batch.values.size(), " values for ",
                     batch.ids.size(), " ids"));
  }
  // Validate everything before touching state.
  std::vector<uint8_t> leaves;
  if (changes) {
    const uint64_t after =
        uint64_t{n} - batch.remove.size() + uint64_t{batch.add.size()};
    if (batch.remove.size() > n || after >= (uint64_t{1} << 29)) {
      return absl::ResourceExhaustedError(absl::StrCat(
          "add: ", after, " points after this step exceed the limit of 2^29"));
    }
    leaves.assign(n, 0);
    if (absl::Status s = MarkDistinctIds(batch.remove, "remove", leaves);
        !s.ok()) {
      return s;
    }
    for (size_t i = 0; i < batch.add.size(); ++i) {
      absl::Status s = CheckPosition(batch.add[i], "add", i);
      if (!s.ok()) return s;
    }
  }
  std::vector<Vec2>& next = next_;
  next.resize(n);
  const bool delta = batch.mode == DisplacementBatch::Mode::kDelta;
  auto new_position = [&](size_t i, uint32_t in) {
    const Vec2& v = batch.values[i];
    return delta ? Vec2{pos_[in].x + v.x, pos_[in].y + v.y} : v;
  };
  auto check = [&](size_t i, uint32_t ext, const Vec2& p) -> absl::Status {
    const Vec2& v = batch.values[i];
    if (std::isnan(v.x) || std::isnan(v.y) || std::isinf(v.x) ||
        std::isinf(v.y)) {
      return CheckPosition(v, field, i);
    }
    return CheckPosition(p, "new position of point", ext);
  };
  if (no_moves) {
    // nothing moves
  } else if (dense) {
    // Parallel, in internal order; the first bad entry (by index) is
    // reported, as a sequential scan would.
    std::atomic<uint64_t> first_bad{UINT64_MAX};
    moved_flag_.resize(n);
    // A non-finite value makes a non-finite position, which the domain
    // check rejects.
    Run([&] {
      ParallelFor(0, n, [&](size_t in) {
        // The batch is in id order, the loop in spatial order: prefetch
        // the scattered reads well ahead (latency-bound otherwise).
        if (in + 32 < n)
          __builtin_prefetch(&batch.values[ext_of_int_[in + 32]]);
        const uint32_t ext = ext_of_int_[in];
        const Vec2 p = new_position(ext, static_cast<uint32_t>(in));
        next[in] = p;
        moved_flag_[in] = p != pos_[in] ? 1 : 0;
        if (!(InExactDomain(p.x) && InExactDomain(p.y))) {
          uint64_t cur = first_bad.load();
          while (ext < cur && !first_bad.compare_exchange_weak(cur, ext)) {
          }
        }
      });
    });
    if (first_bad.load() != UINT64_MAX) {
      const uint32_t ext = static_cast<uint32_t>(first_bad.load());
      return check(ext, ext, next[int_of_ext_[ext]]);
    }
  } else {
    next = pos_;
    std::vector<uint8_t> seen(n, 0);
    if (absl::Status s = MarkDistinctIds(batch.ids, "ids", seen); !s.ok()) {
      return s;
    }
    for (size_t i = 0; i < batch.ids.size(); ++i) {
      const uint32_t ext = batch.ids[i];
      if (!leaves.empty() && leaves[ext]) {
        return absl::InvalidArgumentError(
            absl::StrCat("ids[", i, "] = ", ext,
                         " leaves with this step (it is in remove)"));
      }
      const uint32_t in = int_of_ext_[ext];
      const Vec2 p = new_position(i, in);
      absl::Status st = check(i, ext, p);
      if (!st.ok()) return st;
      next[in] = p;
    }
  }

  // Points that leave stay where they are until they leave.
  if (dense && !no_moves && !leaves.empty()) {
    for (uint32_t ext : batch.remove) {
      const uint32_t in = int_of_ext_[ext];
      next[in] = pos_[in];
      moved_flag_[in] = 0;
    }
  }

  StepReport report;
  std::vector<uint32_t> moved;
  if (!no_moves) {
    // Dense batches flagged their moved points as they computed them (a
    // byte per point to read, not two positions).
    Run([&] {
      moved = dense ? FilterIndices(n, [&](size_t i) { return moved_flag_[i]; })
                    : FilterIndices(
                          n, [&](size_t i) { return next[i] != pos_[i]; });
    });
  }
  report.moved_points = static_cast<uint32_t>(moved.size());
  if (cancel != nullptr) {
    if (absl::Status s = cancel->Check("step"); !s.ok()) return s;
  }
  if (moved.empty() && !changes) {
    ++steps_;
    report.num_sites = num_sites();
    report.num_points = size();
    return report;
  }
  {
    std::lock_guard<std::mutex> lock(adjacency_->mu);
    AdjacencyCache& cache = *adjacency_;
    cache.valid = false;
    for (AdjacencyCache::CellsSlot& slot : cache.cells) {
      slot = AdjacencyCache::CellsSlot{};
    }
    // The hint grid this step may pass on (see AdjacencyCache::carried).
    cache.carried.reset();
    if (num_sites() == size() && !changes) {
      cache.carried = cache.hints != nullptr ? cache.hints : cache.stale_hints;
      cache.carried_step =
          cache.hints != nullptr ? cache.hints_step : cache.stale_step;
    }
    cache.hints.reset();
    cache.stale_hints.reset();
  }

  // Many points leave or join (or the points lie on a line): the step is
  // one rebuild of its final positions, built aside, so that a stopped one
  // leaves the previous step as it was.
  std::string join_reason;
  if (changes &&
      JoinsByRebuild(batch.remove.size(), batch.add.size(), &join_reason)) {
    bool built = false;
    Run([&] {
      built = Rebuild(
          JoinedPositions(batch.remove, batch.add, no_moves ? pos_ : next),
          cancel);
    });
    if (!built) return cancel->Check("step");  // fired, so not OK
    ++steps_;
    report.path = UpdatePath::kRebuilt;
    report.fallback_reason = join_reason;
    report.renumbered = true;
    report.removed_points = static_cast<uint32_t>(batch.remove.size());
    report.added_points = static_cast<uint32_t>(batch.add.size());
    report.num_sites = num_sites();
    report.num_points = size();
    report.seconds = SecondsSince(start);
    return report;
  }
  // Back to the previous step after an attempt that changed the mesh was
  // stopped: the mesh and the coincident-point chains are rebuilt from the
  // positions before the step (not stoppable: it is what a stop must
  // leave). The region executor undoes its own changes (and the
  // coincident-point chains are put back), so this happens only after the
  // round and device executors' later passes. Those move pos_ as their
  // sub-steps pass, so their positions before the step are kept aside
  // (regression: a device step stopped after its first sub-step used to
  // come back CANCELLED with part of its motion applied).
  std::vector<Vec2> pos_before;
  if (options_.executor != Executor::kRegions && !moved.empty()) {
    pos_before = pos_;
  }
  auto restore_previous = [&] {
    if (!pos_before.empty()) {
      pos_ = std::move(pos_before);
      pos_before.clear();
    }
    std::vector<Vec2> by_ext(n);
    for (uint32_t i = 0; i < n; ++i) by_ext[ext_of_int_[i]] = pos_[i];
    Rebuild(by_ext);
  };
  int cancelled = 0;
  if (moved.empty()) ++steps_;
  if (!moved.empty())
    Run([&] {
      std::string reason;
      bool ok = false;
      // On failure: the attempt changed nothing, so the rebuild that
      // follows can stop on `cancel` and leave the previous step.
      bool untouched = false;
      if (mesh_.empty()) {
        reason = "fewer than two dimensions (line mode)";
        untouched = true;
      } else {
        ok = options_.executor == Executor::kRegions
                 ? RegionUpdate(next, moved, cancel, &report, &reason,
                                &cancelled, &untouched)
                 : LocalUpdate(next, moved, cancel, &report, &reason,
                               &cancelled);
      }
      if (cancelled == 2) restore_previous();
      if (cancelled) return;
      ++steps_;
      if (ok) {
        report.path = report.reinserted > 0 ? UpdatePath::kReinserted
                      : report.substeps > 1 ? UpdatePath::kSubdivided
                                            : UpdatePath::kLocal;
        if (options_.renumber_check_interval > 0 &&
            steps_ % options_.renumber_check_interval == 0) {
          KeepLocality(&report);
        }
      } else {
        std::vector<Vec2> by_ext(n);
        for (uint32_t i = 0; i < n; ++i) by_ext[ext_of_int_[i]] = next[i];
        if (!Rebuild(by_ext, cancel)) {
          // Stopped: the previous step stays (restored if the attempt had
          // changed the mesh).
          if (!untouched) restore_previous();
          --steps_;
          cancelled = 1;
          return;
        }
        report.path = UpdatePath::kRebuilt;
        report.fallback_reason = reason;
        report.renumbered = true;
      }
    });
  if (cancelled) return cancel->Check("step");  // fired, so not OK
  if (changes) {
    // Once the moves are done, the points that leave and join follow (not
    // cancelled: local work bounded by the batch).
    Run([&] {
      std::string reason;
      if (JoinAndLeave(batch.remove, batch.add, &report, &reason)) {
        if (report.path == UpdatePath::kNoop) report.path = UpdatePath::kLocal;
        if (options_.renumber_check_interval > 0 &&
            steps_ % options_.renumber_check_interval == 0 &&
            !report.renumbered) {
          KeepLocality(&report);
        }
      } else {
        // Degenerate leftovers only (fewer than three positions, or a
        // line): a rebuild of few or collinear points.
        Rebuild(JoinedPositions(batch.remove, batch.add, pos_));
        report.path = UpdatePath::kRebuilt;
        report.fallback_reason =
            report.fallback_reason.empty()
                ? reason
                : absl::StrCat(report.fallback_reason, "; ", reason);
        report.renumbered = true;
        report.removed_points = static_cast<uint32_t>(batch.remove.size());
        report.added_points = static_cast<uint32_t>(batch.add.size());
      }
    });
  }
  report.num_sites = num_sites();
  report.num_points = size();
  {
    std::lock_guard<std::mutex> lock(adjacency_->mu);
    AdjacencyCache& cache = *adjacency_;
    if (cache.carried != nullptr && !changes && num_sites() == size()) {
      cache.stale_hints = std::move(cache.carried);
      cache.stale_step = cache.carried_step;
    }
    cache.carried.reset();
  }
  report.seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start)
          .count();
  return report;
}

uint32_t Triangulation::SiteId(uint32_t v) const {
  uint32_t best = ext_of_int_[v];
  for (uint32_t p = dup_next_[v]; p != kNoVertex; p = dup_next_[p]) {
    best = std::min(best, ext_of_int_[p]);
  }
  return best;
}

std::vector<std::array<uint32_t, 3>> Triangulation::Triangles() const {
  std::vector<std::array<uint32_t, 3>> out;
  uint32_t slot = 0;
  AppendTriangles(&slot, SIZE_MAX, &out);
  return out;
}

void Triangulation::AppendTriangles(
    uint32_t* slot, size_t max,
    std::vector<std::array<uint32_t, 3>>* out) const {
  if (mesh_.empty()) return;
  const MeshView m = mesh_.view();
  const uint32_t nt = mesh_.num_triangles();
  size_t added = 0;
  uint32_t t = *slot;
  for (; t < nt && added < max; ++t) {
    if (m.IsFree(t) || m.IsGhost(t)) continue;
    out->push_back({SiteId(m.origin[3 * t]), SiteId(m.origin[3 * t + 1]),
                    SiteId(m.origin[3 * t + 2])});
    ++added;
  }
  *slot = t;
}

uint64_t Triangulation::CountTriangles(uint32_t lo, uint32_t hi) const {
  if (mesh_.empty()) return 0;
  const MeshView m = mesh_.view();
  hi = std::min(hi, mesh_.num_triangles());
  uint64_t count = 0;
  for (uint32_t t = lo; t < hi; ++t) {
    count += !m.IsFree(t) && !m.IsGhost(t);
  }
  return count;
}

std::vector<std::pair<uint32_t, uint32_t>> Triangulation::Edges() const {
  std::vector<std::pair<uint32_t, uint32_t>> out;
  auto add = [&](uint32_t a, uint32_t b) {
    uint32_t x = SiteId(a), y = SiteId(b);
    if (x > y) std::swap(x, y);
    out.emplace_back(x, y);
  };
  if (mesh_.empty()) {
    for (size_t r = 1; r < line_.size(); ++r) add(line_[r - 1], line_[r]);
  } else {
    const MeshView m = mesh_.view();
    for (uint32_t e = 0; e < mesh_.num_half_edges(); ++e) {
      const uint32_t a = m.origin[e], b = m.Dest(e);
      if (a == kInfiniteVertex || b == kInfiniteVertex || e > m.twin[e]) {
        continue;
      }
      add(a, b);
    }
  }
  std::sort(out.begin(), out.end());
  return out;
}

}  // namespace kinetri::core
