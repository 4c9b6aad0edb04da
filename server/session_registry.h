// Sessions (one triangulation each) and the registry that owns them.
#ifndef KINETRI_SERVER_SESSION_REGISTRY_H_
#define KINETRI_SERVER_SESSION_REGISTRY_H_

#include <atomic>
#include <cstdint>
#include <deque>
#include <functional>
#include <map>
#include <memory>
#include <string>
#include <string_view>
#include <vector>

#include "absl/container/flat_hash_map.h"
#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "absl/time/time.h"
#include "core/cancel.h"
#include "core/triangulation.h"
#include "server/auth.h"
#include "server/memory_budget.h"
#include "server/persistence.h"
#include "server/point_id_map.h"

namespace kinetri::server {

struct ServerLimits {
  uint32_t max_sessions = 64;
  uint64_t max_points_per_session = 50'000'000;
  uint64_t max_query_results = 200'000'000;
  int default_threads = 0;
  // Most worker threads a session may ask for (SessionOptions.threads).
  uint32_t max_threads = 256;
  // Idle expiry of sessions that do not set their own (0: never).
  uint64_t default_idle_ttl_seconds = 0;
  // The device executor sessions with BACKEND_AUTO / BACKEND_CUDA get
  // (--device); none: every session runs on the CPU.
  bool has_device = false;
  core::device::DeviceBackend device = core::device::DeviceBackend::kCuda;
};

// One session: its triangulation, step counter and metadata.
//
// Readers (queries, export, describe) take an immutable snapshot of the
// current step and hold no lock while they compute or stream: a step never
// waits for them. A step (one at a time) moves the triangulation in place
// when no reader holds it (readers arriving meanwhile wait for the step),
// else a copy, published when it is done (read-copy-update); readers keep
// their snapshot until they finish.
class Session {
 public:
  // client_ids: null for sequential ids (POINT_ID_POLICY_CLIENT: the id of
  // each point).
  // `memory` (kept for the session's life) is its share of the server's
  // budget; `budget` (optional) is asked for the copies steps make.
  Session(std::string id, core::Triangulation tri, std::string backend,
          uint64_t max_query_results, uint32_t threads,
          std::shared_ptr<const PointIdMap> client_ids = nullptr,
          MemoryBudget::Reservation memory = {},
          MemoryBudget* budget = nullptr);

  const std::string& id() const { return id_; }
  // The tenant that owns it ("" without authentication); set before Add.
  const std::string& tenant() const { return tenant_; }
  void set_tenant(std::string tenant) { tenant_ = std::move(tenant); }
  std::string name() const { return "sessions/" + id_; }
  const std::string& backend() const { return backend_; }
  uint64_t max_query_results() const { return max_query_results_; }
  uint32_t threads() const { return threads_; }
  absl::Time create_time() const { return create_time_; }
  // Points at the current step (points join and leave with steps).
  uint64_t point_count() const { return point_count_.load(); }

  // POINT_ID_POLICY_CLIENT: points are named by the client's ids (the map
  // of each step comes with its Snapshot).
  bool has_client_ids() const { return client_policy_; }

  // Growth (points that join beyond those that leave) is admitted up to
  // `max_points` and by `check` (the tenant's quota), and reserved from the
  // memory budget; set before the session takes steps.
  void set_growth_limits(uint64_t max_points,
                         std::function<absl::Status(uint64_t)> check) {
    max_points_ = max_points;
    growth_check_ = std::move(check);
  }

  // Idle expiry (0: never). Touch() marks an access.
  void set_idle_ttl(uint64_t seconds) { idle_ttl_seconds_ = seconds; }
  uint64_t idle_ttl_seconds() const { return idle_ttl_seconds_; }
  void Touch() { last_access_ns_ = absl::GetCurrentTimeNanos(); }
  // absl::InfiniteFuture() without a TTL.
  absl::Time ExpireTime() const {
    if (idle_ttl_seconds_ == 0) return absl::InfiniteFuture();
    return absl::FromUnixNanos(last_access_ns_.load()) +
           absl::Seconds(static_cast<int64_t>(idle_ttl_seconds_));
  }

