// The device executor's queries (DeviceExecutor::Query), written once in
// CCCL and compiled with the rest of the executor by both backends (see
// core/device/round_executor.inl, which includes this file). One query per
// element, running the mark-free searches of core/query_search.h (the
// greedy walk, the reverse-search radius enumeration, the growing-disk
// k-NN) over a device copy of the triangulation's query view. Only Thrust
// algorithms over the functors below touch device memory.
//
// A batch runs in blocks of queries. Each block: prepare the queries (walk
// position queries to their nearest site), count every row (stopping at
// what the row may still hold under the per-row cut and the total limit),
// scan the counts into offsets, fill the rows (each sorted into the exact
// order of core/queries.h by its own thread), and download. Between blocks the
// host polls the cancellation token and checks the total limit; block sizes
// adapt so that a block takes about BlockSizer::kTargetSeconds. While a
// block runs, a host thread polls the token and raises a stop word that
// the radius kernels read (pinned host memory on a GPU), so a block of
// queries whose disks hold thousands of points stops soon too.
#ifndef KINETRI_DEVICE_NS
#error "define KINETRI_DEVICE_NS before including device_queries.inl"
#endif

#include <thrust/copy.h>
#include <thrust/device_vector.h>
#include <thrust/for_each.h>
#include <thrust/iterator/counting_iterator.h>
#include <thrust/scan.h>
#include <thrust/transform.h>
#include <thrust/universal_vector.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <condition_variable>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <memory>
#include <mutex>
#include <new>
#include <stdexcept>
#include <string>
#include <system_error>
#include <thread>
#include <type_traits>
#include <vector>

#include "core/cancel.h"
#include "core/device/atomic.h"
#include "core/device/block_sizer.h"
#include "core/device/device_executor.h"
#include "core/device/fault_injector.h"
#include "core/device/profile.h"
#include "core/device/scratch_pool.inl"
#include "core/device/staging.inl"
#include "core/hint_grid.h"
#include "core/query_search.h"
#include "core/query_types.h"
#include "core/query_walks.h"
#include "core/triangulation_view.h"

