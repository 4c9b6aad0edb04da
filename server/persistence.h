// Durable sessions (--data_dir): a snapshot per session plus an append-only
// journal of the steps since, the way Redis keeps RDB + AOF.
//
// Layout: DIR/sessions/<tenant>@<id>/{snapshot,journal} (tenant empty
// without authentication). Both files are sequences of checksummed
// records (CRC-32, zlib): a record that does not check is never loaded.
//   * snapshot: the session's metadata and the positions of every point at
//     one step; written to snapshot.tmp, fsynced, renamed over the old one
//     (the directory fsynced too), so a crash leaves the old or the new one.
//   * journal: one record per step (its number and batch: moves, points
//     that leave and join, the joining points' client ids) appended before
//     the step is applied; a step that then fails (cancelled, bad values)
//     gets an abort record. --fsync=always syncs before the step is
//     acknowledged, everysec once a second (a background thread), no never.
//   * compaction: when the journal outgrows the snapshot (or every
//     --snapshot_interval_steps), a new snapshot is written and the journal
//     restarts empty.
// Restore (server start, before SERVING): each session's snapshot, then
// its journal replayed; a truncated or corrupt journal tail is cut at the
// last valid record (reported); a snapshot that does not check makes that
// one session unavailable (DATA_LOSS on access) until it is deleted.
#ifndef KINETRI_SERVER_PERSISTENCE_H_
#define KINETRI_SERVER_PERSISTENCE_H_

#include <atomic>
#include <cstdint>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "absl/container/flat_hash_map.h"
#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "absl/time/time.h"
#include "core/triangulation.h"

namespace kinetri::server {

enum class FsyncPolicy { kAlways, kEverySecond, kNo };
absl::StatusOr<FsyncPolicy> ParseFsyncPolicy(const std::string& s);

// What a snapshot holds besides the positions.
struct SessionMeta {
  std::string id;
  std::string tenant;
  std::string backend;
  uint64_t max_query_results = 0;
  uint32_t threads = 0;
  uint64_t idle_ttl_seconds = 0;
  uint64_t step = 0;
  absl::Time create_time;
  std::vector<uint64_t> client_ids;
  // POINT_ID_POLICY_CLIENT (client_ids is empty when no point is left).
  bool client_id_policy = false;
};

class SessionStore;

// One session's journal (owned by its Session).
class Journal {
 public:
  ~Journal();
  // Appends step `step` (before it is applied) with the client ids of its
  // joining points (POINT_ID_POLICY_CLIENT); with kAlways also syncs.
  absl::Status Append(uint64_t step, const core::DisplacementBatch& batch,
                      const std::vector<uint64_t>& added_client_ids = {});
  // The step appended last was not applied.
  absl::Status Abort(uint64_t step);
  // Counts an applied step; true when the journal has grown past the
  // compaction threshold.
  bool CompactionDue();
  // Writes a snapshot of `tri` at `meta.step`, then empties the journal.
  absl::Status Compact(const SessionMeta& meta, const core::Triangulation& tri);
  // Records written since the last snapshot (a checkpoint would shorten
  // the next restore).
  bool has_records() const { return size_ > 0; }
  // Syncs the journal file (everysec's background thread).
  void Sync();
  // A write failed after a step was journaled: the files may no longer
  // match the session, so further steps are refused.
  bool broken() const { return broken_.load(); }
  // The session was deleted: nothing is written any more.
  void Close() { closed_ = true; }
  const std::string& dir() const { return dir_; }

 private:
  friend class SessionStore;
  Journal(SessionStore* store, std::string dir, int fd, uint64_t size,
          uint64_t snapshot_bytes, FsyncPolicy fsync, uint64_t interval_steps);
  absl::Status Write(uint32_t type, const std::string& payload);

  SessionStore* const store_;
  const std::string dir_;
  int fd_;
  uint64_t size_;
  uint64_t snapshot_bytes_;
  const FsyncPolicy fsync_;
  const uint64_t interval_steps_;
  uint64_t steps_since_snapshot_ = 0;
  std::atomic<bool> dirty_{false};
  std::atomic<bool> broken_{false};
  std::atomic<bool> closed_{false};
  absl::Mutex sync_mu_;  // Sync() against compaction's truncation
};

// A session read back from disk.
struct RestoredSession {
  SessionMeta meta;
  std::vector<core::Vec2> positions;  // at meta.step
  struct Step {
    uint64_t step;
    core::DisplacementBatch batch;
    std::vector<uint64_t> added_client_ids;
  };
  std::vector<Step> steps;  // journaled after the snapshot, in order
  uint64_t cut_bytes = 0;   // corrupt or truncated journal tail removed
};

class SessionStore {
 public:
  // interval_steps: snapshot every that many steps (0: when the journal
  // outgrows 4x the snapshot).
  static absl::StatusOr<std::unique_ptr<SessionStore>> Open(
      const std::string& dir, FsyncPolicy fsync, uint64_t interval_steps);
  ~SessionStore();

  // Writes the first snapshot of a new session and opens its journal.
  absl::StatusOr<std::unique_ptr<Journal>> Create(
      const SessionMeta& meta, const core::Triangulation& tri);
  // Removes a session's files.
  absl::Status Remove(const std::string& tenant, const std::string& id);

  // Every session on disk; `broken` receives the ones whose snapshot does
  // not check (key "tenant@id" -> why). Journal tails that do not check
  // are cut here.
  std::vector<RestoredSession> LoadAll(
      absl::flat_hash_map<std::string, std::string>* broken);
  // Opens the journal of a restored session (after its replay).
  absl::StatusOr<std::unique_ptr<Journal>> Reopen(
      const SessionMeta& meta, const core::Triangulation& tri);

  static std::string Key(const std::string& tenant, const std::string& id) {
    return tenant + "@" + id;
  }
  FsyncPolicy fsync() const { return fsync_; }

  // everysec: journals register for the background sync.
  void Track(Journal* j);
  void Untrack(Journal* j);

 private:
  SessionStore(std::string dir, FsyncPolicy fsync, uint64_t interval_steps);
  std::string SessionDir(const std::string& tenant,
                         const std::string& id) const;
  absl::StatusOr<std::unique_ptr<Journal>> OpenJournal(const std::string& dir,
                                                       uint64_t snapshot_bytes,
                                                       bool truncate);

  const std::string dir_;
  const FsyncPolicy fsync_;
  const uint64_t interval_steps_;
  absl::Mutex mu_;
  std::vector<Journal*> tracked_ ABSL_GUARDED_BY(mu_);
  std::atomic<bool> stop_{false};
  std::thread syncer_;
};

// Writes the snapshot file of a session in `dir` (atomic rename); returns
// its size.
absl::StatusOr<uint64_t> WriteSnapshot(const std::string& dir,
                                       const SessionMeta& meta,
                                       const core::Triangulation& tri);

}  // namespace kinetri::server

#endif  // KINETRI_SERVER_PERSISTENCE_H_
