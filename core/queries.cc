// Batched proximity queries on the Delaunay graph, results in CSR form.
#include "core/queries.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <memory>
#include <mutex>
#include <optional>
#include <queue>

#if defined(__SSE2__)
#include <emmintrin.h>
#endif

#include "absl/container/flat_hash_set.h"
#include "absl/strings/str_cat.h"
#include "core/cell_index.h"
#include "core/hint_grid.h"
#include "core/nearest_by_triangles.h"
#include "core/parallel.h"
#include "core/predicates.h"
#include "core/query_walks.h"

namespace kinetri::core {
namespace {

struct Hit {
  // Left uninitialized by resize(): rows are written in place.
  Hit() {}
  Hit(uint32_t e, double d) : ext(e), dist(d) {}
  uint32_t ext;
  double dist;
};

struct Query {
  Vec2 q;
  uint32_t self_ext = kNoVertex;    // point to exclude
  uint32_t start_site = kNoVertex;  // walk start (kNoVertex: use a hint)
};

double Distance(const Vec2& a, const Vec2& b) {
  const double dx = a.x - b.x, dy = a.y - b.y;
  return std::sqrt(dx * dx + dy * dy);
}

// Per-thread visited marks for graph searches: Begin() starts a new search
// in O(1) (an epoch counter) and returns a handle held in registers;
// Visit() marks a site and says if it was new.
class VisitMarks {
 public:
  struct Search {
    uint32_t* stamp;
    uint32_t epoch;
    bool Visit(uint32_t site) const {
      if (stamp[site] == epoch) return false;
      stamp[site] = epoch;
      return true;
    }
  };
  static Search Begin(uint32_t num_points) {
    thread_local VisitMarks marks;
    if (marks.stamp_.size() < num_points) marks.stamp_.assign(num_points, 0);
    if (++marks.epoch_ == 0) {
      std::fill(marks.stamp_.begin(), marks.stamp_.end(), 0);
      marks.epoch_ = 1;
    }
    return {marks.stamp_.data(), marks.epoch_};
  }