namespace kinetri::core::device {
namespace KINETRI_DEVICE_NS {
namespace {

namespace qthr = THRUST_NS_QUALIFIER;

static_assert(std::is_trivially_copyable_v<TriangulationView>);
static_assert(std::is_trivially_copyable_v<HintGridView>);
static_assert(std::is_trivially_copyable_v<KnnEntry>);

// One query on the device: where it is, its nearest site, the point it
// leaves out (external id, or kNoVertex).
struct QueryItem {
  Vec2 q;
  uint32_t root;
  uint32_t self;
};
static_assert(std::is_trivially_copyable_v<QueryItem>);

struct PrepareIds {
  TriangulationView v;
  const uint32_t* ids;
  bool exclude_self;
  QueryItem* out;
  KINETRI_HD void operator()(uint32_t i) const {
    const uint32_t in = v.int_of_ext[ids[i]];
    out[i] = {v.pos[in], v.rep[in], exclude_self ? ids[i] : kNoVertex};
  }
};

struct PreparePositions {
  TriangulationView v;
  HintGridView hints;
  const Vec2* qs;
  QueryItem* out;
  KINETRI_HD void operator()(uint32_t i) const {
    out[i] = {qs[i], WalkToNearestSite(v, qs[i], hints.Hint(qs[i])), kNoVertex};
  }
};

// k-NN rows into k slots per query; counts[i] = the row's length.
struct KnnRows {
  TriangulationView v;
  const QueryItem* qs;
  uint32_t k;
  KnnEntry* slots;
  uint64_t* counts;
  KINETRI_HD void operator()(uint32_t i) const {
    const QueryItem& it = qs[i];
    counts[i] =
        KNearestSearch(v, it.q, k, it.root, it.self, slots + uint64_t{i} * k);
  }
};

// Whether the host raised the stop word. On CPU threads (a host word, read
// in nanoseconds) before a row's search and every 64 sites after, so the
// rows not begun yet when it rises end at once too. On a GPU the word is
// pinned host memory, each read a round trip across the bus: on the fourth
// lease the radius kernels took the same time whether their searches did a
// third of the work or all of it, most likely these reads, one per row
// (docs/DEVICE.md), so there it is read every 256 sites only (a row of a
// few dozen sites never reads it; the long rows cancellation is for do).
struct StopPoll {
#if THRUST_DEVICE_SYSTEM == THRUST_DEVICE_SYSTEM_CUDA
  static constexpr uint32_t kEvery = 256;
  static constexpr bool kAtFirst = false;
#else
  static constexpr uint32_t kEvery = 64;
  static constexpr bool kAtFirst = true;
#endif
  const uint32_t* word;
  uint32_t sites = 0;
  KINETRI_HD bool Stop() {
    const uint32_t s = sites++;
    return (s == 0 ? kAtFirst : s % kEvery == 0) && LoadSystem(word) != 0;
  }
};

// Radius rows, first pass: points within r of each query, counted up to
// `cap` (max_results + 1 when rows are cut, the rest of the total limit
// + 1 when there is one). kept[i] is what the row will hold. A raised stop
// word ends the count early (the block's rows are then thrown away).
struct RadiusCounts {
  TriangulationView v;
  const QueryItem* qs;
  double r;
  uint32_t max_results;
  uint32_t cap;
  const uint32_t* stop;
  uint32_t* found;
  uint64_t* kept;
  KINETRI_HD void operator()(uint32_t i) const {
    const QueryItem& it = qs[i];
    StopPoll poll{stop};
    const uint32_t n =
        poll.Stop() ? 0
                    : CountPointsWithin(v, it.q, r, it.root, it.self, cap,
                                        [&] { return poll.Stop(); });
    found[i] = n;
    kept[i] = max_results != 0 && n > max_results ? max_results : n;
  }
};

// Radius rows, second pass: the points of each row (internal id, squared
// distance) from offsets[i]. A cut row holds the max_results first points
// (the k-NN search: every one of them lies in the disk, which holds more),
// already in order; the others come in traversal order, and `closest_first`
// sorts each in its thread (core/query_search.h's SortRow: no global sort,
// no memory). A raised stop word ends the row early (the block's rows are
// then thrown away).
struct RadiusFill {
  TriangulationView v;
  const QueryItem* qs;
  double r;
  uint32_t max_results;
  bool closest_first;
  const uint32_t* stop;
  const uint32_t* found;
  const uint64_t* offsets;
  KnnEntry* entries;
  KINETRI_HD void operator()(uint32_t i) const {
    const QueryItem& it = qs[i];
    const uint64_t b = offsets[i];
    if (max_results != 0 && found[i] > max_results) {
      KNearestSearch(v, it.q, max_results, it.root, it.self, entries + b);
      return;
    }
    uint64_t j = b;
    StopPoll poll{stop};
    bool stopped = poll.Stop();
    if (stopped) return;
    DiskSearch(v, it.q, r, it.root, [&](uint32_t s) {
      const double d2 = SquaredDistance(it.q, v.pos[s]);
      if (v.dup_next[s] != kNoVertex && v.site_member_offsets != nullptr) {
        const uint32_t end = v.site_member_offsets[s + 1];
        for (uint32_t m = v.site_member_offsets[s]; m < end; ++m) {
          const uint32_t ext = v.site_members[m];
          if (ext != it.self) entries[j++] = {v.int_of_ext[ext], d2};
        }
      } else {
        for (uint32_t p = s; p != kNoVertex; p = v.dup_next[p]) {
          if (v.ext_of_int[p] != it.self) entries[j++] = {p, d2};
        }
      }
      stopped = poll.Stop();
      return !stopped;
    });
    if (closest_first && !stopped) {
      SortRow(v, it.q, entries + b, static_cast<uint32_t>(j - b));
    }
  }
};

// Output entry j from entries[j].
struct WriteEntries {
  const uint32_t* ext_of_int;
  const KnnEntry* entries;
  uint32_t* ids;
  double* dist;  // null: no distances
  KINETRI_HD void operator()(uint64_t j) const {
    const KnnEntry& e = entries[j];
    ids[j] = ext_of_int[e.point];
    if (dist != nullptr) dist[j] = sqrt(e.d2);
  }
};

// k-NN slots to CSR entries.
struct CompactKnn {
  const uint32_t* ext_of_int;
  const KnnEntry* slots;
  uint32_t k;
  const uint64_t* offsets;
  uint32_t* ids;
  double* dist;
  KINETRI_HD void operator()(uint32_t i) const {
    const KnnEntry* row = slots + uint64_t{i} * k;
    for (uint64_t j = offsets[i]; j < offsets[i + 1]; ++j, ++row) {
      ids[j] = ext_of_int[row->point];
      dist[j] = sqrt(row->d2);
    }
  }
};

struct AllNearest {
  TriangulationView v;
  uint32_t* nn;  // by external id
  double* dist;
  KINETRI_HD void operator()(uint32_t in) const {
    const uint32_t ext = v.ext_of_int[in];
    uint32_t best;
    double d;
    if (NearestOtherPoint(v, in, &best, &d)) {
      nn[ext] = best;
      dist[ext] = d;
    } else {
      nn[ext] = kNoVertex;
      dist[ext] = 0.0;
    }
  }
};

template <typename T>
T* QRaw(qthr::device_vector<T>& v) {
  return qthr::raw_pointer_cast(v.data());
}

// to[at, at + n) = from[0, n), through the query's pinned staging.
template <typename T>
void Download(Staging& staging, qthr::device_vector<T>& from, size_t n,
              std::vector<T>* to, size_t at) {
  staging.ToHost(QRaw(from), n, to->data() + at, Stream{});
}

double SecondsSince(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0)
      .count();
}

// The queries that occupy every multiprocessor of the GPU once (its
// multiprocessors times Thrust's 512 elements per CUDA block;
// core/device/block_sizer.h), or times KINETRI_DEVICE_FILL_PER_SM queries
// where that is set (read once per process: 1024 lets two CUDA blocks share
// a multiprocessor where the registers allow); 0 on CPU threads.
size_t DeviceFill() {
#if THRUST_DEVICE_SYSTEM == THRUST_DEVICE_SYSTEM_CUDA
  static const size_t fill = [] {
    int device = 0, sms = 0;
    if (cudaGetDevice(&device) != cudaSuccess ||
        cudaDeviceGetAttribute(&sms, cudaDevAttrMultiProcessorCount, device) !=
            cudaSuccess) {
      return size_t{0};
    }
    size_t per_sm = 512;
    if (const char* e = std::getenv("KINETRI_DEVICE_FILL_PER_SM")) {
      const long v = std::strtol(e, nullptr, 10);
      if (v >= 32 && v <= (1 << 16)) per_sm = static_cast<size_t>(v);
    }
    return static_cast<size_t>(std::max(sms, 0)) * per_sm;
  }();
  return fill;
#else
  return 0;
#endif
}

// While alive, polls a cancellation token on a thread of its own (every
// millisecond; none without a token) and raises the stop word the query
// kernels read once the token fires.
class StopWatcher {
 public:
  StopWatcher(const CancelToken* cancel, uint32_t* word)
      : cancel_(cancel), word_(word) {
    StoreSystem(word_, 0);
    if (cancel_ == nullptr) return;
    try {
      thread_ = std::thread([this] { Watch(); });
    } catch (const std::system_error&) {
      // No thread to spare: cancellation is still polled between blocks.
    }
  }
  StopWatcher(const StopWatcher&) = delete;
  StopWatcher& operator=(const StopWatcher&) = delete;
  ~StopWatcher() {
    if (!thread_.joinable()) return;
    {
      std::lock_guard<std::mutex> lock(mu_);
      done_ = true;
    }
    cv_.notify_one();
    thread_.join();
  }

