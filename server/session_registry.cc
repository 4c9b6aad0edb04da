// Sessions (one triangulation each) and the registry that owns them.
#include "server/session_registry.h"

#include <malloc.h>

#include "absl/strings/escaping.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/time/clock.h"

namespace kinetri::server {

Session::ReturnMemoryOnDestroy::~ReturnMemoryOnDestroy() {
#if defined(__GLIBC__)
  malloc_trim(0);
#endif
}

std::shared_ptr<core::Triangulation> Session::Share(
    core::Triangulation tri) const {
  return std::shared_ptr<core::Triangulation>(
      new core::Triangulation(std::move(tri)),
      [retired = retired_](core::Triangulation* t) {
        delete t;
#if defined(__GLIBC__)
        if (retired->load()) malloc_trim(0);
#endif
      });
}

Session::~Session() { retired_->store(true); }

Session::Session(std::string id, core::Triangulation tri, std::string backend,
                 uint64_t max_query_results, uint32_t threads,
                 std::shared_ptr<const PointIdMap> client_ids,
                 MemoryBudget::Reservation memory, MemoryBudget* budget)
    : id_(std::move(id)),
      backend_(std::move(backend)),
      max_query_results_(max_query_results),
      threads_(threads),
      create_time_(absl::Now()),
      point_count_(tri.size()),
      client_policy_(client_ids != nullptr),
      memory_(std::move(memory)),
      budget_(budget),
      current_(Share(std::move(tri))),
      update_time_(create_time_) {
  ids_ = std::move(client_ids);
}

Session::Snapshot Session::Read() const {
  absl::MutexLock lock(&mu_);
  mu_.Await(absl::Condition(
      +[](const bool* in_place) { return !*in_place; }, &in_place_));
  return Snapshot{current_, step_, update_time_, ids_};
}

absl::StatusOr<core::StepReport> Session::ApplyStep(
    uint64_t step, core::DisplacementBatch batch,
    const StepClientIds* client_ids, const core::CancelToken* cancel,
    bool* copied, const std::string& request_id, bool* replayed) {
  absl::MutexLock write_lock(&write_mu_);
  std::shared_ptr<core::Triangulation> target;
  std::shared_ptr<const core::Triangulation> source;
  std::shared_ptr<const PointIdMap> ids;  // the step before's
  if (replayed) *replayed = false;
  {
    absl::MutexLock lock(&mu_);
    if (step <= step_ && !request_id.empty()) {
      for (const Applied& a : applied_) {
        if (a.step == step && a.request_id == request_id) {
          if (replayed) *replayed = true;
          return a.report;
        }
      }
    }
    if (step != step_ + 1) {
      return absl::FailedPreconditionError(
          absl::StrCat("step: got ", step, ", expected ", step_ + 1,
                       " (steps apply in order)"));
    }
    ids = ids_;
  }
  // Client ids name points of the step before this one: only this writer
  // changes them, so they hold until the step is published.
  std::shared_ptr<const PointIdMap> next_ids;
  std::vector<uint64_t> added_ids;
  if (ids != nullptr && client_ids != nullptr) {
    batch.ids.resize(client_ids->moved.size());
    for (size_t i = 0; i < client_ids->moved.size(); ++i) {
      auto in = ids->IndexOf(client_ids->moved[i],
                             absl::StrCat("client_ids[", i, "]"));
      if (!in.ok()) return in.status();
      batch.ids[i] = *in;
    }
    batch.remove.resize(client_ids->removed.size());
    absl::flat_hash_map<uint32_t, size_t> removed_at;
    for (size_t i = 0; i < client_ids->removed.size(); ++i) {
      auto in = ids->IndexOf(client_ids->removed[i],
                             absl::StrCat("remove_client_ids[", i, "]"));
      if (!in.ok()) return in.status();
      auto [it, fresh] = removed_at.emplace(*in, i);
      if (!fresh) {
        return absl::InvalidArgumentError(absl::StrCat(
            "remove_client_ids[", i, "] = ", client_ids->removed[i],
            " appears twice (also remove_client_ids[", it->second, "])"));
      }
      batch.remove[i] = *in;
    }
    for (size_t i = 0; i < batch.ids.size(); ++i) {
      if (removed_at.contains(batch.ids[i])) {
        return absl::InvalidArgumentError(absl::StrCat(
            "client_ids[", i, "] = ", client_ids->moved[i],
            " leaves with this step (it is in remove_client_ids)"));
      }
    }
    added_ids = client_ids->added;
  }
  if (ids != nullptr && (!batch.remove.empty() || !added_ids.empty())) {
    auto after = ids->After(batch.remove, added_ids);
    if (!after.ok()) return after.status();
    next_ids = *std::move(after);
  }
  // Growth beyond the creation's points is admitted and reserved first.
  std::vector<MemoryBudget::Reservation> growth;
  const uint64_t count = point_count_.load();
  if (batch.add.size() > batch.remove.size()) {
    const uint64_t more = batch.add.size() - batch.remove.size();
    if (count + more > max_points_) {
      return absl::ResourceExhaustedError(absl::StrCat(
          "add: ", count, " points + ", more, " exceed the limit of ",
          max_points_, " points per session"));
    }
    if (growth_check_) {
      absl::Status st = growth_check_(more);
      if (!st.ok()) return st;
    }
    if (budget_ != nullptr) {
      auto r =
          budget_->Reserve(more * MemoryBudget::SessionBytesPerPoint(backend_),
                           absl::StrCat("add: ", more, " points"));
      if (!r.ok()) return r.status();
      growth.push_back(*std::move(r));
    }
  }
  {
    absl::MutexLock lock(&mu_);
    // Every reference a reader holds was taken under mu_, so a count of
    // one means nobody reads this triangulation, and nobody will until
    // in_place_ is cleared.
    if (current_.use_count() == 1) {
      in_place_ = true;
      target = current_;
    } else {
      source = current_;
    }
  }
  MemoryBudget::Reservation copy_memory;
  if (!target && budget_ != nullptr) {
    // A copy on a device has an executor of its own (on the emulated
    // device, its device memory is host memory).
    auto r =
        budget_->Reserve(count * MemoryBudget::CopyBytesPerPoint(backend_) +
                             MemoryBudget::DeviceFixedBytes(backend_),
                         "step copy");
    if (r.ok()) {
      copy_memory = std::move(*r);
    } else {
      // No room for a copy: keep new readers out and wait for the current
      // ones to finish, then move the triangulation in place.
      source.reset();
      {
        absl::MutexLock lock(&mu_);
        in_place_ = true;
      }
      while (true) {
        {
          absl::MutexLock lock(&mu_);
          if (current_.use_count() == 1) {
            target = current_;
            break;
          }
        }
        absl::SleepFor(absl::Milliseconds(1));
      }
    }
  }
  if (copied) *copied = target == nullptr;
  if (!target) {
    // Readers hold the current step: move a copy. Only this writer ever
    // replaces current_, so `source` stays the current step meanwhile.
    target = Share(source->Clone());
    source.reset();
  }
  // Durable sessions: the step is journaled before it applies (a step the
  // journal cannot take is refused and changes nothing).
  if (journal_ != nullptr) {
    absl::Status st = journal_->Append(step, batch, added_ids);
    if (!st.ok()) {
      absl::MutexLock lock(&mu_);
      in_place_ = false;
      return absl::Status(
          st.code(),
          absl::StrCat("step ", step, " not applied: ", st.message()));
    }
  }
  absl::StatusOr<core::StepReport> report =
      target->ApplyDisplacements(batch, cancel);
  if (!report.ok() && journal_ != nullptr) {
    journal_->Abort(step).IgnoreError();  // marks the journal broken
  }
  {
    absl::MutexLock lock(&mu_);
    if (in_place_) {
      in_place_ = false;  // on error ApplyDisplacements changed nothing
    } else if (report.ok()) {
      current_ = target;
    }
    if (report.ok()) {
      step_ = step;
      update_time_ = absl::Now();
      if (next_ids != nullptr) ids_ = std::move(next_ids);
      point_count_ = target->size();
      for (auto& r : growth) growth_memory_.push_back(std::move(r));
      if (!request_id.empty()) {
        applied_.push_back({step, request_id, *report});
        if (applied_.size() > kRememberedSteps) applied_.pop_front();
      }
    }
  }
  if (report.ok() && journal_ != nullptr && journal_->CompactionDue()) {
    // Compaction reads the step just published (immutable for readers);
    // a failure only postpones it.
    journal_->Compact(Meta(step), *target).IgnoreError();
  }
  return report;
}

absl::StatusOr<bool> Session::Checkpoint() {
  absl::MutexLock write_lock(&write_mu_);
  if (journal_ == nullptr || journal_->broken() || !journal_->has_records()) {
    return false;
  }
  const Snapshot now = Read();
  absl::Status st = journal_->Compact(Meta(now.step), *now.tri);
  if (!st.ok()) return st;
  return true;
}

void Session::RestoreStep(uint64_t step, absl::Time create_time) {
  absl::MutexLock lock(&mu_);
  step_ = step;
  create_time_ = create_time;
  update_time_ = absl::Now();
}

SessionMeta Session::Meta(uint64_t step) const {
  SessionMeta m;
  m.id = id_;
  m.tenant = tenant_;
  m.backend = backend_;
  m.max_query_results = max_query_results_;
  m.threads = threads_;
  m.idle_ttl_seconds = idle_ttl_seconds_;
  m.step = step;
  m.create_time = create_time_;
  {
    absl::MutexLock lock(&mu_);
    if (ids_ != nullptr) m.client_ids = ids_->ids();
    m.client_id_policy = client_policy_;
  }
  return m;
}

namespace {
constexpr char kPageTokenPrefix[] = "kinetri.page.v1:";
constexpr size_t kPageTokenPrefixSize = sizeof(kPageTokenPrefix) - 1;
}  // namespace

std::string EncodePageToken(const std::string& after_id) {
  return absl::WebSafeBase64Escape(absl::StrCat(kPageTokenPrefix, after_id));
}

absl::StatusOr<std::string> DecodePageToken(const std::string& token) {
  std::string raw;
  if (token.size() > 256 || !absl::WebSafeBase64Unescape(token, &raw) ||
      !absl::StartsWith(raw, kPageTokenPrefix) ||
      !ValidSessionId(raw.substr(kPageTokenPrefixSize))) {
    return absl::InvalidArgumentError(
        absl::StrCat("page_token: \"", EchoForError(token),
                     "\" is not a token from ListSessions"));
  }
  return raw.substr(kPageTokenPrefixSize);
}

bool ValidSessionId(const std::string& id) {
  if (id.empty() || id.size() > 63) return false;
  for (char c : id) {
    if (!((c >= 'a' && c <= 'z') || (c >= '0' && c <= '9') || c == '-')) {
      return false;
    }
  }
  return true;
}

std::string EchoForError(const std::string& value) {
  constexpr size_t kMax = 80;
  if (value.size() <= kMax) return absl::CHexEscape(value);
  return absl::StrCat(absl::CHexEscape(value.substr(0, kMax)), "... (",
                      value.size(), " bytes)");
}

absl::StatusOr<std::string> ParseSessionName(const std::string& name,
                                             const std::string& field) {
  constexpr absl::string_view kPrefix = "sessions/";
  if (!absl::StartsWith(name, kPrefix) ||
      !ValidSessionId(name.substr(kPrefix.size()))) {
    return absl::InvalidArgumentError(
        absl::StrCat(field, ": \"", EchoForError(name),
                     "\" is not a session name (sessions/{id})"));
  }
  return name.substr(kPrefix.size());
}

namespace {

std::string Key(const std::string& tenant, const std::string& id) {
  return tenant.empty() ? id : absl::StrCat(tenant, "/", id);
}

}  // namespace

absl::Status SessionRegistry::CheckTenantLocked(uint64_t points,
                                                std::string_view backend,
                                                const Tenant& tenant,
                                                bool new_session) const {
  if (tenant.max_sessions == 0 && tenant.max_points == 0 &&
      tenant.max_memory_mb == 0) {
    return absl::OkStatus();
  }
  uint64_t sessions = 0, total = 0, held_bytes = 0;
  const std::string prefix = Key(tenant.name, "");
  for (auto it = sessions_.lower_bound(prefix);
       it != sessions_.end() && absl::StartsWith(it->first, prefix); ++it) {
    ++sessions;
    const uint64_t n = it->second->point_count();
    const std::string& b = it->second->backend();
    total += n;
    held_bytes += n * MemoryBudget::SessionBytesPerPoint(b) +
                  MemoryBudget::DeviceFixedBytes(b);
  }
  if (new_session && tenant.max_sessions != 0 &&
      sessions >= tenant.max_sessions) {
    return absl::ResourceExhaustedError(
        absl::StrCat("tenant ", tenant.name, " holds its maximum of ",
                     tenant.max_sessions, " sessions; delete one first"));
  }
  // Memory by the same estimates the server's budget admits with.
  const uint64_t bytes =
      held_bytes + points * MemoryBudget::SessionBytesPerPoint(backend) +
      (new_session ? MemoryBudget::DeviceFixedBytes(backend) : 0);
  if (tenant.max_memory_mb != 0 && bytes > (tenant.max_memory_mb << 20)) {
    return absl::ResourceExhaustedError(
        absl::StrCat("tenant ", tenant.name, ": ", total, " points held + ",
                     points, " need about ", bytes >> 20,
                     " MiB, over its limit of ", tenant.max_memory_mb, " MiB"));
  }
  if (tenant.max_points != 0 && total + points > tenant.max_points) {
    return absl::ResourceExhaustedError(absl::StrCat(
        "tenant ", tenant.name, ": ", total, " points held + ", points,
        " exceed its limit of ", tenant.max_points, " points"));
  }
  return absl::OkStatus();
}

absl::Status SessionRegistry::CheckGrowth(uint64_t points,
                                          std::string_view backend,
                                          const Tenant& tenant) const {
  absl::MutexLock lock(&mu_);
  return CheckTenantLocked(points, backend, tenant, /*new_session=*/false);
}

absl::Status SessionRegistry::CheckCapacity(uint64_t points,
                                            std::string_view backend,
                                            const Tenant& tenant) const {
  if (points > limits_.max_points_per_session) {
    return absl::ResourceExhaustedError(
        absl::StrCat("point_count: ", points, " exceeds the limit of ",
                     limits_.max_points_per_session, " points per session"));
  }
  absl::MutexLock lock(&mu_);
  if (sessions_.size() >= limits_.max_sessions) {
    return absl::ResourceExhaustedError(
        absl::StrCat("the server holds its maximum of ", limits_.max_sessions,
                     " sessions; delete one first"));
  }
  return CheckTenantLocked(points, backend, tenant);
}

absl::StatusOr<std::shared_ptr<Session>> SessionRegistry::Add(
    std::shared_ptr<Session> s, const Tenant& tenant) {
  s->set_tenant(tenant.name);
  absl::MutexLock lock(&mu_);
  if (sessions_.size() >= limits_.max_sessions) {
    return absl::ResourceExhaustedError(
        absl::StrCat("the server holds its maximum of ", limits_.max_sessions,
                     " sessions; delete one first"));
  }
  absl::Status st = CheckTenantLocked(s->point_count(), s->backend(), tenant);
  if (!st.ok()) return st;
  if (!sessions_.emplace(Key(tenant.name, s->id()), s).second) {
    return absl::AlreadyExistsError(
        absl::StrCat("session_id: ", s->name(), " already exists"));
  }
  return s;
}

absl::StatusOr<std::shared_ptr<Session>> SessionRegistry::Get(
    const std::string& name, const std::string& tenant) const {
  auto id = ParseSessionName(name, "name");
  if (!id.ok()) return id.status();
  absl::MutexLock lock(&mu_);
  auto it = sessions_.find(Key(tenant, *id));
  if (it == sessions_.end()) {
    return absl::NotFoundError(absl::StrCat(name, " does not exist"));
  }
  return it->second;
}

absl::Status SessionRegistry::Remove(const std::string& name,
                                     const std::string& tenant) {
  auto id = ParseSessionName(name, "name");
  if (!id.ok()) return id.status();
  absl::MutexLock lock(&mu_);
  if (sessions_.erase(Key(tenant, *id)) == 0) {
    return absl::NotFoundError(absl::StrCat(name, " does not exist"));
  }
  return absl::OkStatus();
}

std::vector<std::shared_ptr<Session>> SessionRegistry::List(
    const std::string& after, size_t limit, const std::string& tenant) const {
  absl::MutexLock lock(&mu_);
  std::vector<std::shared_ptr<Session>> out;
  for (auto it = sessions_.upper_bound(Key(tenant, after));
       it != sessions_.end() && out.size() < limit; ++it) {
    // The unnamed tenant's keys have no '/'; a named tenant's start with
    // "tenant/".
    const bool mine = tenant.empty()
                          ? it->first.find('/') == std::string::npos
                          : absl::StartsWith(it->first, Key(tenant, ""));
    if (!mine) {
      if (!tenant.empty()) break;  // past this tenant's range
      continue;
    }
    out.push_back(it->second);
  }
  return out;
}

std::vector<std::shared_ptr<Session>> SessionRegistry::All() const {
  absl::MutexLock lock(&mu_);
  std::vector<std::shared_ptr<Session>> out;
  out.reserve(sessions_.size());
  for (const auto& [key, s] : sessions_) out.push_back(s);
  return out;
}

bool SessionRegistry::RemoveSession(const std::shared_ptr<Session>& s) {
  absl::MutexLock lock(&mu_);
  auto it = sessions_.find(Key(s->tenant(), s->id()));
  if (it == sessions_.end() || it->second != s) return false;
  sessions_.erase(it);
  return true;
}

std::string SessionRegistry::NewId() const {
  return absl::StrCat("s-", RandomHex128());
}

size_t SessionRegistry::size() const {
  absl::MutexLock lock(&mu_);
  return sessions_.size();
}

uint64_t SessionRegistry::total_points() const {
  absl::MutexLock lock(&mu_);
  uint64_t total = 0;
  for (const auto& [id, s] : sessions_) total += s->point_count();
  return total;
}

}  // namespace kinetri::server
