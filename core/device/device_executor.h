// The device executor of the kinetic update: the round executor's schedule
// (core/kinetic.h: global rounds, atomic claims, sorted worklists) written
// once in CCCL (Thrust algorithms over functors that call the shared
// per-element rules of core/flip_rules.h) and built twice:
//   * kCuda: by nvcc, running on a GPU (core/device/cuda_backend.cu);
//   * kEmulated: by the host compiler with Thrust's TBB device system, on
//     CPU threads (core/device/emulated_backend.cc), so that every CI run
//     executes the same device source without a GPU.
// Both come from core/device/round_executor.inl; nothing here exposes
// Thrust or CUDA types. The same executor answers the queries of
// core/queries.h for its triangulation (core/device/device_queries.inl,
// the same mark-free searches of core/query_search.h on every backend).
//
// The executor owns a device copy of the mesh that lives across steps: after
// a successful attempt the device and host meshes are equal (checked by the
// mesh's content_version(), without a pass over it, unless something wrote
// to it since) and the next step uploads only positions: the entries that
// changed since the last attempt when they are at most a quarter, else all of
// them. Whoever changes the host mesh otherwise calls Invalidate() (a
// rebuild, renumbering: the next attempt uploads it again) or names what it
// changed with ChangedOnHost() (re-insertion: only those entries go up).
// Hold-back decisions, re-insertion and rebuilds stay on the host
// (Triangulation), with explicit transfers that the attempt reports.
#ifndef KINETRI_CORE_DEVICE_DEVICE_EXECUTOR_H_
#define KINETRI_CORE_DEVICE_DEVICE_EXECUTOR_H_

#include <cstdint>
#include <future>
#include <memory>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/types/span.h"
#include "core/cancel.h"
#include "core/kinetic.h"
#include "core/mesh.h"
#include "core/query_types.h"
#include "core/triangulation_view.h"
#include "core/vec2.h"