  // Whether the word was raised (the rows since are incomplete).
  bool stopped() const { return LoadSystem(word_) != 0; }

 private:
  void Watch() {
    std::unique_lock<std::mutex> lock(mu_);
    while (!done_) {
      if (cancel_->Cancelled()) {
        StoreSystem(word_, 1);
        return;
      }
      cv_.wait_for(lock, std::chrono::milliseconds(1));
    }
  }

  const CancelToken* cancel_;
  uint32_t* word_;
  std::mutex mu_;
  std::condition_variable cv_;
  bool done_ = false;
  std::thread thread_;
};

// Per-call device buffers, reused by later calls (a pool: no allocation
// per call once the sizes are reached).
struct Scratch {
  qthr::device_vector<QueryItem> items;
  qthr::device_vector<uint32_t> targets, found, ids;
  qthr::device_vector<Vec2> positions;
  qthr::device_vector<uint64_t> counts, offsets;
  qthr::device_vector<double> dist;
  qthr::device_vector<KnnEntry> slots, entries;
  // The stop word (host memory the device reads; StopWatcher).
  qthr::universal_host_pinned_vector<uint32_t> stop =
      qthr::universal_host_pinned_vector<uint32_t>(1, 0u);
  std::vector<uint64_t> h_offsets;
  std::vector<uint8_t> h_truncated;
  std::vector<uint32_t> h_found;
  Staging staging;  // the answers' downloads
  uint64_t bytes() const {
    return items.capacity() * sizeof(QueryItem) +
           (targets.capacity() + found.capacity() + ids.capacity()) *
               sizeof(uint32_t) +
           positions.capacity() * sizeof(Vec2) +
           (counts.capacity() + offsets.capacity()) * sizeof(uint64_t) +
           dist.capacity() * sizeof(double) +
           (slots.capacity() + entries.capacity()) * sizeof(KnnEntry);
  }
};

// The device copy of a query view and the queries over it.
class QueryEngine {
 public:
  QueryEngine() = default;
  // The executor's fault injector (DeviceExecutor::InjectFault), asked
  // before each device call; it outlives the engine.
  void set_faults(FaultInjector* faults) { faults_ = faults; }
  QueryEngine(const QueryEngine&) = delete;
  QueryEngine& operator=(const QueryEngine&) = delete;
  ~QueryEngine() {
    if (DeviceProfileLevel() == 0) return;
    std::fprintf(stderr,
                 "[device profile] queries: %llu calls, %llu blocks, %llu "
                 "queries, %llu device algorithms, %.3f s\n",
                 static_cast<unsigned long long>(runs_.load()),
                 static_cast<unsigned long long>(blocks_.load()),
                 static_cast<unsigned long long>(queries_.load()),
                 static_cast<unsigned long long>(calls_.load()),
                 static_cast<double>(nanos_.load()) * 1e-9);
    std::fprintf(stderr,
                 "[device profile] query rows by phase: prepare %.3f s, "
                 "search and count %.3f s, radius fill %.3f s, download and "
                 "append %.3f s\n",
                 static_cast<double>(phase_nanos_[kPrepare].load()) * 1e-9,
                 static_cast<double>(phase_nanos_[kSearch].load()) * 1e-9,
                 static_cast<double>(phase_nanos_[kFill].load()) * 1e-9,
                 static_cast<double>(phase_nanos_[kDownload].load()) * 1e-9);
  }