  // Durable sessions (--data_dir): steps are journaled before they apply.
  void AttachJournal(std::unique_ptr<Journal> journal) {
    journal_ = std::move(journal);
  }
  Journal* journal() const { return journal_.get(); }
  // Durable sessions: writes a snapshot of the current step and empties the
  // journal (the drain at shutdown does it, so that a restart restores
  // without replaying). Waits for a running step; false when there was
  // nothing to write.
  absl::StatusOr<bool> Checkpoint();
  // Restored sessions start at their last durable step.
  void RestoreStep(uint64_t step, absl::Time create_time);
  // What a snapshot of this session at `step` records.
  SessionMeta Meta(uint64_t step) const;

  struct Snapshot {
    std::shared_ptr<const core::Triangulation> tri;
    uint64_t step = 0;
    absl::Time update_time;
    // POINT_ID_POLICY_CLIENT: the client ids of this step's points.
    std::shared_ptr<const PointIdMap> ids;
  };
  // The current step, immutable for as long as the caller holds it.
  Snapshot Read() const;

  // Applies `batch` as step number `step` (FAILED_PRECONDITION unless it is
  // the next one). POINT_ID_POLICY_CLIENT sessions name the points of the
  // step in `client_ids` (resolved here, against the ids of the step
  // before; batch.ids and batch.remove are then filled from them). On any
  // error, cancellation included, the session stays at its previous step.
  // `copied` (optional): the step moved a copy because readers held the current
  // step. When the memory budget has no room for a copy, the step waits for the
  // readers instead (new readers wait behind it).
  //
  // `request_id` (optional) names the step: a step already applied under
  // the same number and request_id (among the last kRememberedSteps) is
  // not applied again; its original report is returned and `*replayed`
  // (optional) is set.
  absl::StatusOr<core::StepReport> ApplyStep(uint64_t step,
                                             core::DisplacementBatch batch,
                                             const StepClientIds* client_ids,
                                             const core::CancelToken* cancel,
                                             bool* copied = nullptr,
                                             const std::string& request_id = "",
                                             bool* replayed = nullptr);
  static constexpr size_t kRememberedSteps = 64;
  ~Session();

 private:
  // Declared first, destroyed last: once the triangulation's memory is
  // freed, give the freed pages back to the system (glibc keeps large
  // freed blocks in its heap otherwise, and a deleted 1M-point session
  // returned nothing to the OS).
  struct ReturnMemoryOnDestroy {
    ~ReturnMemoryOnDestroy();
  } return_memory_;
  // Set when the session is destroyed: the last holder of one of its
  // triangulations (a reader may outlive the session) then gives the freed
  // pages back too.
  std::shared_ptr<std::atomic<bool>> retired_ =
      std::make_shared<std::atomic<bool>>(false);
  std::shared_ptr<core::Triangulation> Share(core::Triangulation tri) const;
  const std::string id_;
  const std::string backend_;
  std::string tenant_;
  const uint64_t max_query_results_;
  const uint32_t threads_;
  absl::Time create_time_;
  std::atomic<uint64_t> point_count_;
  const bool client_policy_;
  uint64_t max_points_ = UINT64_MAX;
  std::function<absl::Status(uint64_t)> growth_check_;