namespace kinetri::core::device {

enum class DeviceBackend {
  kEmulated,  // Thrust's TBB device system on CPU threads (tests, CI)
  kCuda,      // nvcc build on a GPU
};
const char* DeviceBackendName(DeviceBackend backend);

// One attempt to move every vertex to `to` (see DeviceExecutor::Attempt).
struct DeviceAttempt {
  bool tangled = false;  // dense attempt with too many inverted triangles
  bool fixed = false;    // the mesh is now Delaunay for `to` (downloaded)
  bool cancelled = false;
  FlipCounts counts;  // fixing and legalizing flips (when fixed)
  // When not fixed: the corners of the triangles that fixing could not
  // repair, three per triangle (kNoVertex for the infinite vertex).
  std::vector<uint32_t> stuck_corners;
  // Hold-back (Attempt with `from`): the vertices fixing held back at their
  // old positions, in the order the host's round executor holds them
  // (KineticExecutor::Fix). Filled whether or not the attempt fixed.
  std::vector<uint32_t> held;
  double fix_seconds = 0.0;
  double legalize_seconds = 0.0;
  double transfer_seconds = 0.0;  // uploads and downloads
  uint64_t bytes_uploaded = 0;
  uint64_t bytes_downloaded = 0;
  // Device algorithms (Thrust calls, each a launch or more) the attempt
  // ran, and how many of them the host waited for (it reads their result,
  // a worklist's size or the flip counts; on the CUDA backend the others
  // return at once, the TBB one runs every call to its end): with the
  // seconds above, the cost of one on the backend.
  uint64_t device_calls = 0;
  uint64_t host_waits = 0;
  // Legalizing rounds the device ran in its own loop (LoopControl), and how
  // often such a loop handed a worklist that outgrew its capacity back to
  // the host.
  uint32_t loop_rounds = 0;
  uint32_t loop_returns = 0;
  // 1 when the fixed mesh came down as the half-edges and vertex_edge
  // entries it changed, not as the whole arrays.
  uint32_t patched_downloads = 0;
  // 1 when the host's changes since the last attempt went up alone (the
  // entries DeviceExecutor::ChangedOnHost named), not the whole mesh.
  uint32_t patched_uploads = 0;
  // 1 when the host mesh was not the copy the device kept (a caller that
  // changed it without Invalidate(), which is a bug: the executor found it
  // by the mesh's fingerprint and uploaded the mesh again, so the attempt
  // is still exact), or when, with KINETRI_DEVICE_CHECK=1, the caller wrote
  // a position that PositionsWrittenAt did not name or a mesh entry that
  // ChangedOnHost did not name (found by the whole comparison or the
  // fingerprint, and sent).
  uint32_t resyncs = 0;
  // 1 when the attempt checked the host mesh by a pass over it
  // (Mesh::Fingerprint): its first attempt, after Invalidate() or a change
  // of the mesh's shape, or after a change of its content_version() with no
  // ChangedOnHost names pending or with names it could not use (more than
  // a patch holds, out of range); named changes are checked so only with
  // KINETRI_DEVICE_CHECK=1. 0 when the host mesh is known to be the
  // device's copy (nothing wrote to it since) or its changes were named.
  uint32_t fingerprint_passes = 0;
};

// How the device executor runs the tail of legalizing, where rounds are
// many and small (the worklist shrinks from every edge to a few hundred
// over about 170 rounds at σ 0.1). Once a worklist holds at most
// `capacity` edges the device runs whole rounds on its own: every
// algorithm is launched over `capacity` elements and reads the worklist's
// size from device memory, the next worklist is appended and deduplicated
// on the device, and a one-element step decides whether the loop goes on.
// The host enqueues `rounds_per_check` rounds, then reads one word (done,
// still running, or the worklist outgrew the capacity: the host takes it
// back); rounds enqueued after the end do nothing. The rounds and their
// results are those of the host-driven rounds (the same candidates, claims
// and winners), so the mesh does not depend on these settings.
// capacity 0: the host drives every round (two waits per round).
struct LoopControl {
  uint32_t capacity = 0;
  uint32_t rounds_per_check = 8;
};
// The defaults: 65536 edges and a check every 8 rounds on a GPU (not yet
// measured on one); 1024 and every 8 on CPU threads, where a call costs the
// same whether the host waits or not, so the loop saves nothing there
// (100K points: the same step time as capacity 0 within the noise; 4096
// cost 5-10 %), but every test run goes through both paths.
LoopControl DefaultLoopControl(DeviceBackend backend);

// One batch of queries for the device executor. Its arguments are already
// checked (core/queries.cc checks them once for every executor).
struct DeviceQuery {
  enum class Kind { kAllNearest, kKNearest, kRadius };
  Kind kind = Kind::kKNearest;
  // Point queries (ids) or position queries (positions).
  bool by_ids = false;
  absl::Span<const uint32_t> ids;
  absl::Span<const Vec2> positions;
  bool exclude_self = false;
  uint32_t k = 0;            // kKNearest
  double radius = 0.0;       // kRadius
  uint32_t max_results = 0;  // kRadius: per-row cut (0: none)
  RowOptions rows;
  QueryLimits limits;
  size_t size() const { return by_ids ? ids.size() : positions.size(); }
};

// A device failure on demand (DeviceExecutor::InjectFault, for tests): the
// device algorithm `after_calls` calls from now (every algorithm of the
// executor's attempts and queries counts; 0 is the next one) fails as a
// failing CUDA system makes it fail: exhausted memory (std::bad_alloc) or
// an error (a thrown std::runtime_error, as thrust::system_error is).
struct DeviceFault {
  enum class Kind { kNone, kOutOfMemory, kError };
  Kind kind = Kind::kNone;
  uint64_t after_calls = 0;
};

// A stream of the caller's (a cudaStream_t on the CUDA backend) for the
// _async forms below, or null. Ignored by the emulated backend, whose
// algorithms run to their end on CPU threads.
struct DeviceStream {
  void* cuda_stream = nullptr;
};

class DeviceExecutor {
 public:
  virtual ~DeviceExecutor() = default;
  virtual DeviceBackend backend() const = 0;