  absl::StatusOr<NeighborLists> Run(const TriangulationView& host,
                                    uint64_t generation, const DeviceQuery& q,
                                    bool large_blocks) {
    const auto t0 = std::chrono::steady_clock::now();
    absl::StatusOr<NeighborLists> out =
        Guarded([&] { return RunQuery(host, generation, q, large_blocks); });
    const size_t count =
        q.kind == DeviceQuery::Kind::kAllNearest ? view_.num_points : q.size();
    runs_.fetch_add(1, std::memory_order_relaxed);
    queries_.fetch_add(count, std::memory_order_relaxed);
    const double seconds = SecondsSince(t0);
    nanos_.fetch_add(static_cast<uint64_t>(seconds * 1e9),
                     std::memory_order_relaxed);
    if (DeviceProfileLevel() >= 2) {
      std::fprintf(stderr, "[device profile] query: %zu queries, %.6f s%s\n",
                   count, seconds, out.ok() ? "" : " (refused)");
    }
    return out;
  }

  // Calls that hold scratch now (0 once every query has returned, however
  // it ended).
  uint32_t in_flight() const {
    std::lock_guard<std::mutex> lock(mu_);
    return leased_;
  }

  uint64_t bytes() const {
    std::lock_guard<std::mutex> lock(mu_);
    uint64_t words = 0;
    for (const auto* v : {&ext_of_int_, &int_of_ext_, &rep_, &dup_next_,
                          &sites_, &line_, &line_rank_, &adj_offsets_, &adj_,
                          &member_offsets_, &members_, &hint_cells_}) {
      words += v->capacity();
    }
    uint64_t bytes = words * sizeof(uint32_t) + pos_.capacity() * sizeof(Vec2) +
                     pool_.bytes();
    for (const Scratch* w : free_) bytes += w->bytes();  // idle ones
    return bytes;
  }

 private:
  using U32 = qthr::device_vector<uint32_t>;

  absl::StatusOr<NeighborLists> RunQuery(const TriangulationView& host,
                                         uint64_t generation,
                                         const DeviceQuery& q,
                                         bool large_blocks) {
    Refresh(host, generation);
    switch (q.kind) {
      case DeviceQuery::Kind::kAllNearest:
        return AllNearestRows();
      case DeviceQuery::Kind::kKNearest:
      case DeviceQuery::Kind::kRadius:
        return Rows(q, large_blocks);
    }
    return absl::InternalError("unknown device query kind");
  }

  // The policy of every Thrust algorithm below (temporaries from pool_);
  // each call counts one device algorithm.
  PoolPolicy P() {
    if (faults_ != nullptr) faults_->BeforeCall();
    calls_.fetch_add(1, std::memory_order_relaxed);
    return Policy(pool_, Stream{});  // the default stream
  }

