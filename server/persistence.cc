// Durable sessions: snapshots and journals (see persistence.h).
#include "server/persistence.h"

#include <dirent.h>
#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>
#include <zlib.h>

#include <cerrno>
#include <cstring>
#include <fstream>
#include <sstream>

#include "absl/strings/str_cat.h"

namespace kinetri::server {
namespace {

constexpr uint32_t kMagic = 0x52544E4B;  // "KNTR"
constexpr uint32_t kSnapshotRecord = 1;
constexpr uint32_t kStepRecord = 2;
constexpr uint32_t kAbortRecord = 3;
// 2: the client-id policy is recorded (version 1 implied it from the ids).
constexpr uint32_t kSnapshotVersion = 2;
constexpr size_t kHeader = 4 + 4 + 8 + 4;

// Little-endian encoding (the x86-64 and arm64 hosts we run on).
template <typename T>
void Put(std::string* out, T v) {
  out->append(reinterpret_cast<const char*>(&v), sizeof(T));
}
void PutString(std::string* out, const std::string& s) {
  Put<uint32_t>(out, static_cast<uint32_t>(s.size()));
  out->append(s);
}

class Reader {
 public:
  Reader(const char* p, size_t n) : p_(p), end_(p + n) {}
  template <typename T>
  bool Get(T* v) {
    if (static_cast<size_t>(end_ - p_) < sizeof(T)) return false;
    std::memcpy(v, p_, sizeof(T));
    p_ += sizeof(T);
    return true;
  }
  bool GetString(std::string* s) {
    uint32_t n = 0;
    if (!Get(&n) || static_cast<size_t>(end_ - p_) < n) return false;
    s->assign(p_, n);
    p_ += n;
    return true;
  }
  // Room for `count` items of `size` bytes (bounds every allocation by
  // the bytes actually present).
  bool Has(uint64_t count, size_t size) const {
    return count <= static_cast<uint64_t>(end_ - p_) / size;
  }
  bool done() const { return p_ == end_; }