  // The host mesh changed outside Attempt(): upload it before the next one.
  virtual void Invalidate() = 0;
  // The host changed only these triangles' half-edges (origin, twin) and
  // these vertices' vertex_edge entries since the mesh was last the
  // device's copy (the calls add up until the next attempt; repeats are
  // allowed): the next attempt sends only them, without a pass over the
  // host mesh. The lists are a promise, as PositionsWrittenAt's are: a
  // change left out, or the next attempt made on another mesh (without
  // Invalidate()), leaves the device's copy wrong. With
  // KINETRI_DEVICE_CHECK=1 (core/device/checks.h, the test suites) the
  // attempt checks by the mesh's fingerprint that nothing else changed,
  // and a change left out costs an upload of the whole mesh
  // (DeviceAttempt::resyncs). More changes than an eighth of the mesh's
  // entries: the whole mesh goes up. After Invalidate(), until the next
  // attempt, it does nothing.
  virtual void ChangedOnHost(absl::Span<const uint32_t> triangles,
                             absl::Span<const uint32_t> vertices) = 0;
  // Before an attempt: since the previous attempt, the caller wrote its
  // `to` array only at the entries `to` and its `from` array only at the
  // entries `from` (the calls add up until the next attempt to run, which
  // for the _async forms is the next to take the executor's lock; repeats, and
  // entries written with their old values, are allowed). The next attempt
  // then looks for the positions to send among these entries alone (at 1M
  // points a sparse attempt otherwise passes over both arrays on the host,
  // about 32 MB each). An attempt without such a call before it compares
  // the whole arrays, and so does one after a device failure or whose
  // arrays have another size than the previous attempt's. The lists are a
  // promise: a written entry left out is not sent, and so is a position of
  // another array of the same size (the caller that passes `to` or `from`
  // arrays other than the previous attempt's makes no call). With
  // KINETRI_DEVICE_CHECK=1 (core/device/checks.h, the test suites) each
  // promise is checked by the whole comparison, and a broken one is
  // repaired and counted in DeviceAttempt::resyncs.
  virtual void PositionsWrittenAt(absl::Span<const uint32_t> to,
                                  absl::Span<const uint32_t> from) = 0;

  // Moves to `to` on the device: finds the invalid triangles (all of them,
  // or among `candidates` when non-null), repairs them by fixing rounds
  // (core/flip_rules.h proposals, claims by smallest edge id), checks that
  // the hull winds once, then legalizes (every edge, or the edges of
  // `seeds` plus the triangles fixing touched when seeds is non-null). On
  // success the mesh is downloaded into `mesh` (origin, twin, vertex_edge,
  // the latter kept as the host's round executor keeps it, so both give the
  // same mesh down to the numbering). On failure `mesh`
  // is untouched (it is still valid for the old positions). A dense attempt
  // with more than `rebuild_fraction` of the triangles inverted stops at
  // once (tangled). `cancel` is polled every round.
  //
  // `from` (empty, or the positions `mesh` is Delaunay for): a fixing round
  // that finds no flip holds back the culprits of the triangles left
  // (rules::Culprits) at their `from` positions and fixing goes on, as the
  // host's round executor does with KineticExecutor::HoldBack; the held
  // vertices come back in DeviceAttempt::held (the mesh is then Delaunay for
  // `to` with those entries replaced by `from`'s). Empty: the attempt ends
  // stuck there.
  virtual absl::StatusOr<DeviceAttempt> Attempt(
      Mesh& mesh, absl::Span<const Vec2> to, absl::Span<const Vec2> from,
      const std::vector<uint32_t>* candidates,
      const std::vector<uint32_t>* seeds, double rebuild_fraction,
      const CancelToken* cancel) = 0;

  // Answers `query` on the device from its copy of the query view `host`
  // (positions, numbering, neighbour rows, site members, and the hint grid
  // of position queries). The copy is uploaded when `generation` differs
  // from the one it holds (the owner passes its step count: the view
  // changes only with a step) and kept until then. Answers, row order,
  // truncation flags and refusals are those of core/queries.h. Queries run
  // in blocks whose size adapts to keep each block near 10 ms; `cancel` is
  // polled and the total limit checked between blocks (a row is counted
  // before it is filled, so a refused query costs about the limit).
  // Concurrent calls with the same generation are safe.
  virtual absl::StatusOr<NeighborLists> Query(const TriangulationView& host,
                                              uint64_t generation,
                                              const DeviceQuery& query) = 0;

  // The _async forms, as cuCollections' *_async members: they return at
  // once, and the work runs on a host thread of its own that drives the
  // device (rounds and query blocks are decided by the host). Its device
  // work begins after the work the caller had queued on `stream` when it
  // called (null: no such order). The caller keeps every argument (`mesh`,
  // `to`, the vectors, the token, the view and the query's spans) alive and
  // unchanged, and reads `mesh` only, once the future is ready. Destroying
  // the future waits for the work (it is std::async's). Attempts of one
  // executor run one at a time, in the order they got its lock (a second
  // one waits for the first); queries as Query(). Errors come back in the
  // future's value, never as exceptions. The executor outlives its futures.
  // It keeps one mesh on the device (the one its last attempt left): to
  // step another mesh with it, call Invalidate() first.
  virtual std::future<absl::StatusOr<DeviceAttempt>> AttemptAsync(
      Mesh& mesh, absl::Span<const Vec2> to, absl::Span<const Vec2> from,
      const std::vector<uint32_t>* candidates,
      const std::vector<uint32_t>* seeds, double rebuild_fraction,
      const CancelToken* cancel, DeviceStream stream) = 0;
  virtual std::future<absl::StatusOr<NeighborLists>> QueryAsync(
      const TriangulationView& host, uint64_t generation,
      const DeviceQuery& query, DeviceStream stream) = 0;