  // Uploads the view when its generation changed (concurrent callers of one
  // generation wait for a single upload).
  void Refresh(const TriangulationView& h, uint64_t generation) {
    std::lock_guard<std::mutex> lock(mu_);
    if (valid_ && generation_ == generation) return;
    valid_ = false;
    const uint32_t n = h.num_points;
    auto up = [](auto& to, const auto* from, size_t count) {
      if (from == nullptr) count = 0;
      to.assign(from, from + count);
    };
    up(pos_, h.pos, n);
    up(ext_of_int_, h.ext_of_int, n);
    up(int_of_ext_, h.int_of_ext, n);
    up(rep_, h.rep, n);
    up(dup_next_, h.dup_next, n);
    up(sites_, h.sites, h.num_sites);
    const bool planar = h.planar();
    up(line_, planar ? nullptr : h.line, h.num_sites);
    up(line_rank_, planar ? nullptr : h.line_rank, n);
    up(adj_offsets_, h.adj_offsets, h.adj_offsets ? size_t{n} + 1 : 0);
    up(adj_, h.adj, h.adj_offsets ? h.adj_offsets[n] : 0);
    up(member_offsets_, h.site_member_offsets,
       h.site_member_offsets ? size_t{n} + 1 : 0);
    up(members_, h.site_members,
       h.site_member_offsets ? h.site_member_offsets[n] : 0);
    // Position queries start their walks from the coarse hint grid.
    hints_ = HintGridView{};
    hint_cells_.clear();
    if (h.num_sites > 0) {
      const HintGrid grid(h);
      hints_ = grid.view();
      up(hint_cells_, grid.cells().data(), grid.cells().size());
      hints_.cells = QRaw(hint_cells_);
    }
    TriangulationView& d = view_;
    d = h;
    d.pos = QRaw(pos_);
    d.ext_of_int = QRaw(ext_of_int_);
    d.int_of_ext = QRaw(int_of_ext_);
    d.rep = QRaw(rep_);
    d.dup_next = QRaw(dup_next_);
    d.sites = QRaw(sites_);
    // The searches read the neighbour rows, never the mesh.
    d.mesh.origin = nullptr;
    d.mesh.twin = nullptr;
    d.vertex_edge = nullptr;
    d.line = planar ? nullptr : QRaw(line_);
    d.line_rank = planar ? nullptr : QRaw(line_rank_);
    d.adj_offsets = h.adj_offsets ? QRaw(adj_offsets_) : nullptr;
    d.adj = h.adj_offsets ? QRaw(adj_) : nullptr;
    d.site_member_offsets =
        h.site_member_offsets ? QRaw(member_offsets_) : nullptr;
    d.site_members = h.site_member_offsets ? QRaw(members_) : nullptr;
    generation_ = generation;
    valid_ = true;
  }

  absl::StatusOr<NeighborLists> AllNearestRows() {
    const uint32_t n = view_.num_points;
    NeighborLists out;
    out.offsets.assign(size_t{n} + 1, 0);
    out.truncated.assign(n, 0);
    if (n == 0) return out;
    const ScratchLease lease(this);  // given back however the call ends
    Scratch* w = lease.get();
    w->ids.resize(n);
    w->dist.resize(n);
    qthr::for_each(P(), qthr::counting_iterator<uint32_t>(0),
                   qthr::counting_iterator<uint32_t>(n),
                   AllNearest{view_, QRaw(w->ids), QRaw(w->dist)});
    std::vector<uint32_t> h_nn(n);
    std::vector<double> h_dist(n);
    Download(w->staging, w->ids, n, &h_nn, 0);
    Download(w->staging, w->dist, n, &h_dist, 0);
    for (uint32_t i = 0; i < n; ++i) {
      out.offsets[i + 1] = out.offsets[i] + (h_nn[i] != kNoVertex ? 1 : 0);
    }
    out.ids.reserve(out.offsets[n]);
    out.distances.reserve(out.offsets[n]);
    for (uint32_t i = 0; i < n; ++i) {
      if (h_nn[i] == kNoVertex) continue;
      out.ids.push_back(h_nn[i]);
      out.distances.push_back(h_dist[i]);
    }
    return out;
  }

  // A call's scratch, from Acquire() until the call ends, however it ends
  // (a device error is thrown through it).
  class ScratchLease {
   public:
    explicit ScratchLease(QueryEngine* engine)
        : engine_(engine), scratch_(engine->Acquire()) {}
    ScratchLease(const ScratchLease&) = delete;
    ScratchLease& operator=(const ScratchLease&) = delete;
    ~ScratchLease() { engine_->Release(scratch_); }
    Scratch* get() const { return scratch_; }

   private:
    QueryEngine* engine_;
    Scratch* scratch_;
  };

  // Scratch for one call (from the pool, or new).
  Scratch* Acquire() {
    std::lock_guard<std::mutex> lock(mu_);
    ++leased_;
    if (!free_.empty()) {
      Scratch* s = free_.back();
      free_.pop_back();
      return s;
    }
    scratch_.push_back(std::make_unique<Scratch>());
    return scratch_.back().get();
  }
  void Release(Scratch* s) {
    // A big answer's buffers are not kept (kDeviceQueryScratchBytes).
    // The pinned staging (host memory, two chunks) stays.
    if (s->bytes() > kDeviceQueryScratchBytes) {
      Staging staging = std::move(s->staging);
      *s = Scratch{};
      s->staging = std::move(staging);
    }
    // The pool's blocks serve the blocks of one call; none is kept after
    // it (kDeviceQueryScratchBytes bounds what stays, the Scratch above).
    // (Called from ScratchLease's destructor: a device in error, which
    // frees nothing more, must not throw out of it.)
    try {
      pool_.Trim(0);
    } catch (...) {
    }
    std::lock_guard<std::mutex> lock(mu_);
    --leased_;
    free_.push_back(s);
  }