 private:
  std::vector<uint32_t> stamp_;
  uint32_t epoch_ = 0;
};

// A per-thread scratch vector (one per element type), reached once per
// query rather than through a thread_local access at every use.
template <typename T>
std::vector<T>& Scratch() {
  thread_local std::vector<T> v;
  return v;
}

// Appends the points of `site` (ascending external id) except `skip`, at
// most `cap` of them. A site of many coincident points is read from the
// sorted member rows of the query view (a prefix, not the whole chain).
void EmitSite(const TriangulationView& v, uint32_t site, const Vec2& q,
              uint32_t skip, std::vector<Hit>& out, bool distance = true,
              size_t cap = SIZE_MAX) {
  if (cap == 0) return;
  const double d = distance ? Distance(q, v.pos[site]) : 0.0;
  if (v.dup_next[site] == kNoVertex) {
    const uint32_t ext = v.ext_of_int[site];
    if (ext != skip) out.push_back({ext, d});
    return;
  }
  if (v.site_member_offsets != nullptr) {
    const uint32_t end = v.site_member_offsets[site + 1];
    for (uint32_t k = v.site_member_offsets[site]; k < end && cap > 0; ++k) {
      if (v.site_members[k] == skip) continue;
      out.push_back({v.site_members[k], d});
      --cap;
    }
    return;
  }
  const size_t begin = out.size();
  for (uint32_t p = site; p != kNoVertex; p = v.dup_next[p]) {
    const uint32_t ext = v.ext_of_int[p];
    if (ext != skip) out.push_back({ext, d});
  }
  std::sort(out.begin() + begin, out.end(),
            [](const Hit& a, const Hit& b) { return a.ext < b.ext; });
  if (out.size() - begin > cap) out.resize(begin + cap);
}

// How a row ended.
enum RowEnd : int {
  kRowComplete = 0,
  kRowTruncated = 1,   // cut at max_results (flagged in NeighborLists)
  kRowOverBudget = 2,  // the query's total limit was passed
  kRowCancelled = 3,
};

// What a row may still produce, and the query's cancellation.
struct RowBudget {
  uint64_t cap = UINT64_MAX;  // results this row may add before the query
                              // exceeds its total limit
  const CancelToken* cancel = nullptr;
  // Poll the token every this many visited sites inside one row.
  static constexpr uint32_t kPollEvery = 4096;
  bool Cancelled() const { return cancel != nullptr && cancel->Cancelled(); }
};

absl::Status CheckQueryPosition(const Vec2& p, size_t i) {
  for (int axis = 0; axis < 2; ++axis) {
    const double c = axis == 0 ? p.x : p.y;
    const char* name = axis == 0 ? "x" : "y";
    if (std::isnan(c) || std::isinf(c) || !InExactDomain(c)) {
      return absl::InvalidArgumentError(
          absl::StrCat("queries[", i, "].", name, " = ", c,
                       std::isnan(c)   ? " is NaN"
                       : std::isinf(c) ? " is infinite"
                                       : " is outside the exact range"));
    }
  }
  return absl::OkStatus();
}

absl::Status CheckRadius(double r) {
  if (std::isnan(r)) return absl::InvalidArgumentError("radius is NaN");
  if (r < 0.0) {
    return absl::InvalidArgumentError(absl::StrCat("radius = ", r, " < 0"));
  }
  if (std::isinf(r) || !InExactDomain(r)) {
    return absl::InvalidArgumentError(absl::StrCat(
        "radius = ", r, " is outside the exact range (0 or [2^-100, 2^100])"));
  }
  return absl::OkStatus();
}

// A batch of queries in request order or, when `every` is set, every
// point of the triangulation `points` views, made on the fly in internal
// order (the processing order: At(j) is the request ext_of_int[j], starting
// at its site; `queries` stays empty). Not materialized, the all-points
// batch costs no 28 bytes per point to write and read back.
struct QueryBatch {
  std::vector<Query> queries;
  bool every = false;
  bool exclude_self = false;
  TriangulationView points;
  size_t size() const { return every ? points.num_points : queries.size(); }
  Query At(size_t j) const {
    return {points.pos[j], exclude_self ? points.ext_of_int[j] : kNoVertex,
            points.rep[j]};
  }
  // Queries of points (each starts at its site), not of positions.
  bool of_points() const {
    return every || (!queries.empty() && queries[0].start_site != kNoVertex);
  }
};

// The queries of positions and of points, their arguments already checked
// (CheckQueryPositions, CheckQueryIds).
QueryBatch PositionQueries(absl::Span<const Vec2> qs) {
  QueryBatch out;
  out.queries.resize(qs.size());
  for (size_t i = 0; i < qs.size(); ++i) out.queries[i].q = qs[i];
  return out;
}

QueryBatch PointQueries(const Triangulation& t, absl::Span<const uint32_t> ids,
                        bool exclude_self) {
  const TriangulationView v = t.view();
  QueryBatch out;
  // Every point, by id (the all-points query): the queries are made in
  // internal order, which is the processing order (internal ids follow a
  // Hilbert curve), reading the points' arrays in sequence; the request
  // of internal id j is its external id.
  bool every_point = ids.size() == v.num_points && !ids.empty();
  if (every_point) {
    std::atomic<bool> identity{true};
    t.Run([&] {
      ParallelFor(0, ids.size(), [&](size_t i) {
        if (ids[i] != i) identity.store(false, std::memory_order_relaxed);
      });
    });
    every_point = identity.load();
  }
  if (every_point) {
    out.every = true;
    out.exclude_self = exclude_self;
    out.points = v;
    return out;
  }
  out.queries.resize(ids.size());
  t.Run([&] {
    ParallelFor(0, ids.size(), [&](size_t i) {
      const uint32_t in = v.int_of_ext[ids[i]];
      Query& q = out.queries[i];
      q.q = v.pos[in];
      q.self_ext = exclude_self ? ids[i] : kNoVertex;
      q.start_site = v.rep[in];
    });
  });
  return out;
}

// Indices 0..keys.size()-1 ordered by key >> shift (stable), keys < bound:
// a counting sort, with the keys coarsened (by the smallest shift) until
// there are at most two buckets per key, so it costs O(keys) whatever the
// bound. The order only groups queries whose start sites are near in the
// Hilbert order (8 sites apart for 100K queries on 1M sites); a comparison
// sort of the exact keys cost 7 ms for 100K queries at 1M, serial.
std::vector<uint32_t> OrderByKey(const std::vector<uint32_t>& keys,
                                 uint32_t bound) {
  std::vector<uint32_t> order(keys.size());
  int shift = 0;
  while ((uint64_t{bound} >> shift) > 2 * uint64_t{keys.size()} + 64) ++shift;
  const size_t buckets = (uint64_t{bound} >> shift) + 1;
  std::vector<uint32_t> count(buckets + 1, 0);
  for (uint32_t k : keys) ++count[(k >> shift) + 1];
  for (size_t b = 0; b < buckets; ++b) count[b + 1] += count[b];
  for (uint32_t i = 0; i < keys.size(); ++i) {
    order[count[keys[i] >> shift]++] = i;
  }
  return order;
}

// Copies a row of ids: rows are short (a call to memmove per row of 8
// cost more than the copy), so in fixed blocks of 8 that the compiler
// inlines, then one by one.
inline void CopyIds(const uint32_t* from, uint64_t len, uint32_t* to) {
  uint64_t k = 0;
  for (; k + 8 <= len; k += 8) std::memcpy(to + k, from + k, 8 * sizeof(*to));
  for (; k < len; ++k) {
    asm("" ::: "memory");  // keeps this loop from becoming a memmove call
    to[k] = from[k];
  }
}

// The memory of an earlier answer (RowOptions::recycle), which is left
// empty; an empty answer when there is none.
NeighborLists TakeRecycled(NeighborLists* recycle) {
  if (recycle == nullptr) return NeighborLists();
  NeighborLists taken = std::move(*recycle);
  *recycle = NeighborLists();
  return taken;
}

// Rows of every query by row_fn, which gets the query's nearest site as
// `root` (find_root false: the site its walk would start from, for a row
// that may not need it). `width` > 0 promises that every complete
// row has exactly that many results (k-NN of a set with more than k
// points): the answer's size is then known before any row is built, so it
// is checked against max_total_results and admitted in one call up front,
// and rows are written straight into the answer. Otherwise rows go to
// per-block buffers, admitted as they grow, then into the answer.
//
// `build_rows` says whether the step's neighbour rows are built for the
// batch (Triangulation::query_view; NeedRows below); without them, rows
// that walk the graph read each site's neighbours off the mesh (the rows
// are still used where an earlier batch of the step built them).
template <typename RowFn>
absl::StatusOr<NeighborLists> RunRows(
    const Triangulation& t, const QueryBatch& batch, QueryLimits limits,
    bool distances, RowFn&& row_fn, size_t width = 0, bool find_root = true,
    bool build_rows = true, NeighborLists* recycle = nullptr) {
  const std::vector<Query>& queries = batch.queries;
  const size_t nq = batch.size();
  if (t.num_sites() == 0) width = 0;
  // The answer is built in the recycled one's memory, if any (resized, not
  // cleared first: a vector that keeps its size is not written twice).
  NeighborLists fixed = TakeRecycled(recycle);
  if (!distances) fixed.distances.clear();
  if (width > 0) {
    const uint64_t all = uint64_t{nq} * width;
    if (limits.max_total_results && all > limits.max_total_results) {
      return ResultLimitError(limits.max_total_results);
    }
    if (limits.admit && all > 0) {
      const uint64_t step = QueryLimits::kAdmitStep;
      if (absl::Status s = limits.admit((all + step - 1) / step * step);
          !s.ok()) {
        return s;
      }
    }
    fixed.ids.resize(all);
    if (distances) fixed.distances.resize(all);
  }
  // Set when a row of a fixed-width answer came out shorter (never
  // expected): the query is then answered the general way.
  std::atomic<bool> short_row{false};
  // Rows are produced in fixed blocks of queries, each block appending to
  // its own buffer (no allocation per row), then copied into the CSR.
  constexpr size_t kBlock = 256;
  const size_t blocks = (nq + kBlock - 1) / kBlock;
  // Per block: the ids of its rows and (when asked) their distances, in
  // separate arrays (4 bytes per result for set rows, not a 16-byte Hit).
  std::vector<std::vector<uint32_t>> block_ids(blocks);
  std::vector<std::vector<double>> block_dist(distances ? blocks : 0);
  // (The per-row bookkeeping of the general way; none for fixed widths.)
  const size_t rows_kept = width > 0 ? 0 : nq;
  std::vector<uint64_t> row_size(rows_kept, 0);
  std::vector<uint8_t> truncated(rows_kept, 0);
  // Where the row of each slot (processing order) starts in its block's
  // buffer (block = slot / kBlock), and then where the row of each request
  // is, so that the final copy reads one address per row.
  std::vector<uint64_t> row_start(rows_kept, 0);
  std::vector<const uint32_t*> ids_of(rows_kept, nullptr);
  std::vector<const double*> dist_of(distances ? rows_kept : 0, nullptr);
  std::atomic<uint64_t> total{0};
  std::atomic<bool> stop{false}, exceeded{false};
  // limits.admit, one call at a time: what it granted, and its refusal.
  std::mutex admit_mu;
  std::atomic<uint64_t> admitted{0};
  absl::Status refused;
  const bool counted = width == 0 && (limits.max_total_results || limits.admit);
  // Results are added to `total` by each block in batches of up to
  // kCountBatch (before the batch's last row is stored), so at any time
  // every other thread holds fewer than that uncounted.
  constexpr uint64_t kCountBatch = QueryLimits::kCountBatch;
  const uint64_t uncounted_elsewhere =
      kCountBatch * static_cast<uint64_t>(std::max(t.num_threads(), 1) - 1);
  if (t.num_sites() > 0) {
    const TriangulationView v =
        build_rows ? t.query_view() : t.view_with_cached_rows();
    t.Run([&] {
      // Queries run in the order of their start sites (internal ids follow
      // a Hilbert curve), so that neighbouring queries touch the same
      // memory; rows still come out in request order. The queries and
      // their per-row bookkeeping are gathered into that order first, so
      // the searches read and write them sequentially (a gather in a tight
      // loop overlaps its cache misses; inside the search loop each one
      // would stall the search). A batch may come in that order already.
      std::vector<uint32_t> order_made;
      std::vector<Query> sorted_made;
      std::vector<uint32_t> sorted_start;
      if (!batch.every) {
        sorted_start.resize(nq);
        std::shared_ptr<const HintGrid> grid;
        bool need_hints = false;
        for (const Query& q : queries) need_hints |= q.start_site == kNoVertex;
        // Built once per step (the server asks a batch in blocks).
        if (need_hints) grid = t.CachedHintGrid();
        const HintGridView hints = grid ? grid->view() : HintGridView{};
        std::vector<uint32_t> start(nq);
        ParallelFor(0, nq, [&](size_t i) {
          const Query& q = queries[i];
          start[i] = q.start_site != kNoVertex ? q.start_site : hints.Hint(q.q);
        });
        order_made = OrderByKey(start, v.num_points);
        sorted_made.resize(nq);
        ParallelFor(0, nq, [&](size_t j) {
          sorted_made[j] = queries[order_made[j]];
          sorted_start[j] = start[order_made[j]];
        });
      }
      // Request of each processing slot, its query, and its start site.
      const uint32_t* const order =
          batch.every ? batch.points.ext_of_int : order_made.data();
      auto query_at = [&](size_t j) {
        return batch.every ? batch.At(j) : sorted_made[j];
      };
      const uint32_t* const starts =
          batch.every ? batch.points.rep : sorted_start.data();
      std::vector<uint64_t> sorted_size(rows_kept, 0);
      std::vector<uint8_t> sorted_truncated(rows_kept, 0);
      ParallelFor(
          0, blocks,
          [&](size_t b) {
            std::vector<uint32_t>& ids = block_ids[b];
            std::vector<Hit>& row = Scratch<Hit>();
            const size_t first = b * kBlock;
            const size_t last = std::min(nq, first + kBlock);
            // Fixed-width rows are staged in processing order and copied
            // to their requests' places once the block is done: written
            // straight there, every row was a scattered store (request
            // order is not spatial order) in the middle of the search
            // (8-NN of all 100K points: 0.3-1.5 ms less of 14-18 ms).
            std::vector<uint32_t>& staged_ids = Scratch<uint32_t>();
            std::vector<double>& staged_dist = Scratch<double>();
            if (width > 0) {
              staged_ids.resize(kBlock * width);
              if (distances) staged_dist.resize(kBlock * width);
            }
            // This block's results not yet added to `total`.
            uint64_t pending = 0;
            for (size_t j = first; j < last; ++j) {
              if (stop.load(std::memory_order_relaxed)) return;
              if (limits.cancel != nullptr && j % 64 == 0 &&
                  limits.cancel->Cancelled()) {
                stop.store(true, std::memory_order_relaxed);
                return;
              }
              const Query q = query_at(j);
              const uint32_t s = starts[j];
              // A query at a site's own position (queries of points)
              // starts there: distance 0 comes first, no walk needed.
              // (Without find_root, row_fn gets the start site and walks
              // from it only if it needs the nearest site.)
              const uint32_t root = !find_root || v.pos[s] == q.q
                                        ? s
                                        : WalkToNearestSite(v, q.q, s);
              row.clear();
              RowBudget budget;
              budget.cancel = limits.cancel;
              if (limits.max_total_results) {
                const uint64_t used =
                    total.load(std::memory_order_relaxed) + pending;
                budget.cap = used >= limits.max_total_results
                                 ? 0
                                 : limits.max_total_results - used;
              }
              const int end = row_fn(v, q, root, budget, row);
              if (end == kRowCancelled) {
                stop.store(true, std::memory_order_relaxed);
                return;
              }
              // The limit is checked inside rows and as rows complete:
              // work stops as soon as the total passes it.
              if (end == kRowOverBudget || row.size() > budget.cap) {
                exceeded.store(true, std::memory_order_relaxed);
                stop.store(true, std::memory_order_relaxed);
                return;
              }
              if (width > 0) {
                if (row.size() != width) {
                  short_row.store(true, std::memory_order_relaxed);
                  stop.store(true, std::memory_order_relaxed);
                  return;
                }
                const size_t at = (j - first) * width;
                for (size_t c = 0; c < width; ++c) {
                  staged_ids[at + c] = row[c].ext;
                }
                if (distances) {
                  for (size_t c = 0; c < width; ++c) {
                    staged_dist[at + c] = row[c].dist;
                  }
                }
                continue;
              }
              // Results kept so far, as far as this block knows (the
              // others' uncounted ones aside).
              uint64_t kept = 0;
              if (counted) {
                pending += row.size();
                if (pending >= kCountBatch) {
                  kept = total.fetch_add(pending, std::memory_order_relaxed) +
                         pending;
                  pending = 0;
                } else {
                  kept = total.load(std::memory_order_relaxed) + pending;
                }
              }
              if (limits.max_total_results && kept > limits.max_total_results) {
                exceeded.store(true, std::memory_order_relaxed);
                stop.store(true, std::memory_order_relaxed);
                return;
              }
              // Admitted before this row is stored (an empty row stores
              // nothing): every result any thread may hold.
              const uint64_t held = kept + uncounted_elsewhere;
              if (limits.admit && !row.empty() &&
                  held > admitted.load(std::memory_order_acquire)) {
                std::lock_guard<std::mutex> lock(admit_mu);
                if (held > admitted.load(std::memory_order_relaxed)) {
                  const uint64_t step = QueryLimits::kAdmitStep;
                  const uint64_t grant = (held + step - 1) / step * step;
                  absl::Status s = refused.ok() ? limits.admit(grant) : refused;
                  if (!s.ok()) {
                    refused = s;
                    stop.store(true, std::memory_order_relaxed);
                    return;
                  }
                  admitted.store(grant, std::memory_order_release);
                }
              }
              sorted_truncated[j] = end == kRowTruncated ? 1 : 0;
              sorted_size[j] = row.size();
              row_start[j] = ids.size();
              // Resized once per row (push_back checks the capacity per
              // id, which cost 10 % of a batch of 8-neighbour rows).
              const size_t at = ids.size();
              ids.resize(at + row.size());
              for (size_t c = 0; c < row.size(); ++c) ids[at + c] = row[c].ext;
              if (distances) {
                std::vector<double>& dist = block_dist[b];
                dist.resize(at + row.size());
                for (size_t c = 0; c < row.size(); ++c) {
                  dist[at + c] = row[c].dist;
                }
              }
            }
            if (pending > 0) {
              // The block's last results: the count that completes the
              // total is checked here (the last block to add sees it all).
              const uint64_t kept =
                  total.fetch_add(pending, std::memory_order_relaxed) + pending;
              if (limits.max_total_results && kept > limits.max_total_results) {
                exceeded.store(true, std::memory_order_relaxed);
                stop.store(true, std::memory_order_relaxed);
              }
            }
            if (width == 0) return;
            // The block's rows to their places, each destination fetched
            // a few rows ahead so that the stores' misses overlap.
            constexpr size_t kAhead = 8;
            for (size_t j = first; j < last; ++j) {
              if (j + kAhead < last) {
                const size_t ahead = size_t{order[j + kAhead]} * width;
                __builtin_prefetch(fixed.ids.data() + ahead, 1);
                if (distances) {
                  __builtin_prefetch(fixed.distances.data() + ahead, 1);
                }
              }
              const size_t at = size_t{order[j]} * width;
              const size_t from = (j - first) * width;
              CopyIds(staged_ids.data() + from, width, fixed.ids.data() + at);
              if (distances) {
                std::copy_n(staged_dist.data() + from, width,
                            fixed.distances.data() + at);
              }
            }
          },
          1);
      ParallelFor(0, rows_kept, [&](size_t j) {
        const uint32_t i = order[j];
        ids_of[i] = block_ids[j / kBlock].data() + row_start[j];
        if (distances)
          dist_of[i] = block_dist[j / kBlock].data() + row_start[j];
        row_size[i] = sorted_size[j];
        truncated[i] = sorted_truncated[j];
      });
    });
  }
  if (exceeded.load()) return ResultLimitError(limits.max_total_results);
  if (!refused.ok()) return refused;
  if (stop.load() && limits.cancel != nullptr) {
    if (absl::Status s = limits.cancel->Check("query"); !s.ok()) return s;
  }
  if (short_row.load()) {
    // The answer was admitted whole already.
    limits.admit = nullptr;
    return RunRows(t, batch, limits, distances, row_fn, 0, find_root,
                   build_rows, &fixed);
  }
  if (width > 0) {
    fixed.offsets.resize(nq + 1);
    ParallelFor(0, nq + 1,
                [&](size_t i) { fixed.offsets[i] = uint64_t{i} * width; });
    fixed.truncated.assign(nq, 0);
    return fixed;
  }
  NeighborLists out = std::move(fixed);
  out.offsets.assign(nq + 1, 0);
  for (size_t i = 0; i < nq; ++i) {
    out.offsets[i + 1] = out.offsets[i] + row_size[i];
  }
  out.ids.resize(out.offsets[nq]);
  if (distances) out.distances.resize(out.offsets[nq]);
  // Rows lie in their blocks in processing order: each one is a cache miss,
  // fetched ahead.
  constexpr size_t kAhead = 16;
  ParallelFor(0, nq, [&](size_t i) {
    if (i + kAhead < nq) __builtin_prefetch(ids_of[i + kAhead]);
    const uint64_t len = out.offsets[i + 1] - out.offsets[i];
    if (len == 0) return;
    CopyIds(ids_of[i], len, out.ids.data() + out.offsets[i]);
    if (distances) {
      std::copy_n(dist_of[i], len, out.distances.begin() + out.offsets[i]);
    }
  });
  out.truncated = std::move(truncated);
  return out;
}

// Sorts a[0..n) (squared distance from q in double, site or slot) closest
// first in the exact order: by the squared distances (by insertion when
// short: rows of a few sites), then an insertion pass in the exact order,
// which moves only near-ties. pos(x) is the position of site or slot x.
// Insertion pass in q's exact order over a[0..n) (squared distances
// cached in .first): a pass of compares where a is already in the order
// of the squared distances and nothing is near a tie.
template <typename PosOf>
void OrderExactly(const Vec2& q, std::pair<double, uint32_t>* a, size_t n,
                  PosOf&& pos) {
  for (size_t i = 1; i < n; ++i) {
    const auto x = a[i];
    size_t j = i;
    while (j > 0 &&
           CompareCloserCached(q, pos(x.second), x.first, pos(a[j - 1].second),
                               a[j - 1].first) < 0) {
      a[j] = a[j - 1];
      --j;
    }
    a[j] = x;
  }
}

template <typename PosOf>
void SortClosestFirst(const Vec2& q, std::pair<double, uint32_t>* a, size_t n,
                      PosOf&& pos) {
  auto by_d2 = [](const std::pair<double, uint32_t>& x,
                  const std::pair<double, uint32_t>& y) {
    return x.first < y.first;
  };
  if (n <= 32) {
    for (size_t i = 1; i < n; ++i) {
      const auto x = a[i];
      size_t j = i;
      for (; j > 0 && by_d2(x, a[j - 1]); --j) a[j] = a[j - 1];
      a[j] = x;
    }
  } else {
    std::sort(a, a + n, by_d2);
  }
  OrderExactly(q, a, n, pos);
}

// Compare-exchange of two packed keys (SelectClosestSmall): the smaller
// in a. Branch-free: minsd / maxsd, written out (the compiler turns the
// conditional form into branches, which mispredict on this data).
inline void CompareExchange(double& a, double& b) {
#if defined(__SSE2__)
  const __m128d x = _mm_set_sd(a), y = _mm_set_sd(b);
  a = _mm_cvtsd_f64(_mm_min_sd(x, y));
  b = _mm_cvtsd_f64(_mm_max_sd(x, y));
#else
  const double lo = b < a ? b : a;
  b = b < a ? a : b;
  a = lo;
#endif
}

// Sorts k[0..8) (Batcher's 19-comparator network).
inline void SortEight(double* k) {
  CompareExchange(k[0], k[2]);
  CompareExchange(k[1], k[3]);
  CompareExchange(k[4], k[6]);
  CompareExchange(k[5], k[7]);
  CompareExchange(k[0], k[4]);
  CompareExchange(k[1], k[5]);
  CompareExchange(k[2], k[6]);
  CompareExchange(k[3], k[7]);
  CompareExchange(k[0], k[1]);
  CompareExchange(k[2], k[3]);
  CompareExchange(k[4], k[5]);
  CompareExchange(k[6], k[7]);
  CompareExchange(k[2], k[4]);
  CompareExchange(k[3], k[5]);
  CompareExchange(k[1], k[4]);
  CompareExchange(k[3], k[6]);
  CompareExchange(k[1], k[2]);
  CompareExchange(k[3], k[4]);
  CompareExchange(k[5], k[6]);
}

// SortClosestPrefix for the common small case, without its branches on
// the data (which mispredict about once per candidate): want <= 8 of
// n <= 64 candidates. Each squared distance is packed with the
// candidate's place in its lowest 6 bits. Non-negative doubles order as
// their bit patterns, so the packed keys order as the distances within
// 2^-46 relative (coordinates in the exact domain make every squared
// distance finite and either 0, which packs below all others, or at
// least 2^-304). Min / max networks keep the 8 smallest in order and the
// smallest of the rest (the 9th) over blocks of 8 candidates. Those
// within rounding (and the packing's error) of the want-th join the
// front, as in SortClosestPrefix, and an exact insertion pass (nearly
// always a pass of compares) orders them. Returns the front's length m,
// with a[m..n) left unspecified (the front's entries may appear there
// again), or 0, with a unchanged, when this case does not apply (n > 64,
// want > 8, or the 9th within rounding of the want-th: the general path
// handles those).
template <typename PosOf>
size_t SelectClosestSmall(const Vec2& q, std::pair<double, uint32_t>* a,
                          size_t n, size_t want, PosOf&& pos) {
  constexpr uint64_t kSlotBits = 0x3f;
  if (n > kSlotBits + 1 || want > 8 || want == 0) return 0;
  constexpr double kInf = std::numeric_limits<double>::infinity();
  auto load = [a, n](size_t first, double* k) {
    for (size_t i = 0; i < 8; ++i) {
      k[i] = kInf;
      if (first + i < n) {
        uint64_t bits;
        std::memcpy(&bits, &a[first + i].first, sizeof bits);
        // A distance of 0 (a position at a site) packs as the smallest
        // normal double, below every other distance (at least 2^-304): a
        // subnormal key would be read as 0 with denormals-are-zero set.
        bits |= uint64_t{bits == 0} << 52;
        bits = (bits & ~kSlotBits) | (first + i);
        std::memcpy(&k[i], &bits, sizeof bits);
      }
    }
  };
  double lo[8], block[8];
  load(0, lo);
  SortEight(lo);
  // Once more than 8: the 8 smallest of lo and the next block, as a
  // bitonic sequence, then in order; the block keeps the rest.
  double ninth = kInf;
  for (size_t first = 8; first < n; first += 8) {
    load(first, block);
    SortEight(block);
    for (int i = 0; i < 8; ++i) CompareExchange(lo[i], block[7 - i]);
    for (int i = 0; i < 4; ++i) CompareExchange(lo[i], lo[i + 4]);
    CompareExchange(lo[0], lo[2]);
    CompareExchange(lo[1], lo[3]);
    CompareExchange(lo[4], lo[6]);
    CompareExchange(lo[5], lo[7]);
    for (int i = 0; i < 8; i += 2) CompareExchange(lo[i], lo[i + 1]);
    for (int i = 0; i < 8; ++i) CompareExchange(ninth, block[i]);
  }
  auto slot = [&](double key) {
    uint64_t bits;
    std::memcpy(&bits, &key, sizeof bits);
    return static_cast<size_t>(bits & kSlotBits);
  };
  const size_t have = std::min<size_t>(n, 8);
  std::pair<double, uint32_t> front[8];
  for (size_t i = 0; i < have; ++i) front[i] = a[slot(lo[i])];
  size_t m = std::min(want, have);
  if (n > want) {
    // Entries after the want-th join the front while they may come before
    // it exactly: within rounding of the cut, or within the packing's
    // error (2^-46 relative) of it, with room to spare.
    const double cut = front[want - 1].first;
    auto may_join = [cut](double d) {
      return d <= cut + internal::kDistErrBound * (cut + d) + cut * 0x1p-40;
    };
    while (m < have && may_join(front[m].first)) ++m;
    // Past an entry that does not join, none does (they come later in the
    // packed order, by more than its error). All 8 joined and more are
    // left: the general path decides when the smallest of the rest (the
    // 9th) may join too.
    if (m == have && n > have && may_join(a[slot(ninth)].first)) return 0;
  }
  OrderExactly(q, front, m, pos);
  std::copy(front, front + m, a);
  return m;
}

// Puts the first `want` of a[0..n) in q's exact order at the front (the
// rest of a is left unspecified) and returns how many leading entries
// are in that order: at least min(want, n). Small cases go to
// SelectClosestSmall. The `want` smallest squared
// distances are selected in double (a later entry replaces the current
// last one when it is smaller); the entries left out whose distance lies
// within rounding of the cut may still come before it exactly, so they
// join the front, and the exact insertion pass of SortClosestFirst orders
// it. When n is not much more than want, everything is sorted.
template <typename PosOf>
size_t SortClosestPrefix(const Vec2& q, std::pair<double, uint32_t>* a,
                         size_t n, size_t want, PosOf&& pos) {
  if (const size_t m = SelectClosestSmall(q, a, n, want, pos); m > 0) {
    return m;
  }
  if (want == 0 || n <= want) {
    SortClosestFirst(q, a, n, pos);
    return n;
  }
  for (size_t i = 1; i < want; ++i) {
    const auto x = a[i];
    size_t j = i;
    for (; j > 0 && x.first < a[j - 1].first; --j) a[j] = a[j - 1];
    a[j] = x;
  }
  for (size_t i = want; i < n; ++i) {
    if (!(a[i].first < a[want - 1].first)) continue;
    const auto x = a[i];
    a[i] = a[want - 1];
    size_t j = want - 1;
    for (; j > 0 && x.first < a[j - 1].first; --j) a[j] = a[j - 1];
    a[j] = x;
  }
  const double cut = a[want - 1].first;
  size_t m = want;
  for (size_t i = want; i < n; ++i) {
    if (a[i].first <= cut + internal::kDistErrBound * (cut + a[i].first)) {
      std::swap(a[m++], a[i]);
    }
  }
  SortClosestFirst(q, a, m, pos);
  return m;
}

// The first `want` points of q's order (fewer if the set is smaller), by
// best-first expansion from root over a bounded candidate list kept in the
// exact order (squared distances in double decide clear cases). A candidate
// ranked beyond what can still be taken is dropped: every pop emits at
// least one point (only the query's own site, popped first, may emit none),
// so with `need` points still wanted at most need + 1 more sites are
// popped, and anything behind need + 1 better candidates is never reached.
// Visited sites are marked with per-thread epoch stamps.
int KnnRow(const TriangulationView& v, const Query& q, uint32_t root,
           size_t want, const RowBudget& budget, std::vector<Hit>& out) {
  using Entry = std::pair<double, uint32_t>;
  auto before = [&](const Entry& a, const Entry& b) {
    return CompareCloserCached(q.q, v.pos[a.second], a.first, v.pos[b.second],
                               b.first) < 0;
  };
  std::vector<Entry>& cand = Scratch<Entry>();
  const VisitMarks::Search marks = VisitMarks::Begin(v.num_points);
  cand.clear();
  cand.push_back({SquaredDistance(q.q, v.pos[root]), root});
  marks.Visit(root);
  size_t head = 0;  // cand[head..] sorted, closest first
  uint32_t pops = 0;
  while (head < cand.size() && out.size() < want) {
    if (++pops % RowBudget::kPollEvery == 0 && budget.Cancelled()) {
      return kRowCancelled;
    }
    const uint32_t s = cand[head++].second;
    EmitSite(v, s, q.q, q.self_ext, out, true, want - out.size());
    if (out.size() >= want) break;
    const size_t cap = want - out.size() + 1;
    auto consider = [&](uint32_t w) __attribute__((always_inline)) {
      if (!marks.Visit(w)) return;
      const Entry e{SquaredDistance(q.q, v.pos[w]), w};
      const size_t live = cand.size() - head;
      if (live >= cap && !before(e, cand.back())) return;
      size_t j = cand.size();
      cand.push_back(e);
      while (j > head && before(e, cand[j - 1])) {
        cand[j] = cand[j - 1];
        --j;
      }
      cand[j] = e;
      if (cand.size() - head > cap) cand.pop_back();
    };
    // The step's rows where they were built (a loop the compiler keeps
    // tight), else the fan of s in the mesh.
    if (v.adj_offsets != nullptr) {
      for (const uint32_t* it = v.RowBegin(s); it != v.RowEnd(s); ++it) {
        consider(*it);
      }
    } else {
      v.ForEachNeighbor(s, consider);
    }
  }
  if (out.size() > want) out.resize(want);
  return kRowComplete;
}

// k nearest from a cell index (KnnCells): the sites of the cells that meet
// the square [q - r, q + r]^2 that may lie within r of q (squared distance
// in double within rounding of r^2) are kept; once `want` of them (the
// query's own point excluded) lie within r for certain, every point that
// comes before the want-th one in q's order is closer, so among the kept
// ones, and sorting them in the exact order gives the row. Otherwise r
// grows by half and the cells are scanned again. The first r of a row is
// the previous row's want-th distance on this thread, enlarged a little
// (rows run in spatial order, so it nearly fits), or `r0` after another
// index. Returns false, with `out` unspecified, when the graph must answer
// the row: a site of several points is a candidate, or the candidates
// pass a bound (the density changed sharply).
bool KnnCellsRow(const CellIndex& cells, const Query& q, size_t want, double r0,
                 std::vector<Hit>& out) {
  // Enlarging the last row's want-th distance by this keeps about 1.4
  // times want candidates in a disk: one scan suffices for most rows.
  constexpr double kGuessGrowth = 1.2;
  constexpr double kRetryGrowth = 1.5;
  struct Guess {
    const CellIndex* cells = nullptr;
    double r = 0.0;
  };
  thread_local Guess guess;
  // (A last row whose want-th point is at distance 0 leaves no guess.)
  double r = guess.cells == &cells && guess.r > 0.0 ? guess.r : r0;
  const size_t max_kept = 64 * want + 256;
  const Vec2* pos = cells.positions();
  const uint32_t* exts = cells.exts();
  // The candidates that may lie in the disk, in a per-thread buffer sized
  // once (written past their count, without a branch on the outcome).
  std::vector<std::pair<double, uint32_t>>& buffer =
      Scratch<std::pair<double, uint32_t>>();
  if (buffer.size() < max_kept) buffer.resize(max_kept);
  std::pair<double, uint32_t>* const kept = buffer.data();
  size_t num_kept;
  while (true) {
    const double rr = r * r;
    // As in the radius filter: below `inside` within r for certain, above
    // `outside` beyond it.
    const double inside = rr * (1.0 - 3.0 * internal::kDistErrBound);
    const double outside = rr * (1.0 + 3.0 * internal::kDistErrBound);
    size_t m = 0, in = 0;
    bool several = false, overflow = false;
    cells.ForEachRun(q.q, r, [&](uint32_t b, uint32_t e) {
      if (m + (e - b) > max_kept) {
        overflow = true;
        return false;
      }
      for (uint32_t c = b; c < e; ++c) {
        const double dw = SquaredDistance(q.q, pos[c]);
        const uint32_t ext = exts[c];
        kept[m] = {dw, c};
        // (Sites of several points have no ext: never the query's own.)
        const bool keep =
            (dw <= outside) & ((ext != q.self_ext) | (ext == kNoVertex));
        m += keep;
        in += keep & (dw < inside);
        several |= keep & (ext == kNoVertex);
      }
      return true;
    });
    if (overflow || several) {
      guess.cells = nullptr;  // the next row starts from r0
      return false;
    }
    if (in >= want) {
      num_kept = m;
      break;
    }
    r *= kRetryGrowth;
  }
  SortClosestPrefix(q.q, kept, num_kept, want,
                    [pos](uint32_t c) -> const Vec2& { return pos[c]; });
  out.resize(want);
  for (size_t i = 0; i < want; ++i) {
    out[i] = {exts[kept[i].second], std::sqrt(kept[i].first)};
  }
  guess = {&cells, std::sqrt(kept[want - 1].first) * kGuessGrowth};
  return true;
}

// Sites per cell of the k-nearest queries' cell index, and the most
// (as a site sees it: the mean over sites of its own cell's count; about
// one more than the mean for uniform points) before the graph is used
// instead: crowded cells (clustered points) cost a scan of all their sites
// for every query in them.
constexpr double kKnnCellsSitesPerCell = 2.0;
constexpr double kKnnCellsMaxOccupancy = 4.0 * (kKnnCellsSitesPerCell + 1.0);
// The cell index serves k up to this; it pays for batches of at least one
// query per kCellsMinQueriesPerSite sites (below).
constexpr int kKnnCellsMaxK = 64;
// Every this many sites are sampled to estimate the occupancy first.
constexpr uint32_t kKnnCellsOccupancySample = 16;
constexpr size_t kKnnCellsMinSites = 4096;

std::shared_ptr<const CellIndex> KnnCells(const Triangulation& t, int k,
                                          size_t num_queries,
                                          RowOptions options);

// Whether a batch builds the step's neighbour rows (RunRows' build_rows).
// Sites of several points need them (their members are listed there).
// Otherwise rows pay for a batch that walks the graph (no cell index) with
// at least one query per kRowsMinQueriesPerSite sites: building them is a
// pass over every site's fan (about 40 ms at 1M points on 2 cores), which
// a smaller batch, or one answered from cells, would not earn back.
constexpr size_t kRowsMinQueriesPerSite = 8;
bool NeedRows(const Triangulation& t, bool cells, size_t num_queries,
              RowOptions options) {
  if (t.num_sites() < t.size()) return true;
  if (cells) return false;
  const uint64_t batch = std::max<uint64_t>(num_queries, options.batch_queries);
  return batch * kRowsMinQueriesPerSite >= t.num_sites();
}

absl::StatusOr<NeighborLists> KNearestImpl(const Triangulation& t,
                                           const QueryBatch& queries, int k,
                                           QueryLimits limits,
                                           RowOptions options) {
  const size_t want = static_cast<size_t>(k);
  std::shared_ptr<const CellIndex> index =
      KnnCells(t, k, queries.size(), options);
  // A sparse index (clustered points) serves queries of points, which lie
  // in occupied cells. A position between the clusters would grow its disk
  // across empty space, scan after scan (8-NN of 100K positions on 1M
  // clustered points: 40 ms by the graph, 95 ms from a sparse index); kAuto
  // sends position batches to the graph there.
  const bool of_points = queries.of_points();
  if (index != nullptr && index->sparse() && !of_points &&
      options.plan == RowOptions::Plan::kAuto) {
    index = nullptr;
  }
  const CellIndex* cells = index.get();
  // The first radius tried: where a disk holds want + 1 sites and a few
  // more (the query's own point may be one) at the mean density.
  const double r0 =
      cells == nullptr
          ? 0.0
          : cells->side() *
                std::sqrt((double(want) + 2.0 + 2.0 * std::sqrt(want + 1.0)) /
                          (3.14159 * kKnnCellsSitesPerCell));
  return RunRows(
      t, queries, limits, /*distances=*/true,
      [want, cells, r0](const TriangulationView& v, const Query& q,
                        uint32_t root, const RowBudget& budget,
                        std::vector<Hit>& out) {
        if (cells == nullptr) return KnnRow(v, q, root, want, budget, out);
        if (KnnCellsRow(*cells, q, want, r0, out)) return int{kRowComplete};
        // `root` is where the walk to the nearest site starts.
        out.clear();
        if (v.pos[root] != q.q) root = WalkToNearestSite(v, q.q, root);
        return KnnRow(v, q, root, want, budget, out);
      },
      // Every row holds k points when the set has more than k.
      t.size() > want ? want : 0, /*find_root=*/cells == nullptr,
      NeedRows(t, cells != nullptr, queries.size(), options), options.recycle);
}

// Disks expected to hold at least this many sites are scanned in a cell
// index (RowOptions::Plan::kAuto); below, the graph walk visits fewer
// candidates than the nine cells around the query hold.
constexpr double kCellsMinSitesPerDisk = 3.0;
// ... and only for batches of at least one query per this many sites.
constexpr size_t kCellsMinQueriesPerSite = 8;

// The cell index a radius batch scans, or null when the plan (or the
// expected disk size) says: walk the graph. kAuto's index is cached in the
// triangulation for the step and radius (the server asks a batch in
// blocks), and so is its decision to walk.
std::shared_ptr<const CellIndex> RadiusCells(const Triangulation& t, double r,
                                             size_t num_queries,
                                             RowOptions options) {
  using Plan = RowOptions::Plan;
  if (options.plan == Plan::kGraph || !t.is_planar() || !(r > 0.0) ||
      num_queries == 0) {
    return nullptr;
  }
  const TriangulationView v = t.view();
  // At most about four cells (or rows) per site: the index's memory stays
  // O(n). kAuto also wants the disks to hold kCellsMinSitesPerDisk sites:
  // at the mean density over the box, i.e. at most pi / that many cells per
  // site, for a dense index; counted over the occupied cells, as the sites
  // see them, for a sparse one (clustered points), which kAuto builds only
  // where a dense one would not fit at all (between the two, kAuto walks
  // the graph). The index gives up before sorting when neither form is
  // allowed; a sparse one is judged after it is built (the decision is
  // cached for the step and radius).
  const size_t memory_cells = 4 * size_t{v.num_sites} + 64;
  CellIndex::Limits limits;
  limits.max_dense_cells = memory_cells;
  limits.min_sparse_cells = memory_cells;
  limits.max_rows = memory_cells;
  if (options.plan == Plan::kAuto) {
    limits.max_dense_cells = std::min<size_t>(
        memory_cells, static_cast<size_t>(double(v.num_sites) * 3.14159 /
                                          kCellsMinSitesPerDisk));
  }
  auto build = [&]() -> std::shared_ptr<const CellIndex> {
    std::optional<CellIndex> cells;
    t.Run([&] { cells = CellIndex::Build(v, r, limits); });
    if (!cells) return nullptr;
    if (options.plan == Plan::kAuto && cells->sparse() &&
        cells->occupancy() * 3.14159 < kCellsMinSitesPerDisk) {
      return nullptr;
    }
    return std::make_shared<const CellIndex>(*std::move(cells));
  };
  if (options.plan == Plan::kCells) return build();
  // Building the index costs a pass over every site: a batch of few
  // queries walks the graph (100K position queries on 1M sites: 70 ms by
  // the graph, 77-82 ms with an index built for them).
  const uint64_t batch = std::max<uint64_t>(num_queries, options.batch_queries);
  if (batch * kCellsMinQueriesPerSite < v.num_sites &&
      !t.HasCachedCellIndex(Triangulation::CellIndexUse::kRadius, r)) {
    return nullptr;
  }
  return t.CachedCellIndex(Triangulation::CellIndexUse::kRadius, r, build);
}

// The cell index a k-nearest batch scans, or null when the plan says:
// walk the graph. kAuto builds it for large batches of k up to
// kKnnCellsMaxK on sets of at least kKnnCellsMinSites sites spread evenly
// enough, and caches it for the step (any k) with its decision.
std::shared_ptr<const CellIndex> KnnCells(const Triangulation& t, int k,
                                          size_t num_queries,
                                          RowOptions options) {
  using Plan = RowOptions::Plan;
  if (options.plan == Plan::kGraph || !t.is_planar() || num_queries == 0 ||
      k < 1 || t.size() <= static_cast<size_t>(k) + 1) {
    return nullptr;
  }
  const TriangulationView v = t.view();
  // k = 1 walks to the nearest site anyway (the walk is the answer).
  if (k > kKnnCellsMaxK || (options.plan == Plan::kAuto &&
                            (k < 2 || v.num_sites < kKnnCellsMinSites))) {
    return nullptr;
  }
  auto build = [&]() -> std::shared_ptr<const CellIndex> {
    std::optional<CellIndex> cells;
    t.Run([&] {
      const double side = CellIndex::SideForOccupancy(v, kKnnCellsSitesPerCell);
      if (!(side > 0.0)) return;
      // About 1 / kKnnCellsSitesPerCell cells per site (a little more
      // where rounding adds a row or column); never the sparse form.
      CellIndex::Limits limits;
      limits.max_dense_cells = 4 * size_t{v.num_sites} + 64;
      // Crowded cells (clustered points) call for cells small enough for
      // the clusters, in the sparse form (only the occupied cells of each
      // row), where the box allows that many rows. A sample of the sites
      // tells them apart before anything is built (building the dense
      // index to measure its occupancy cost 12 ms at 1M).
      auto sparse = [&](double occupancy) {
        const double finer =
            side * std::sqrt((kKnnCellsSitesPerCell + 1.0) / occupancy);
        CellIndex::Limits sparse_limits = limits;
        sparse_limits.min_sparse_cells = limits.max_dense_cells;
        sparse_limits.max_rows = limits.max_dense_cells;
        return CellIndex::Build(v, finer, sparse_limits);
      };
      const double estimate = CellIndex::EstimateOccupancy(
          v, side, kKnnCellsOccupancySample, limits.max_dense_cells);
      if (std::isfinite(estimate) && estimate > 2.0 * kKnnCellsMaxOccupancy) {
        cells = sparse(estimate);
        if (cells) return;
      }
      cells = CellIndex::Build(v, side, limits);
      if (cells && cells->occupancy() > kKnnCellsMaxOccupancy) {
        std::optional<CellIndex> finer = sparse(cells->occupancy());
        if (finer) cells = std::move(finer);
      }
    });
    if (!cells) return nullptr;
    if (options.plan == Plan::kAuto &&
        cells->occupancy() > kKnnCellsMaxOccupancy) {
      return nullptr;
    }
    return std::make_shared<const CellIndex>(*std::move(cells));
  };
  if (options.plan == Plan::kCells) return build();
  const uint64_t batch = std::max<uint64_t>(num_queries, options.batch_queries);
  if (batch * kCellsMinQueriesPerSite < v.num_sites &&
      !t.HasCachedCellIndex(Triangulation::CellIndexUse::kNearest, 0.0)) {
    return nullptr;
  }
  return t.CachedCellIndex(Triangulation::CellIndexUse::kNearest, 0.0, build);
}

absl::StatusOr<NeighborLists> RadiusImpl(const Triangulation& t,
                                         const QueryBatch& queries, double r,
                                         uint32_t max_results,
                                         QueryLimits limits,
                                         RowOptions options) {
  const std::shared_ptr<const CellIndex> index =
      RadiusCells(t, r, queries.size(), options);
  const CellIndex* cells = index.get();
  return RunRows(
      t, queries, limits, options.distances,
      [r, max_results, options, cells](
          const TriangulationView& v, const Query& q, uint32_t root,
          const RowBudget& budget, std::vector<Hit>& out) -> int {
        if (CompareDistanceToRadius(q.q, v.pos[root], r) > 0) {
          return kRowComplete;
        }
        // A row cut at max_results ends with at most that many points:
        // when the budget has room for them, the points met on the way to
        // the closest ones do not stop it (they once refused queries of cut
        // rows whose answers were within the limit).
        const uint64_t cap = max_results != 0 && max_results <= budget.cap
                                 ? UINT64_MAX
                                 : budget.cap;
        auto& found = Scratch<std::pair<double, uint32_t>>();
        found.clear();
        const double rr = r * r;
        // A row cut at max_results holds the closest max_results points:
        // once the disk holds clearly more sites than that, the k-nearest
        // expansion finds them with work bounded by max_results instead.
        const size_t knn_switch =
            max_results ? 4 * size_t{max_results} + 1024 : SIZE_MAX;
        auto cut_by_knn = [&]() -> int {
          out.clear();
          const int end =
              KnnRow(v, q, root, size_t{max_results} + 1, budget, out);
          if (end != kRowComplete) return end;
          size_t keep = 0;
          while (keep < out.size() &&
                 CompareDistanceToRadius(
                     q.q, v.pos[v.int_of_ext[out[keep].ext]], r) <= 0) {
            ++keep;
          }
          out.resize(keep);
          if (!options.distances) {
            for (Hit& h : out) h.dist = 0.0;
          }
          if (out.size() > max_results) {
            out.resize(max_results);
            return kRowTruncated;
          }
          return kRowComplete;
        };
        // Sites in the disk: squared distances in double decide clear
        // cases, exact predicates the boundary and near-ties.
        auto in_disk = [&](const Vec2& p, double d2) {
          const double tol = internal::kDistErrBound * (d2 + rr);
          if (d2 > rr + tol) return false;
          return d2 < rr - tol || CompareDistanceToRadius(q.q, p, r) <= 0;
        };
        if (cells != nullptr) {
          // Scan the cells around q. Rows in traversal order are written
          // as the sites are found (the index holds the external ids of
          // single-point sites next to their positions).
          int end = kRowComplete;
          uint32_t scanned = 0;
          bool knn = false;
          const bool direct = !options.closest_first;
          out.clear();
          if (direct && max_results == 0) {
            // Rows neither sorted nor cut: each run of slots is filtered
            // without a branch on the outcome (a disk holds under half of
            // its candidates, a coin toss for the branch predictor). Sites
            // near the circle (the exact predicate decides) and sites of
            // several points take the slow path.
            const Vec2* pos = cells->positions();
            const uint32_t* exts = cells->exts();
            // Squared distances below `inside` are within r for certain,
            // above `outside` beyond it: across the band the error bound of
            // in_disk, kDistErrBound (dw + rr), stays below 3 kDistErrBound
            // rr, with room for the rounding of these two products.
            const double inside = rr * (1.0 - 3.0 * internal::kDistErrBound);
            const double outside = rr * (1.0 + 3.0 * internal::kDistErrBound);
            // One run of candidates into out from slot c (the row holds m
            // results), without a branch on the outcome; returns m. (Both
            // fields are written: the vector may copy the slot.)
            const bool with_distances = options.distances;
            auto filter = [&](uint32_t c, uint32_t ce, size_t m) {
              out.resize(m + (ce - c));
              Hit* o = out.data();
              for (uint32_t s = c; s < ce; ++s) {
                const double dw = SquaredDistance(q.q, pos[s]);
                const uint32_t ext = exts[s];
                if (((dw >= inside) & (dw <= outside)) | (ext == kNoVertex)) {
                  if (!in_disk(pos[s], dw)) continue;
                  out.resize(m);
                  if (ext == kNoVertex) {
                    EmitSite(v, cells->site(s), q.q, q.self_ext, out,
                             options.distances);
                  } else if (ext != q.self_ext) {
                    out.push_back({ext, with_distances ? std::sqrt(dw) : 0.0});
                  }
                  m = out.size();
                  out.resize(m + (ce - s - 1));
                  o = out.data();
                  continue;
                }
                o[m] = {ext, with_distances ? std::sqrt(dw) : 0.0};
                m += (dw < inside) & (ext != q.self_ext);
              }
              return m;
            };
            cells->ForEachRun(q.q, r, [&](uint32_t b, uint32_t e) {
              // In chunks: the row overshoots the budget by at most one
              // chunk's sites (the points of each), and the token is polled
              // between them.
              constexpr uint32_t kChunk = 256;
              for (uint32_t c = b; c < e; c += kChunk) {
                const uint32_t ce = std::min(e, c + kChunk);
                const size_t m = filter(c, ce, out.size());
                out.resize(m);
                scanned += ce - c;
                if (m > cap) {
                  end = kRowOverBudget;
                  return false;
                }
                if (scanned >= RowBudget::kPollEvery) {
                  scanned = 0;
                  if (budget.Cancelled()) {
                    end = kRowCancelled;
                    return false;
                  }
                }
              }
              return true;
            });
            return end;
          }
          cells->ForEachCandidate(
              q.q, r, [&](uint32_t w, const Vec2& p, uint32_t ext) {
                if (++scanned % RowBudget::kPollEvery == 0 &&
                    budget.Cancelled()) {
                  end = kRowCancelled;
                  return false;
                }
                const double dw = SquaredDistance(q.q, p);
                if (!in_disk(p, dw)) return true;
                // Rows written directly need the sites only when they may
                // be cut (and then sorted).
                if (!direct || max_results != 0) found.push_back({dw, w});
                if (direct) {
                  if (ext == kNoVertex) {
                    EmitSite(v, w, q.q, q.self_ext, out, options.distances);
                  } else if (ext != q.self_ext) {
                    out.push_back(
                        {ext, options.distances ? std::sqrt(dw) : 0.0});
                  }
                }
                if (found.size() > knn_switch) {
                  knn = true;
                  return false;
                }
                // Every site but the query's own emits a point.
                if ((direct ? out.size() : found.size() - 1) > cap) {
                  end = kRowOverBudget;
                  return false;
                }
                return true;
              });
          if (end != kRowComplete) return end;
          if (knn) return cut_by_knn();
          if (direct) {
            if (max_results == 0 || out.size() <= max_results) {
              return kRowComplete;
            }
            out.clear();  // cut: the closest points, sorted below
          }
        } else {
          // Breadth-first over Delaunay neighbours inside the disk, from
          // the first site. Visited marks are per-thread epoch stamps: a
          // constant time check, never a scan.
          const VisitMarks::Search marks = VisitMarks::Begin(v.num_points);
          found.push_back({SquaredDistance(q.q, v.pos[root]), root});
          marks.Visit(root);
          for (size_t head = 0; head < found.size(); ++head) {
            if (found.size() > knn_switch) return cut_by_knn();
            // Every site but the query's own emits a point.
            if (found.size() - 1 > cap) return kRowOverBudget;
            if (head % RowBudget::kPollEvery == RowBudget::kPollEvery - 1 &&
                budget.Cancelled()) {
              return kRowCancelled;
            }
            const uint32_t u = found[head].second;
            v.ForEachNeighbor(u, [&](uint32_t w) {
              if (!marks.Visit(w)) return;
              const double dw = SquaredDistance(q.q, v.pos[w]);
              if (in_disk(v.pos[w], dw)) found.push_back({dw, w});
            });
          }
        }
        if (!options.closest_first) {
          for (const auto& f : found) {
            EmitSite(v, f.second, q.q, q.self_ext, out, options.distances);
          }
          if (max_results == 0 || out.size() <= max_results) {
            return kRowComplete;
          }
          out.clear();  // a cut row keeps the closest points: sort after all
        }
        // Closest first: sort on the double squared distances,
        // then an insertion pass with the exact order (linear
        // unless rounding misordered near-ties).
        SortClosestFirst(q.q, found.data(), found.size(),
                         [&v](uint32_t w) -> const Vec2& { return v.pos[w]; });
        for (const auto& f : found) {
          EmitSite(v, f.second, q.q, q.self_ext, out, options.distances);
        }
        if (max_results && out.size() > max_results) {
          out.resize(max_results);
          return kRowTruncated;
        }
        return kRowComplete;
      },
      /*width=*/0, /*find_root=*/true,
      // Positions walk to their nearest site whether or not cells answer
      // (the rows make the walks shorter); points start at their site.
      NeedRows(t, cells != nullptr && queries.of_points(), queries.size(),
               options),
      options.recycle);
}

// The rows of `q` from t's device executor (t.device_executor() is set;
// the arguments are checked), over the query view of t's current step.
absl::StatusOr<NeighborLists> DeviceRows(const Triangulation& t,
                                         const device::DeviceQuery& q) {
  const TriangulationView v = t.query_view();
  absl::StatusOr<NeighborLists> out = absl::InternalError("not run");
  t.Run([&] { out = t.device_executor()->Query(v, t.steps(), q); });
  return out;
}

device::DeviceQuery DeviceKnn(int k, QueryLimits limits) {
  device::DeviceQuery q;
  q.kind = device::DeviceQuery::Kind::kKNearest;
  q.k = static_cast<uint32_t>(k);
  q.limits = limits;
  return q;
}

device::DeviceQuery DeviceRadius(double r, uint32_t max_results,
                                 QueryLimits limits, RowOptions options) {
  device::DeviceQuery q;
  q.kind = device::DeviceQuery::Kind::kRadius;
  q.radius = r;
  q.max_results = max_results;
  q.rows = options;
  q.limits = limits;
  return q;
}

}  // namespace

absl::Status ResultLimitError(uint64_t max_total_results) {
  return absl::ResourceExhaustedError(absl::StrCat(
      "query stopped: its rows hold more than ", max_total_results,
      " results in all (the limit); ask fewer targets, a smaller k or "
      "radius, or set max_results_per_row"));
}

absl::StatusOr<NeighborLists> AllNearestNeighbors(const Triangulation& t,
                                                  RowOptions options) {
  if (t.device_executor() != nullptr) {
    device::DeviceQuery q;
    q.kind = device::DeviceQuery::Kind::kAllNearest;
    return DeviceRows(t, q);
  }
  const TriangulationView v = t.view_with_cached_rows();
  const uint32_t n = v.num_points;
  NeighborLists out = TakeRecycled(options.recycle);
  out.offsets.resize(size_t{n} + 1);
  out.ids.resize(n);
  out.distances.resize(n);
  out.truncated.assign(n, 0);
  std::atomic<bool> missing{false};  // a point without another point
  t.Run([&] {
    // Each point's answer (external id, distance) in internal (Hilbert)
    // order, where memory access is local; then gathered into external
    // order (reads gathered with prefetching overlap; writes scattered
    // over the answer cost more).
    std::unique_ptr<NearestNeighbor[]> by_int(new NearestNeighbor[n]);
    if (v.planar() && v.num_sites == n) {
      // Every point is a vertex: one pass over the triangles, whose loads
      // are independent, instead of a walk around each fan, whose loads
      // wait for each other. Then to external ids and distances while in
      // internal order, where the reads of ext_of_int are local.
      NearestNeighborsByTriangles(v.mesh, v.pos, v.vertex_edge, n,
                                  by_int.get());
      ParallelFor(0, n, [&](size_t in) {
        NearestNeighbor& r = by_int[in];
        if (r.id == kNoVertex) return;
        r.id = v.ext_of_int[r.id];
        r.d2 = std::sqrt(r.d2);  // the distance from here on
      });
    } else {
      // Coincident points (or a line): each point's chain, then a walk
      // around its site's fan (the rows are used when a query built them
      // since the step, never built for this).
      ParallelFor(0, n, [&](size_t in) {
        NearestNeighbor& r = by_int[in];
        if (!NearestOtherPoint(v, static_cast<uint32_t>(in), &r.id, &r.d2)) {
          r = NearestNeighbor{};
        }
      });
    }
    ParallelFor(0, n, [&](size_t ext) {
      if (ext + 32 < n) __builtin_prefetch(&by_int[v.int_of_ext[ext + 32]]);
      const NearestNeighbor& r = by_int[v.int_of_ext[ext]];
      if (r.id == kNoVertex) missing.store(true, std::memory_order_relaxed);
      out.ids[ext] = r.id;
      out.distances[ext] = r.d2;
      out.offsets[ext + 1] = ext + 1;
    });
  });
  out.offsets[0] = 0;
  if (!missing.load()) return out;  // two points or more: a row each
  // Rows without a point (fewer than two points), compacted in place.
  uint64_t k = 0;
  for (uint32_t i = 0; i < n; ++i) {
    if (out.ids[i] != kNoVertex) {
      out.ids[k] = out.ids[i];
      out.distances[k] = out.distances[i];
      ++k;
    }
    out.offsets[i + 1] = k;
  }
  out.ids.resize(k);
  out.distances.resize(k);
  return out;
}

// Every query kind checks its arguments here, once, for every executor;
// then the device executor answers when the triangulation has one.
absl::StatusOr<NeighborLists> KNearest(const Triangulation& t,
                                       absl::Span<const Vec2> queries, int k,
                                       QueryLimits limits, RowOptions options) {
  if (absl::Status s = CheckQueryPositions(queries); !s.ok()) return s;
  if (absl::Status s = CheckQueryK(k); !s.ok()) return s;
  if (t.device_executor() != nullptr) {
    device::DeviceQuery q = DeviceKnn(k, limits);
    q.positions = queries;
    return DeviceRows(t, q);
  }
  return KNearestImpl(t, PositionQueries(queries), k, limits, options);
}

absl::StatusOr<NeighborLists> KNearestOfPoints(const Triangulation& t,
                                               absl::Span<const uint32_t> ids,
                                               int k, bool exclude_self,
                                               QueryLimits limits,
                                               RowOptions options) {
  if (absl::Status s = CheckQueryIds(t, ids); !s.ok()) return s;
  if (absl::Status s = CheckQueryK(k); !s.ok()) return s;
  if (t.device_executor() != nullptr) {
    device::DeviceQuery q = DeviceKnn(k, limits);
    q.by_ids = true;
    q.ids = ids;
    q.exclude_self = exclude_self;
    return DeviceRows(t, q);
  }
  return KNearestImpl(t, PointQueries(t, ids, exclude_self), k, limits,
                      options);
}

absl::StatusOr<NeighborLists> Nearest(const Triangulation& t,
                                      absl::Span<const Vec2> queries) {
  return KNearest(t, queries, 1);
}

absl::StatusOr<NeighborLists> WithinRadius(const Triangulation& t,
                                           absl::Span<const Vec2> queries,
                                           double r, uint32_t max_results,
                                           QueryLimits limits,
                                           RowOptions options) {
  if (absl::Status s = CheckQueryPositions(queries); !s.ok()) return s;
  if (absl::Status s = CheckRadius(r); !s.ok()) return s;
  if (t.device_executor() != nullptr) {
    device::DeviceQuery q = DeviceRadius(r, max_results, limits, options);
    q.positions = queries;
    return DeviceRows(t, q);
  }
  return RadiusImpl(t, PositionQueries(queries), r, max_results, limits,
                    options);
}

absl::StatusOr<NeighborLists> WithinRadiusOfPoints(
    const Triangulation& t, absl::Span<const uint32_t> ids, double r,
    bool exclude_self, uint32_t max_results, QueryLimits limits,
    RowOptions options) {
  if (absl::Status s = CheckQueryIds(t, ids); !s.ok()) return s;
  if (absl::Status s = CheckRadius(r); !s.ok()) return s;
  if (t.device_executor() != nullptr) {
    device::DeviceQuery q = DeviceRadius(r, max_results, limits, options);
    q.by_ids = true;
    q.ids = ids;
    q.exclude_self = exclude_self;
    return DeviceRows(t, q);
  }
  return RadiusImpl(t, PointQueries(t, ids, exclude_self), r, max_results,
                    limits, options);
}

absl::Status CheckQueryPositions(absl::Span<const Vec2> queries) {
  for (size_t i = 0; i < queries.size(); ++i) {
    if (absl::Status s = CheckQueryPosition(queries[i], i); !s.ok()) return s;
  }
  return absl::OkStatus();
}

absl::Status CheckQueryIds(const Triangulation& t,
                           absl::Span<const uint32_t> ids) {
  const uint32_t n = t.size();
  for (size_t i = 0; i < ids.size(); ++i) {
    if (ids[i] >= n) {
      return absl::NotFoundError(absl::StrCat(
          "ids[", i, "] = ", ids[i], ": no such point (size ", n, ")"));
    }
  }
  return absl::OkStatus();
}

absl::Status CheckQueryRadius(double r) { return CheckRadius(r); }

absl::Status CheckQueryK(int k) {
  if (k <= 0) {
    return absl::InvalidArgumentError(absl::StrCat("k = ", k, " must be > 0"));
  }
  return absl::OkStatus();
}

}  // namespace kinetri::core