 private:
  const char* p_;
  const char* end_;
};

uint32_t Crc(const std::string& payload) {
  return static_cast<uint32_t>(
      crc32(0L, reinterpret_cast<const Bytef*>(payload.data()),
            static_cast<uInt>(payload.size())));
}

// A record is this header followed by the payload (written separately: a
// step's payload is as large as the positions).
std::string Header(uint32_t type, const std::string& payload) {
  std::string r;
  Put<uint32_t>(&r, kMagic);
  Put<uint32_t>(&r, type);
  Put<uint64_t>(&r, payload.size());
  Put<uint32_t>(&r, Crc(payload));
  return r;
}

// Reads the record at `offset` of `data`: type and payload, or false if it
// is truncated or does not check.
bool Unframe(const std::string& data, size_t offset, uint32_t* type,
             std::string* payload, size_t* next) {
  if (data.size() - offset < kHeader) return false;
  Reader r(data.data() + offset, kHeader);
  uint32_t magic = 0, crc = 0;
  uint64_t len = 0;
  r.Get(&magic);
  r.Get(type);
  r.Get(&len);
  r.Get(&crc);
  if (magic != kMagic || len > data.size() - offset - kHeader) return false;
  payload->assign(data, offset + kHeader, len);
  if (Crc(*payload) != crc) return false;
  *next = offset + kHeader + len;
  return true;
}

absl::Status Errno(const std::string& what) {
  const int e = errno;
  const std::string msg = absl::StrCat(what, ": ", std::strerror(e));
  if (e == ENOSPC || e == EFBIG || e == EDQUOT) {
    return absl::ResourceExhaustedError(absl::StrCat(msg, " (disk full)"));
  }
  return absl::UnavailableError(msg);
}

absl::Status WriteAll(int fd, const std::string& data,
                      const std::string& what) {
  size_t done = 0;
  while (done < data.size()) {
    const ssize_t k = ::write(fd, data.data() + done, data.size() - done);
    if (k < 0) {
      if (errno == EINTR) continue;
      return Errno(what);
    }
    done += static_cast<size_t>(k);
  }
  return absl::OkStatus();
}

absl::Status SyncDir(const std::string& dir) {
  const int fd = ::open(dir.c_str(), O_RDONLY | O_DIRECTORY);
  if (fd < 0) return Errno(absl::StrCat("open ", dir));
  const int r = ::fsync(fd);
  ::close(fd);
  return r == 0 ? absl::OkStatus() : Errno(absl::StrCat("fsync ", dir));
}

absl::StatusOr<std::string> ReadAll(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) return absl::NotFoundError(absl::StrCat("cannot read ", path));
  std::ostringstream out;
  out << in.rdbuf();
  return out.str();
}

std::string StepPayload(uint64_t step, const core::DisplacementBatch& b,
                        const std::vector<uint64_t>& added_client_ids) {
  std::string p;
  p.reserve(64 + 4 * b.ids.size() + 16 * b.values.size() + 4 * b.remove.size() +
            16 * b.add.size() + 8 * added_client_ids.size());
  Put<uint64_t>(&p, step);
  Put<uint8_t>(&p, b.mode == core::DisplacementBatch::Mode::kAbsolute ? 1 : 0);
  Put<uint64_t>(&p, b.ids.size());
  p.append(reinterpret_cast<const char*>(b.ids.data()), 4 * b.ids.size());
  Put<uint64_t>(&p, b.values.size());
  static_assert(sizeof(core::Vec2) == 2 * sizeof(double));
  p.append(reinterpret_cast<const char*>(b.values.data()),
           sizeof(core::Vec2) * b.values.size());
  // Points that leave and join (absent in journals written before them).
  if (!b.remove.empty() || !b.add.empty()) {
    Put<uint64_t>(&p, b.remove.size());
    p.append(reinterpret_cast<const char*>(b.remove.data()),
             4 * b.remove.size());
    Put<uint64_t>(&p, b.add.size());
    p.append(reinterpret_cast<const char*>(b.add.data()),
             sizeof(core::Vec2) * b.add.size());
    Put<uint64_t>(&p, added_client_ids.size());
    p.append(reinterpret_cast<const char*>(added_client_ids.data()),
             8 * added_client_ids.size());
  }
  return p;
}

bool ParseStep(const std::string& payload, RestoredSession::Step* out) {
  Reader r(payload.data(), payload.size());
  uint8_t mode = 0;
  uint64_t nids = 0, nvals = 0;
  if (!r.Get(&out->step) || !r.Get(&mode) || !r.Get(&nids) || !r.Has(nids, 4)) {
    return false;
  }
  out->batch.mode = mode ? core::DisplacementBatch::Mode::kAbsolute
                         : core::DisplacementBatch::Mode::kDelta;
  out->batch.ids.resize(nids);
  for (uint32_t& id : out->batch.ids) r.Get(&id);
  if (!r.Get(&nvals) || !r.Has(nvals, 16)) return false;
  out->batch.values.resize(nvals);
  for (core::Vec2& v : out->batch.values) r.Get(&v);
  if (r.done()) return true;
  uint64_t nremove = 0, nadd = 0, nadd_ids = 0;
  if (!r.Get(&nremove) || !r.Has(nremove, 4)) return false;
  out->batch.remove.resize(nremove);
  for (uint32_t& id : out->batch.remove) r.Get(&id);
  if (!r.Get(&nadd) || !r.Has(nadd, 16)) return false;
  out->batch.add.resize(nadd);
  for (core::Vec2& v : out->batch.add) r.Get(&v);
  if (!r.Get(&nadd_ids) || !r.Has(nadd_ids, 8)) return false;
  if (nadd_ids != 0 && nadd_ids != nadd) return false;
  out->added_client_ids.resize(nadd_ids);
  for (uint64_t& id : out->added_client_ids) r.Get(&id);
  return r.done();
}

}  // namespace

absl::StatusOr<FsyncPolicy> ParseFsyncPolicy(const std::string& s) {
  if (s == "always") return FsyncPolicy::kAlways;
  if (s == "everysec") return FsyncPolicy::kEverySecond;
  if (s == "no") return FsyncPolicy::kNo;
  return absl::InvalidArgumentError(
      absl::StrCat("--fsync must be always, everysec or no, not \"", s, "\""));
}