  // f(), with the exceptions of device allocations and calls (Thrust throws
  // std::bad_alloc and thrust::system_error) as statuses.
  template <typename F>
  static absl::StatusOr<NeighborLists> Guarded(F&& f) {
    try {
      return f();
    } catch (const std::bad_alloc&) {
      return absl::ResourceExhaustedError(
          "query: out of device memory for the answer");
    } catch (const std::exception& e) {
      return absl::InternalError(std::string("query: device error: ") +
                                 e.what());
    }
  }

  // k-NN and radius rows, block by block.
  absl::StatusOr<NeighborLists> Rows(const DeviceQuery& q, bool large_blocks) {
    const size_t nq = q.size();
    NeighborLists out;
    out.offsets.assign(nq + 1, 0);
    out.truncated.assign(nq, 0);
    if (nq == 0 || view_.num_sites == 0) return out;
    const ScratchLease lease(this);
    absl::Status status = RowsWith(q, large_blocks, *lease.get(), &out);
    if (!status.ok()) return status;
    return out;
  }

  absl::Status RowsWith(const DeviceQuery& q, bool large_blocks, Scratch& w,
                        NeighborLists* out) {
    const size_t nq = q.size();
    const bool knn = q.kind == DeviceQuery::Kind::kKNearest;
    const bool distances = knn || q.rows.distances;
    const uint64_t limit = q.limits.max_total_results;
    const CancelToken* cancel = q.limits.cancel;
    // k-NN slots per block stay within kMaxSlotBytes.
    const uint32_t kk =
        knn ? std::min<uint32_t>(q.k, view_.num_points) : uint32_t{0};
    const size_t max_block_memory =
        knn ? std::max<size_t>(1, kMaxSlotBytes / (sizeof(KnnEntry) * kk))
            : SIZE_MAX;
    const size_t max_block = std::min(
        max_block_memory, large_blocks ? kMaxBlockLarge : kMaxBlockSmall);
    BlockSizer blocks(max_block, /*fixed_cost_aware=*/large_blocks,
                      BlockSizer::FirstBlockFromEnvironment(), DeviceFill());
    // Only the radius kernels read the stop word (a k-NN row is short).
    StopWatcher watcher(knn ? nullptr : cancel,
                        qthr::raw_pointer_cast(w.stop.data()));
    uint64_t total = 0;
    uint64_t granted = 0;  // by q.limits.admit
    if (knn && view_.num_points > q.k) {
      // Every row holds k points: the answer is checked and admitted whole
      // before any block runs (as the host executors do).
      const uint64_t all = uint64_t{nq} * q.k;
      if (limit && all > limit) return ResultLimitError(limit);
      if (q.limits.admit) {
        const uint64_t step = QueryLimits::kAdmitStep;
        granted = (all + step - 1) / step * step;
        if (absl::Status s = q.limits.admit(granted); !s.ok()) return s;
      }
      out->ids.reserve(all);
      out->distances.reserve(all);
    }
    for (size_t begin = 0; begin < nq;) {
      if (cancel != nullptr) {
        if (absl::Status s = cancel->Check("query"); !s.ok()) return s;
      }
      const auto t0 = std::chrono::steady_clock::now();
      const uint32_t nb =
          static_cast<uint32_t>(std::min(blocks.size(), nq - begin));
      blocks_.fetch_add(1, std::memory_order_relaxed);
      PhaseClock phase(this);
      Prepare(q, begin, nb, w);
      phase.To(kSearch);
      const uint64_t remaining = limit ? limit - total : UINT64_MAX;
      uint64_t rows_total;
      uint32_t rows = nb;  // the rows of the block appended below
      if (knn) {
        rows_total = KnnBlock(kk, nb, w);
      } else {
        rows_total = RadiusCount(q, nb, remaining, w);
        if (watcher.stopped()) return cancel->Check("query");
        if (limit && rows_total > remaining) return ResultLimitError(limit);
        // The rows filled at once stay within kMaxBlockResultBytes: the
        // block ends after the last row that fits (one row at least); the
        // rows after it are counted again by the next block.
        const uint64_t fits = MaxBlockResults();
        rows = static_cast<uint32_t>(
            std::upper_bound(w.h_offsets.begin() + 1,
                             w.h_offsets.begin() + nb + 1, fits) -
            (w.h_offsets.begin() + 1));
        rows = std::max<uint32_t>(rows, 1);
        rows_total = w.h_offsets[rows];
      }
      // Admitted before the rows are filled (they are allocated there).
      if (q.limits.admit && total + rows_total > granted) {
        const uint64_t step = QueryLimits::kAdmitStep;
        granted = (total + rows_total + step - 1) / step * step;
        if (absl::Status s = q.limits.admit(granted); !s.ok()) return s;
      }
      if (!knn) {
        phase.To(kFill);
        RadiusRows(q, rows, rows_total, w);
        // Rows a raised stop word ended are incomplete.
        if (watcher.stopped()) return cancel->Check("query");
      }
      phase.To(kDownload);
      // Append the block's rows.
      for (uint32_t i = 0; i < rows; ++i) {
        out->offsets[begin + i + 1] = total + w.h_offsets[i + 1];
        out->truncated[begin + i] = w.h_truncated[i];
      }
      out->ids.resize(total + rows_total);
      Download(w.staging, w.ids, rows_total, &out->ids, total);
      if (distances) {
        out->distances.resize(total + rows_total);
        Download(w.staging, w.dist, rows_total, &out->distances, total);
      }
      total += rows_total;
      begin += rows;
      if (rows < nb) {
        blocks.CutTo(rows);
      } else {
        blocks.Done(rows, SecondsSince(t0));
      }
    }
    return absl::OkStatus();
  }