  MemoryBudget::Reservation memory_;
  // Reserved for points that joined beyond the creation's count.
  std::vector<MemoryBudget::Reservation> growth_memory_;
  MemoryBudget* const budget_;
  std::unique_ptr<Journal> journal_;
  uint64_t idle_ttl_seconds_ = 0;
  std::atomic<int64_t> last_access_ns_{absl::GetCurrentTimeNanos()};
  absl::Mutex write_mu_;  // one step at a time
  mutable absl::Mutex mu_;
  std::shared_ptr<core::Triangulation> current_ ABSL_GUARDED_BY(mu_);
  std::shared_ptr<const PointIdMap> ids_ ABSL_GUARDED_BY(mu_);
  bool in_place_ ABSL_GUARDED_BY(mu_) = false;  // a step moves current_
  uint64_t step_ ABSL_GUARDED_BY(mu_) = 0;
  // The last kRememberedSteps steps applied with a request_id.
  struct Applied {
    uint64_t step;
    std::string request_id;
    core::StepReport report;
  };
  std::deque<Applied> applied_ ABSL_GUARDED_BY(mu_);
  absl::Time update_time_ ABSL_GUARDED_BY(mu_);
};

class SessionRegistry {
 public:
  explicit SessionRegistry(ServerLimits limits) : limits_(limits) {}

  const ServerLimits& limits() const { return limits_; }

  // Sessions are keyed by (tenant, id): a tenant sees and finds only its
  // own (another tenant's session is NOT_FOUND, as if it did not exist).
  // Adds a session for its tenant; ALREADY_EXISTS / RESOURCE_EXHAUSTED on
  // conflict (server limits, then the tenant's own).
  absl::StatusOr<std::shared_ptr<Session>> Add(std::shared_ptr<Session> s,
                                               const Tenant& tenant = {});
  // Checks that one more session of `points` on `backend` ("cpu",
  // "emulated", "cuda") would fit (before building it).
  absl::Status CheckCapacity(uint64_t points, std::string_view backend = "cpu",
                             const Tenant& tenant = {}) const;
  // Checks that the tenant's sessions may hold `points` more points (in a
  // session on `backend`).
  absl::Status CheckGrowth(uint64_t points, std::string_view backend,
                           const Tenant& tenant) const;
  // NOT_FOUND (naming the session) if absent; name is "sessions/{id}".
  absl::StatusOr<std::shared_ptr<Session>> Get(
      const std::string& name, const std::string& tenant = "") const;
  absl::Status Remove(const std::string& name, const std::string& tenant = "");
  // The tenant's sessions with id > after, ascending, at most `limit`.
  std::vector<std::shared_ptr<Session>> List(
      const std::string& after, size_t limit,
      const std::string& tenant = "") const;
  // A fresh session id: "s-" and 128 random bits in hex (unguessable).
  std::string NewId() const;
  // Every session of every tenant.
  std::vector<std::shared_ptr<Session>> All() const;
  // Removes exactly this session (if it is still registered).
  bool RemoveSession(const std::shared_ptr<Session>& s);
  size_t size() const;
  uint64_t total_points() const;

 private:
  const ServerLimits limits_;
  mutable absl::Mutex mu_;
  // `points` more for the tenant, on `backend` (in a new session unless
  // !new_session); its memory by the budget's estimate of each session's
  // backend.
  absl::Status CheckTenantLocked(uint64_t points, std::string_view backend,
                                 const Tenant& tenant,
                                 bool new_session = true) const
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  // Key: "tenant/id" ("id" for the unnamed tenant); tenant names and ids
  // contain no '/'.
  std::map<std::string, std::shared_ptr<Session>> sessions_
      ABSL_GUARDED_BY(mu_);
};

// "sessions/{id}" -> id, or INVALID_ARGUMENT naming `field`.
absl::StatusOr<std::string> ParseSessionName(const std::string& name,
                                             const std::string& field);
// A client's string as shown in an error message: escaped and cut to 80
// bytes (a huge echo would turn the status itself into an oversized
// trailer, and the client would see a metadata error instead).
std::string EchoForError(const std::string& value);
// Session ids: [a-z0-9-]{1,63}.
bool ValidSessionId(const std::string& id);
// ListSessions paging tokens: opaque to clients (web-safe base64 of a
// versioned position), INVALID_ARGUMENT for anything not made here.
std::string EncodePageToken(const std::string& after_id);
absl::StatusOr<std::string> DecodePageToken(const std::string& token);

}  // namespace kinetri::server

#endif  // KINETRI_SERVER_SESSION_REGISTRY_H_