absl::StatusOr<uint64_t> WriteSnapshot(const std::string& dir,
                                       const SessionMeta& meta,
                                       const core::Triangulation& tri) {
  std::string p;
  const std::vector<core::Vec2> pos = tri.Positions();
  p.reserve(128 + 16 * pos.size() + 8 * meta.client_ids.size());
  Put<uint32_t>(&p, kSnapshotVersion);
  PutString(&p, meta.id);
  PutString(&p, meta.tenant);
  PutString(&p, meta.backend);
  Put<uint64_t>(&p, meta.max_query_results);
  Put<uint32_t>(&p, meta.threads);
  Put<uint64_t>(&p, meta.idle_ttl_seconds);
  Put<uint64_t>(&p, meta.step);
  Put<int64_t>(&p, absl::ToUnixNanos(meta.create_time));
  Put<uint64_t>(&p, pos.size());
  p.append(reinterpret_cast<const char*>(pos.data()),
           sizeof(core::Vec2) * pos.size());
  Put<uint64_t>(&p, meta.client_ids.size());
  p.append(reinterpret_cast<const char*>(meta.client_ids.data()),
           8 * meta.client_ids.size());
  Put<uint8_t>(&p, meta.client_id_policy ? 1 : 0);
  const std::string header = Header(kSnapshotRecord, p);
  const std::string tmp = dir + "/snapshot.tmp";
  const int fd = ::open(tmp.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0600);
  if (fd < 0) return Errno(absl::StrCat("create ", tmp));
  absl::Status st = WriteAll(fd, header, absl::StrCat("write ", tmp));
  if (st.ok()) st = WriteAll(fd, p, absl::StrCat("write ", tmp));
  if (st.ok() && ::fsync(fd) != 0) st = Errno(absl::StrCat("fsync ", tmp));
  ::close(fd);
  if (st.ok() && ::rename(tmp.c_str(), (dir + "/snapshot").c_str()) != 0) {
    st = Errno(absl::StrCat("rename ", tmp));
  }
  if (st.ok()) st = SyncDir(dir);
  if (!st.ok()) {
    ::unlink(tmp.c_str());
    return st;
  }
  return header.size() + p.size();
}

Journal::Journal(SessionStore* store, std::string dir, int fd, uint64_t size,
                 uint64_t snapshot_bytes, FsyncPolicy fsync,
                 uint64_t interval_steps)
    : store_(store),
      dir_(std::move(dir)),
      fd_(fd),
      size_(size),
      snapshot_bytes_(snapshot_bytes),
      fsync_(fsync),
      interval_steps_(interval_steps) {
  if (fsync_ == FsyncPolicy::kEverySecond) store_->Track(this);
}

Journal::~Journal() {
  if (fsync_ == FsyncPolicy::kEverySecond) store_->Untrack(this);
  if (!closed_) Sync();
  ::close(fd_);
}

absl::Status Journal::Write(uint32_t type, const std::string& payload) {
  if (closed_) {
    return absl::FailedPreconditionError("the session was deleted");
  }
  if (broken_) {
    return absl::UnavailableError(
        "the session's journal failed earlier; its files may not match it, "
        "so it takes no more steps (queries still work)");
  }
  const std::string header = Header(type, payload);
  absl::Status st = WriteAll(fd_, header, absl::StrCat("journal ", dir_));
  if (st.ok()) st = WriteAll(fd_, payload, absl::StrCat("journal ", dir_));
  if (!st.ok()) {
    // Leave no partial record behind.
    if (::ftruncate(fd_, static_cast<off_t>(size_)) != 0) broken_ = true;
    return st;
  }
  size_ += header.size() + payload.size();
  if (fsync_ == FsyncPolicy::kAlways) {
    if (::fdatasync(fd_) != 0) return Errno(absl::StrCat("fsync ", dir_));
  } else if (fsync_ == FsyncPolicy::kEverySecond) {
    dirty_ = true;
  }
  return absl::OkStatus();
}

absl::Status Journal::Append(uint64_t step,
                             const core::DisplacementBatch& batch,
                             const std::vector<uint64_t>& added_client_ids) {
  return Write(kStepRecord, StepPayload(step, batch, added_client_ids));
}

absl::Status Journal::Abort(uint64_t step) {
  std::string p;
  Put<uint64_t>(&p, step);
  absl::Status st = Write(kAbortRecord, p);
  // Without the abort record a restore would replay a step that never
  // happened: stop taking steps.
  if (!st.ok() && !closed_) broken_ = true;
  return st;
}

bool Journal::CompactionDue() {
  if (closed_ || broken_) return false;
  ++steps_since_snapshot_;
  return interval_steps_ > 0 ? steps_since_snapshot_ >= interval_steps_
                             : size_ > 4 * snapshot_bytes_;
}