  // Queries [begin, begin + nb) of q into w.items.
  void Prepare(const DeviceQuery& q, size_t begin, uint32_t nb, Scratch& w) {
    w.items.resize(nb);
    const qthr::counting_iterator<uint32_t> first(0), last(nb);
    if (q.by_ids) {
      w.targets.resize(nb);
      w.staging.ToDevice(q.ids.data() + begin, nb, QRaw(w.targets), Stream{});
      qthr::for_each(
          P(), first, last,
          PrepareIds{view_, QRaw(w.targets), q.exclude_self, QRaw(w.items)});
    } else {
      w.positions.resize(nb);
      w.staging.ToDevice(q.positions.data() + begin, nb, QRaw(w.positions),
                         Stream{});
      qthr::for_each(
          P(), first, last,
          PreparePositions{view_, hints_, QRaw(w.positions), QRaw(w.items)});
    }
  }

  // w.counts[0..nb) -> w.offsets (exclusive scan) and w.h_offsets; returns
  // the block's total.
  uint64_t ScanCounts(uint32_t nb, Scratch& w) {
    w.counts.resize(size_t{nb} + 1);
    w.counts[nb] = 0;
    w.offsets.resize(size_t{nb} + 1);
    qthr::exclusive_scan(P(), w.counts.begin(), w.counts.end(),
                         w.offsets.begin());
    w.h_offsets.resize(size_t{nb} + 1);
    qthr::copy(w.offsets.begin(), w.offsets.end(), w.h_offsets.begin());
    return w.h_offsets[nb];
  }

  uint64_t KnnBlock(uint32_t kk, uint32_t nb, Scratch& w) {
    w.slots.resize(uint64_t{kk} * nb);
    w.counts.resize(size_t{nb} + 1);
    qthr::for_each(
        P(), qthr::counting_iterator<uint32_t>(0),
        qthr::counting_iterator<uint32_t>(nb),
        KnnRows{view_, QRaw(w.items), kk, QRaw(w.slots), QRaw(w.counts)});
    const uint64_t total = ScanCounts(nb, w);
    w.h_truncated.assign(nb, 0);
    w.ids.resize(total);
    w.dist.resize(total);
    qthr::for_each(P(), qthr::counting_iterator<uint32_t>(0),
                   qthr::counting_iterator<uint32_t>(nb),
                   CompactKnn{QRaw(ext_of_int_), QRaw(w.slots), kk,
                              QRaw(w.offsets), QRaw(w.ids), QRaw(w.dist)});
    return total;
  }

  // Counts the block's radius rows (w.found, w.offsets, w.h_offsets,
  // w.h_truncated); returns the block's total (more than `remaining`:
  // refused, and counted no further than that; short where the stop word
  // rose, which the caller checks).
  uint64_t RadiusCount(const DeviceQuery& q, uint32_t nb, uint64_t remaining,
                       Scratch& w) {
    uint64_t cap = UINT32_MAX;
    if (q.max_results != 0) cap = uint64_t{q.max_results} + 1;
    if (remaining != UINT64_MAX) cap = std::min(cap, remaining + 1);
    w.found.resize(nb);
    w.counts.resize(size_t{nb} + 1);
    qthr::for_each(
        P(), qthr::counting_iterator<uint32_t>(0),
        qthr::counting_iterator<uint32_t>(nb),
        RadiusCounts{view_, QRaw(w.items), q.radius, q.max_results,
                     static_cast<uint32_t>(std::min<uint64_t>(cap, UINT32_MAX)),
                     StopWord(w), QRaw(w.found), QRaw(w.counts)});
    const uint64_t total = ScanCounts(nb, w);
    if (total > remaining) return total;
    w.h_found.resize(nb);
    qthr::copy(w.found.begin(), w.found.end(), w.h_found.begin());
    w.h_truncated.resize(nb);
    for (uint32_t i = 0; i < nb; ++i) {
      w.h_truncated[i] = q.max_results != 0 && w.h_found[i] > q.max_results;
    }
    return total;
  }