  // Device memory held across steps (mesh, positions, claims, scratch, the
  // query view).
  virtual uint64_t device_bytes() const = 0;
  // Host memory held across steps beside the host mesh: the mirrors of the
  // device's positions, the arrays the next mesh download goes into, the
  // changes on their way up and down, the pinned staging.
  virtual uint64_t host_bytes() const = 0;

  // The device loop's settings (LoopControl); they apply from the next
  // attempt. rounds_per_check 0 is taken as 1.
  virtual void set_loop_control(const LoopControl& control) = 0;
  virtual LoopControl loop_control() const = 0;

  // Testing the error path: arms one device failure (DeviceFault; kNone
  // disarms). It fires once, inside whatever attempt or query makes the
  // armed call, which then ends as a device error ends: an attempt with
  // RESOURCE_EXHAUSTED or INTERNAL, the host mesh untouched and the device
  // state forgotten (the next attempt uploads the mesh again); a query with
  // the same codes (its view is uploaded again by the next one).
  // fault_armed() says whether it has not fired yet.
  virtual void InjectFault(const DeviceFault& fault) = 0;
  virtual bool fault_armed() const = 0;

  // Queries running now (each holds scratch device memory until it
  // returns, however it ends).
  virtual uint32_t queries_in_flight() const = 0;
};

// Upper bound of the memory the device executor holds per point of a
// session once it has stepped (mesh, positions, claims, scratch; checked by
// tests/core/device_executor_test.cc). Used for admission before anything
// is allocated.
inline constexpr uint64_t kDeviceBytesPerPoint = 256;
// Upper bound of the host memory the device executor holds per point
// beside the host mesh (host_bytes(): two position mirrors, 32 bytes; the
// download arrays, ~52; the largest patch and change lists, ~16; the
// lists of written positions, a quarter of the points each, at most 4:
// about 104, each array kept within a quarter over its size), plus
// DeviceHostFixedBytes of staging (pinned on CUDA); checked with the
// above. The server admits a device session's host memory with them.
inline constexpr uint64_t kDeviceHostBytesPerPoint = 128;
inline constexpr uint64_t kCudaHostFixedBytes = uint64_t{8} << 20;
inline constexpr uint64_t kEmulatedHostFixedBytes = uint64_t{64} << 10;
inline constexpr uint64_t DeviceHostFixedBytes(DeviceBackend backend) {
  return backend == DeviceBackend::kCuda ? kCudaHostFixedBytes
                                         : kEmulatedHostFixedBytes;
}
// Query scratch kept between queries, per query running at once (larger
// buffers are freed when their query ends). Checked with the above.
inline constexpr uint64_t kDeviceQueryScratchBytes = uint64_t{8} << 20;

// Whether this build has the backend, and (kCuda) a GPU to run it.
bool DeviceBackendAvailable(DeviceBackend backend);

// Free memory on the backend's device (UINT64_MAX for the emulated backend,
// whose memory is the host's and is budgeted with it).
uint64_t DeviceFreeBytes(DeviceBackend backend);

// A new executor on `backend`; FAILED_PRECONDITION when it is unavailable.
absl::StatusOr<std::unique_ptr<DeviceExecutor>> MakeDeviceExecutor(
    DeviceBackend backend);

// The CUDA build registers itself (kinetri::device_cuda calls this from
// RegisterCudaBackend()); the emulated backend is built into the core when
// the CCCL headers exist.
using DeviceExecutorFactory = std::unique_ptr<DeviceExecutor> (*)();
void RegisterDeviceBackend(DeviceBackend backend, DeviceExecutorFactory make,
                           bool (*available)(), uint64_t (*free_bytes)());

}  // namespace kinetri::core::device

#endif  // KINETRI_CORE_DEVICE_DEVICE_EXECUTOR_H_