absl::Status Journal::Compact(const SessionMeta& meta,
                              const core::Triangulation& tri) {
  auto bytes = WriteSnapshot(dir_, meta, tri);
  // Without a new snapshot the journal simply keeps growing.
  if (!bytes.ok()) return bytes.status();
  snapshot_bytes_ = *bytes;
  steps_since_snapshot_ = 0;
  absl::MutexLock lock(&sync_mu_);
  // The snapshot covers every journaled step (a crash before this leaves
  // records the restore skips by step number).
  if (::ftruncate(fd_, 0) != 0) {
    broken_ = true;
    return Errno(absl::StrCat("truncate journal ", dir_));
  }
  size_ = 0;
  return absl::OkStatus();
}

void Journal::Sync() {
  if (!dirty_.exchange(false)) return;
  absl::MutexLock lock(&sync_mu_);
  ::fdatasync(fd_);
}

SessionStore::SessionStore(std::string dir, FsyncPolicy fsync,
                           uint64_t interval_steps)
    : dir_(std::move(dir)), fsync_(fsync), interval_steps_(interval_steps) {
  if (fsync_ == FsyncPolicy::kEverySecond) {
    syncer_ = std::thread([this] {
      while (!stop_) {
        for (int i = 0; i < 10 && !stop_; ++i) {
          std::this_thread::sleep_for(std::chrono::milliseconds(100));
        }
        absl::MutexLock lock(&mu_);
        for (Journal* j : tracked_) j->Sync();
      }
    });
  }
}

SessionStore::~SessionStore() {
  stop_ = true;
  if (syncer_.joinable()) syncer_.join();
}

absl::StatusOr<std::unique_ptr<SessionStore>> SessionStore::Open(
    const std::string& dir, FsyncPolicy fsync, uint64_t interval_steps) {
  for (const std::string& d : {dir, dir + "/sessions"}) {
    if (::mkdir(d.c_str(), 0700) != 0 && errno != EEXIST) {
      return Errno(absl::StrCat("--data_dir: cannot create ", d));
    }
  }
  const std::string probe = dir + "/sessions/.probe";
  const int fd = ::open(probe.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0600);
  if (fd < 0) return Errno(absl::StrCat("--data_dir: cannot write in ", dir));
  ::close(fd);
  ::unlink(probe.c_str());
  return std::unique_ptr<SessionStore>(
      new SessionStore(dir, fsync, interval_steps));
}

void SessionStore::Track(Journal* j) {
  absl::MutexLock lock(&mu_);
  tracked_.push_back(j);
}

void SessionStore::Untrack(Journal* j) {
  absl::MutexLock lock(&mu_);
  std::erase(tracked_, j);
}

std::string SessionStore::SessionDir(const std::string& tenant,
                                     const std::string& id) const {
  return absl::StrCat(dir_, "/sessions/", Key(tenant, id));
}

absl::StatusOr<std::unique_ptr<Journal>> SessionStore::OpenJournal(
    const std::string& dir, uint64_t snapshot_bytes, bool truncate) {
  const std::string path = dir + "/journal";
  const int fd =
      ::open(path.c_str(),
             O_WRONLY | O_CREAT | O_APPEND | (truncate ? O_TRUNC : 0), 0600);
  if (fd < 0) return Errno(absl::StrCat("open ", path));
  struct stat st {};
  ::fstat(fd, &st);
  return std::unique_ptr<Journal>(
      new Journal(this, dir, fd, static_cast<uint64_t>(st.st_size),
                  snapshot_bytes, fsync_, interval_steps_));
}

absl::StatusOr<std::unique_ptr<Journal>> SessionStore::Create(
    const SessionMeta& meta, const core::Triangulation& tri) {
  const std::string dir = SessionDir(meta.tenant, meta.id);
  // A directory left by a session that was never acknowledged, or by a
  // broken one the client chose to replace, is overwritten.
  if (::mkdir(dir.c_str(), 0700) != 0 && errno != EEXIST) {
    return Errno(absl::StrCat("create ", dir));
  }
  ::unlink((dir + "/journal").c_str());
  auto bytes = WriteSnapshot(dir, meta, tri);
  if (!bytes.ok()) {
    Remove(meta.tenant, meta.id).IgnoreError();
    return bytes.status();
  }
  return OpenJournal(dir, *bytes, /*truncate=*/true);
}

absl::StatusOr<std::unique_ptr<Journal>> SessionStore::Reopen(
    const SessionMeta& meta, const core::Triangulation& tri) {
  const std::string dir = SessionDir(meta.tenant, meta.id);
  auto bytes = WriteSnapshot(dir, meta, tri);
  if (!bytes.ok()) return bytes.status();
  return OpenJournal(dir, *bytes, /*truncate=*/true);
}