  // Fills the first nb counted rows (`total` entries) into w.ids, w.dist.
  void RadiusRows(const DeviceQuery& q, uint32_t nb, uint64_t total,
                  Scratch& w) {
    w.entries.resize(total);
    qthr::for_each(P(), qthr::counting_iterator<uint32_t>(0),
                   qthr::counting_iterator<uint32_t>(nb),
                   RadiusFill{view_, QRaw(w.items), q.radius, q.max_results,
                              q.rows.closest_first, StopWord(w), QRaw(w.found),
                              QRaw(w.offsets), QRaw(w.entries)});
    w.ids.resize(total);
    w.dist.resize(q.rows.distances ? total : 0);
    qthr::for_each(P(), qthr::counting_iterator<uint64_t>(0),
                   qthr::counting_iterator<uint64_t>(total),
                   WriteEntries{QRaw(ext_of_int_), QRaw(w.entries), QRaw(w.ids),
                                q.rows.distances ? QRaw(w.dist) : nullptr});
  }

  static const uint32_t* StopWord(Scratch& w) {
    return qthr::raw_pointer_cast(w.stop.data());
  }

  // Largest blocks (GPUs need many queries in flight; CPU threads few);
  // core/device/block_sizer.h sizes each block.
  static constexpr size_t kMaxBlockSmall = size_t{1} << 14;
  static constexpr size_t kMaxBlockLarge = size_t{1} << 20;
  static constexpr size_t kMaxSlotBytes = size_t{64} << 20;
  // The device memory of one radius block's results (an entry, an id and a
  // distance each).
  static constexpr uint64_t kResultBytes =
      sizeof(KnnEntry) + sizeof(uint32_t) + sizeof(double);
  static constexpr uint64_t kMaxBlockResultBytes = uint64_t{256} << 20;
  // The results of one radius block: kMaxBlockResultBytes' worth, or
  // KINETRI_DEVICE_BLOCK_RESULTS (read once per process; tests cut blocks
  // with it).
  static uint64_t MaxBlockResults() {
    static const uint64_t n = [] {
      const char* v = std::getenv("KINETRI_DEVICE_BLOCK_RESULTS");
      const uint64_t given = v ? std::strtoull(v, nullptr, 10) : 0;
      return given > 0 ? given : kMaxBlockResultBytes / kResultBytes;
    }();
    return n;
  }

  // The phases of a block of rows (KINETRI_DEVICE_PROFILE prints the time
  // spent in each): its queries prepared, its rows searched (k-NN) or
  // counted (radius) and scanned, its radius rows filled, and its rows
  // downloaded and appended to the answer.
  enum Phase { kPrepare, kSearch, kFill, kDownload, kPhases };
  // Adds the time since the previous To() (or since it was made) to the
  // phase it was in; the last one ends with it. Costs nothing while the
  // profile is off.
  class PhaseClock {
   public:
    explicit PhaseClock(QueryEngine* engine) : engine_(engine) {
      if (DeviceProfileLevel() != 0) since_ = std::chrono::steady_clock::now();
    }
    ~PhaseClock() { To(kPhases); }
    void To(Phase next) {
      if (DeviceProfileLevel() == 0) return;
      const auto now = std::chrono::steady_clock::now();
      engine_->phase_nanos_[phase_].fetch_add(
          static_cast<uint64_t>(
              std::chrono::duration_cast<std::chrono::nanoseconds>(now - since_)
                  .count()),
          std::memory_order_relaxed);
      phase_ = next;
      since_ = now;
    }

   private:
    QueryEngine* engine_;
    Phase phase_ = kPrepare;
    std::chrono::steady_clock::time_point since_;
  };

  mutable std::mutex mu_;
  ScratchPool pool_;  // Thrust's temporaries of every call
  // Over the engine's life (KINETRI_DEVICE_PROFILE prints them).
  std::atomic<uint64_t> calls_{0}, runs_{0}, blocks_{0}, queries_{0}, nanos_{0};
  FaultInjector* faults_ = nullptr;
  uint32_t leased_ = 0;  // scratch out of free_ (guarded by mu_)
  std::atomic<uint64_t> phase_nanos_[kPhases] = {};
  bool valid_ = false;
  uint64_t generation_ = 0;
  TriangulationView view_;
  HintGridView hints_;
  qthr::device_vector<Vec2> pos_;
  U32 ext_of_int_, int_of_ext_, rep_, dup_next_, sites_, line_, line_rank_,
      adj_offsets_, adj_, member_offsets_, members_, hint_cells_;
  // Scratch of calls in flight and of calls done (kept for the next ones).
  std::vector<std::unique_ptr<Scratch>> scratch_;
  std::vector<Scratch*> free_;
};

}  // namespace
}  // namespace KINETRI_DEVICE_NS
}  // namespace kinetri::core::device