absl::Status SessionStore::Remove(const std::string& tenant,
                                  const std::string& id) {
  const std::string dir = SessionDir(tenant, id);
  for (const char* f : {"/snapshot", "/snapshot.tmp", "/journal"}) {
    ::unlink((dir + f).c_str());
  }
  if (::rmdir(dir.c_str()) != 0 && errno != ENOENT) {
    return Errno(absl::StrCat("remove ", dir));
  }
  return SyncDir(dir_ + "/sessions");
}

std::vector<RestoredSession> SessionStore::LoadAll(
    absl::flat_hash_map<std::string, std::string>* broken) {
  std::vector<RestoredSession> out;
  const std::string root = dir_ + "/sessions";
  DIR* d = ::opendir(root.c_str());
  if (d == nullptr) return out;
  std::vector<std::string> names;
  while (dirent* e = ::readdir(d)) {
    const std::string name = e->d_name;
    if (name.find('@') != std::string::npos) names.push_back(name);
  }
  ::closedir(d);
  std::sort(names.begin(), names.end());
  for (const std::string& name : names) {
    const std::string dir = root + "/" + name;
    auto snap = ReadAll(dir + "/snapshot");
    if (!snap.ok()) {
      // Creation never finished (no snapshot renamed into place): the
      // session was never acknowledged.
      Remove(name.substr(0, name.find('@')), name.substr(name.find('@') + 1))
          .IgnoreError();
      continue;
    }
    RestoredSession s;
    uint32_t type = 0;
    std::string payload;
    size_t next = 0;
    bool ok = Unframe(*snap, 0, &type, &payload, &next) &&
              type == kSnapshotRecord && next == snap->size();
    if (ok) {
      Reader r(payload.data(), payload.size());
      uint32_t version = 0;
      int64_t created = 0;
      uint64_t n = 0, nids = 0;
      ok = r.Get(&version) && (version == 1 || version == kSnapshotVersion) &&
           r.GetString(&s.meta.id) && r.GetString(&s.meta.tenant) &&
           r.GetString(&s.meta.backend) && r.Get(&s.meta.max_query_results) &&
           r.Get(&s.meta.threads) && r.Get(&s.meta.idle_ttl_seconds) &&
           r.Get(&s.meta.step) && r.Get(&created) && r.Get(&n) && r.Has(n, 16);
      if (ok) {
        s.meta.create_time = absl::FromUnixNanos(created);
        s.positions.resize(n);
        for (core::Vec2& v : s.positions) r.Get(&v);
        ok = r.Get(&nids) && r.Has(nids, 8) && (nids == 0 || nids == n);
      }
      if (ok) {
        s.meta.client_ids.resize(nids);
        for (uint64_t& id : s.meta.client_ids) r.Get(&id);
        uint8_t policy = nids > 0 ? 1 : 0;
        if (version >= 2) ok = r.Get(&policy);
        s.meta.client_id_policy = policy != 0;
        ok = ok && r.done() && Key(s.meta.tenant, s.meta.id) == name;
      }
    }
    if (!ok) {
      (*broken)[name] = absl::StrCat(
          "the snapshot of this session (", dir,
          "/snapshot) is corrupt; it cannot be restored (delete the session "
          "to drop it)");
      continue;
    }
    // Journal: records up to the first one that does not check.
    auto journal = ReadAll(dir + "/journal");
    if (journal.ok()) {
      size_t offset = 0;
      while (offset < journal->size()) {
        if (!Unframe(*journal, offset, &type, &payload, &next)) break;
        if (type == kStepRecord) {
          RestoredSession::Step step;
          if (!ParseStep(payload, &step)) break;
          s.steps.push_back(std::move(step));
        } else if (type == kAbortRecord) {
          uint64_t step = 0;
          Reader r(payload.data(), payload.size());
          if (!r.Get(&step)) break;
          if (!s.steps.empty() && s.steps.back().step == step) {
            s.steps.pop_back();
          }
        } else {
          break;
        }
        offset = next;
      }
      if (offset < journal->size()) {
        s.cut_bytes = journal->size() - offset;
        ::truncate((dir + "/journal").c_str(), static_cast<off_t>(offset));
      }
    }
    out.push_back(std::move(s));
  }
  return out;
}

}  // namespace kinetri::server
