// gRPC implementation of kinetri.v1.KinetriService over the core.
#include "server/service.h"

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <memory>
#include <optional>
#include <string>

#include "absl/container/flat_hash_map.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "core/queries.h"
#include "server/convert.h"
#include "server/message_reader.h"

namespace kinetri::server {
namespace {

using Clock = std::chrono::steady_clock;

// A call's deadline (system clock; far future when none) on the steady
// clock the core's cancellation tokens use.
Clock::time_point ToSteadyDeadline(std::chrono::system_clock::time_point d) {
  const auto now_sys = std::chrono::system_clock::now();
  if (d - now_sys > std::chrono::hours(24 * 365)) {
    return Clock::time_point::max();
  }
  return Clock::now() +
         std::chrono::duration_cast<Clock::duration>(d - now_sys);
}

grpc::Status ToGrpc(const absl::Status& s) {
  if (s.ok()) return grpc::Status::OK;
  return grpc::Status(static_cast<grpc::StatusCode>(s.code()),
                      std::string(s.message()));
}

google::protobuf::Timestamp ToTimestamp(absl::Time t) {
  google::protobuf::Timestamp ts;
  const int64_t ns = absl::ToUnixNanos(t);
  ts.set_seconds(ns / 1000000000);
  ts.set_nanos(static_cast<int32_t>(ns % 1000000000));
  return ts;
}

v1::Session Describe(const Session& s) {
  const Session::Snapshot snap = s.Read();
  v1::Session out;
  out.set_name(s.name());
  out.set_backend(s.backend());
  out.set_point_count(snap.tri->size());
  out.set_site_count(snap.tri->num_sites());
  out.set_step(snap.step);
  out.mutable_options()->set_backend(s.backend() == "cpu" ? v1::BACKEND_CPU
                                                          : v1::BACKEND_CUDA);
  out.set_device_bytes(snap.tri->device_bytes());
  out.mutable_options()->set_idle_ttl_seconds(s.idle_ttl_seconds());
  if (s.idle_ttl_seconds() > 0) {
    *out.mutable_expire_time() = ToTimestamp(s.ExpireTime());
  }
  out.mutable_options()->set_threads(s.threads());
  out.mutable_options()->set_point_id_policy(
      s.has_client_ids() ? v1::POINT_ID_POLICY_CLIENT
                         : v1::POINT_ID_POLICY_SEQUENTIAL);
  out.mutable_options()->set_max_query_results(s.max_query_results());
  *out.mutable_create_time() = ToTimestamp(s.create_time());
  *out.mutable_update_time() = ToTimestamp(snap.update_time);
  return out;
}

// Index of `method` in the service (the generated service registers its
// methods in the order of the proto's definition).
int MethodIndex(const char* method) {
  const google::protobuf::ServiceDescriptor* service =
      google::protobuf::DescriptorPool::generated_pool()->FindServiceByName(
          kServiceName);
  const google::protobuf::MethodDescriptor* m =
      service == nullptr ? nullptr : service->FindMethodByName(method);
  if (m == nullptr) {
    std::fprintf(stderr, "kinetri-server: %s.%s missing from the proto\n",
                 kServiceName, method);
    std::abort();
  }
  return m->index();
}

}  // namespace

KinetriServiceImpl::RestoreReport KinetriServiceImpl::EnableDurability(
    SessionStore* store) {
  const auto t0 = std::chrono::steady_clock::now();
  store_ = store;
  RestoreReport report;
  absl::flat_hash_map<std::string, std::string> broken;
  std::vector<RestoredSession> sessions = store->LoadAll(&broken);
  const ServerLimits& limits = registry_->limits();
  for (RestoredSession& r : sessions) {
    const std::string key = SessionStore::Key(r.meta.tenant, r.meta.id);
    report.journal_bytes_cut += r.cut_bytes;
    if (r.cut_bytes > 0) {
      std::fprintf(stderr,
                   "kinetri-server: %s: cut %llu bytes of corrupt or "
                   "truncated journal tail\n",
                   key.c_str(), static_cast<unsigned long long>(r.cut_bytes));
    }
    core::TriangulationOptions opt;
    opt.num_threads = static_cast<int>(r.meta.threads);
    std::string backend = "cpu";
    if (r.meta.backend != "cpu" && limits.has_device) {
      opt.executor = core::Executor::kDevice;
      opt.device_backend = limits.device;
      backend = core::device::DeviceBackendName(limits.device);
    }
    const uint64_t n = r.positions.size();
    auto memory =
        budget_->Reserve(n * MemoryBudget::SessionBytesPerPoint(backend) +
                             MemoryBudget::DeviceFixedBytes(backend),
                         absl::StrCat("restoring ", key));
    if (!memory.ok()) {
      broken[key] = std::string(memory.status().message());
      continue;
    }
    auto tri = core::Triangulation::Create(r.positions, opt);
    if (!tri.ok()) {
      broken[key] = absl::StrCat("cannot restore: ", tri.status().message());
      continue;
    }
    uint64_t step = r.meta.step;
    std::shared_ptr<const PointIdMap> ids;
    if (r.meta.client_id_policy) {
      ids = std::make_shared<const PointIdMap>(std::move(r.meta.client_ids));
    }
    for (const RestoredSession::Step& s : r.steps) {
      if (s.step != step + 1) continue;  // covered by the snapshot
      // A journaled step that fails again failed the first time too (its
      // client ids were resolved before it was journaled).
      std::shared_ptr<const PointIdMap> next_ids = ids;
      if (ids != nullptr && (!s.batch.remove.empty() || !s.batch.add.empty())) {
        auto after = ids->After(s.batch.remove, s.added_client_ids);
        if (!after.ok()) continue;
        next_ids = *std::move(after);
      }
      if (tri->ApplyDisplacements(s.batch).ok()) {
        step = s.step;
        ids = std::move(next_ids);
        ++report.steps_replayed;
      }
    }
    auto session = std::make_shared<Session>(
        r.meta.id, std::move(*tri), backend, r.meta.max_query_results,
        r.meta.threads, std::move(ids), std::move(*memory), budget_);
    {
      Tenant t;
      t.name = r.meta.tenant;
      SessionRegistry* registry = registry_;
      session->set_growth_limits(
          limits.max_points_per_session, [registry, t, backend](uint64_t more) {
            return registry->CheckGrowth(more, backend, t);
          });
    }
    session->RestoreStep(step, r.meta.create_time);
    session->set_idle_ttl(r.meta.idle_ttl_seconds);  // the clock restarts
    Tenant tenant;
    tenant.name = r.meta.tenant;
    session->set_tenant(tenant.name);
    auto journal = store->Reopen(session->Meta(step), *session->Read().tri);
    if (!journal.ok()) {
      broken[key] =
          absl::StrCat("cannot reopen its files: ", journal.status().message());
      continue;
    }
    session->AttachJournal(*std::move(journal));
    auto added = registry_->Add(session, tenant);
    if (!added.ok()) {
      session->journal()->Close();
      broken[key] = std::string(added.status().message());
      continue;
    }
    ++report.sessions;
  }
  report.unavailable = broken.size();
  for (const auto& [key, why] : broken) {
    std::fprintf(stderr, "kinetri-server: session %s unavailable: %s\n",
                 key.c_str(), why.c_str());
  }
  {
    absl::MutexLock lock(&broken_mu_);
    broken_ = std::move(broken);
  }
  report.seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - t0)
          .count();
  metrics_->SetRestore(static_cast<double>(report.sessions),
                       static_cast<double>(report.unavailable),
                       static_cast<double>(report.journal_bytes_cut),
                       report.seconds);
  UpdateGauges();
  return report;
}

size_t KinetriServiceImpl::ExpireIdleSessions() {
  const absl::Time now = absl::Now();
  size_t expired = 0;
  for (const std::shared_ptr<Session>& s : registry_->All()) {
    if (s->ExpireTime() > now || !registry_->RemoveSession(s)) continue;
    if (s->journal() != nullptr) {
      s->journal()->Close();
      store_->Remove(s->tenant(), s->id()).IgnoreError();
    }
    ++expired;
  }
  if (expired > 0) {
    metrics_->SessionsExpired(static_cast<double>(expired));
    UpdateGauges();
  }
  return expired;
}

size_t KinetriServiceImpl::CheckpointAll() {
  if (store_ == nullptr) return 0;
  size_t written = 0;
  for (const std::shared_ptr<Session>& s : registry_->All()) {
    absl::StatusOr<bool> done = s->Checkpoint();
    if (!done.ok()) {
      std::fprintf(stderr, "kinetri-server: no snapshot of %s: %s\n",
                   s->name().c_str(),
                   std::string(done.status().message()).c_str());
    } else if (*done) {
      ++written;
    }
  }
  return written;
}

absl::StatusOr<std::shared_ptr<Session>> KinetriServiceImpl::Lookup(
    const std::string& name, const std::string& tenant) const {
  auto s = registry_->Get(name, tenant);
  if (s.ok()) (*s)->Touch();
  if (s.ok() || store_ == nullptr ||
      s.status().code() != absl::StatusCode::kNotFound) {
    return s;
  }
  auto id = ParseSessionName(name, "name");
  if (!id.ok()) return s;
  absl::MutexLock lock(&broken_mu_);
  auto it = broken_.find(SessionStore::Key(tenant, *id));
  if (it == broken_.end()) return s;
  return absl::DataLossError(absl::StrCat(name, ": ", it->second));
}

absl::StatusOr<Tenant> KinetriServiceImpl::Caller(
    const grpc::ServerContext& ctx) const {
  if (auth_ == nullptr) return Tenant{};
  return auth_->Authenticate(ctx);
}

KinetriServiceImpl::KinetriServiceImpl(SessionRegistry* registry,
                                       Metrics* metrics, IdleWatchdog* watchdog,
                                       MemoryBudget* budget,
                                       const TokenAuth* auth)
    : registry_(registry),
      metrics_(metrics),
      watchdog_(watchdog),
      budget_(budget),
      auth_(auth) {
  // The streaming RPCs take their requests as bytes (see
  // server/message_reader.h); still synchronous handlers.
  using Self = KinetriServiceImpl;
  MarkMethodStreamed(
      MethodIndex("CreateSession"),
      new grpc::internal::ClientStreamingHandler<Self, grpc::ByteBuffer,
                                                 v1::Session>(
          [](Self* self, grpc::ServerContext* ctx,
             grpc::ServerReader<grpc::ByteBuffer>* reader,
             v1::Session* response) {
            return self->CreateSessionFromBytes(ctx, reader, response);
          },
          this));
  MarkMethodStreamed(
      MethodIndex("StreamSteps"),
      new grpc::internal::BidiStreamingHandler<Self, grpc::ByteBuffer,
                                               v1::StepResponse>(
          [](Self* self, grpc::ServerContext* ctx,
             grpc::ServerReaderWriter<v1::StepResponse, grpc::ByteBuffer>*
                 stream) { return self->StreamStepsFromBytes(ctx, stream); },
          this));
  // The query RPCs send bytes too: their chunks are encoded on the query
  // threads (below the priority of steps), not on the handler's thread.
  MarkMethodStreamed(
      MethodIndex("StreamQuery"),
      new grpc::internal::BidiStreamingHandler<Self, grpc::ByteBuffer,
                                               grpc::ByteBuffer>(
          [](Self* self, grpc::ServerContext* ctx, BytesStream* stream) {
            return self->StreamQueryFromBytes(ctx, stream);
          },
          this));
  MarkMethodStreamed(
      MethodIndex("Query"),
      new grpc::internal::BidiStreamingHandler<Self, grpc::ByteBuffer,
                                               grpc::ByteBuffer>(
          [](Self* self, grpc::ServerContext* ctx, BytesStream* stream) {
            return self->QueryFromBytes(ctx, stream);
          },
          this));
}

void KinetriServiceImpl::UpdateGauges() {
  metrics_->SetSessions(static_cast<double>(registry_->size()),
                        static_cast<double>(registry_->total_points()));
}

grpc::Status KinetriServiceImpl::CreateSessionFromBytes(
    grpc::ServerContext* ctx, grpc::ServerReader<grpc::ByteBuffer>* reader,
    v1::Session* response) {
  auto tenant = Caller(*ctx);
  if (!tenant.ok()) return ToGrpc(tenant.status());
  v1::CreateSessionRequest msg;
  MessageReader<v1::CreateSessionRequest, grpc::ServerReader<grpc::ByteBuffer>>
      messages(reader);
  absl::StatusOr<bool> got = messages.Read(&msg);
  if (!got.ok()) return ToGrpc(got.status());
  if (!*got || !msg.has_header()) {
    return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                        "header: the first message must carry the "
                        "session header");
  }
  const v1::CreateSessionHeader header = msg.header();
  std::string id = header.session_id();
  if (id.empty()) {
    id = registry_->NewId();
  } else if (!ValidSessionId(id)) {
    return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                        absl::StrCat("header.session_id: \"", EchoForError(id),
                                     "\" must match [a-z0-9-]{1,63}"));
  }
  const ServerLimits& limits = registry_->limits();
  const v1::Backend asked = header.options().backend();
  if (asked == v1::BACKEND_CUDA && !limits.has_device) {
    return grpc::Status(
        grpc::StatusCode::FAILED_PRECONDITION,
        "header.options.backend: this server has no device executor (started "
        "without --device=emulated; the CUDA backend is refused for now, "
        "docs/DEVICE.md); use BACKEND_AUTO or BACKEND_CPU");
  }
  const bool on_device = limits.has_device && asked != v1::BACKEND_CPU;
  const std::string backend =
      on_device ? core::device::DeviceBackendName(limits.device) : "cpu";
  absl::Status st =
      registry_->CheckCapacity(header.point_count(), backend, *tenant);
  if (!st.ok()) return ToGrpc(st);
  const uint64_t device_bytes =
      on_device ? header.point_count() * core::device::kDeviceBytesPerPoint : 0;
  if (on_device &&
      device_bytes > core::device::DeviceFreeBytes(limits.device)) {
    return grpc::Status(
        grpc::StatusCode::RESOURCE_EXHAUSTED,
        absl::StrCat(
            "CreateSession of ", header.point_count(), " points needs ",
            device_bytes >> 20, " MiB of device memory; ",
            core::device::DeviceFreeBytes(limits.device) >> 20, " MiB free"));
  }
  // Admitted against the memory budget before any point is stored (with
  // the device executor's host memory, and the emulated device's memory,
  // which is host memory).
  auto memory = budget_->Reserve(
      header.point_count() * MemoryBudget::SessionBytesPerPoint(backend) +
          MemoryBudget::DeviceFixedBytes(backend),
      absl::StrCat("CreateSession of ", header.point_count(), " points"));
  if (!memory.ok()) return ToGrpc(memory.status());
  const bool client_ids =
      header.options().point_id_policy() == v1::POINT_ID_POLICY_CLIENT;
  // Memory follows the points received, not the announced count (a client
  // announcing 50M points and sending none holds nothing).
  std::vector<core::Vec2> points;
  std::vector<uint64_t> ids;
  uint64_t chunk = 0;
  IdleWatchdog::Registration idle(watchdog_, ctx);
  while (true) {
    got = messages.Read(&msg);
    if (!got.ok()) return ToGrpc(got.status());
    if (!*got) break;
    idle.Touch();
    if (ctx->IsCancelled()) {
      return grpc::Status(grpc::StatusCode::CANCELLED, "cancelled");
    }
    if (!msg.has_points()) {
      return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                          absl::StrCat("points: message ", chunk + 1,
                                       " after the header carries no points"));
    }
    const size_t before = points.size();
    st = AppendPoints(msg.points().xy(), absl::StrCat("points[", chunk, "].xy"),
                      &points);
    if (!st.ok()) return ToGrpc(st);
    if (client_ids) {
      if (static_cast<size_t>(msg.points().ids_size()) !=
          points.size() - before) {
        return grpc::Status(
            grpc::StatusCode::INVALID_ARGUMENT,
            absl::StrCat("points[", chunk, "].ids: ", msg.points().ids_size(),
                         " ids for ", points.size() - before,
                         " points (POINT_ID_POLICY_CLIENT names each point)"));
      }
      ids.insert(ids.end(), msg.points().ids().begin(),
                 msg.points().ids().end());
    } else if (msg.points().ids_size() > 0) {
      return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                          absl::StrCat("points[", chunk,
                                       "].ids: set only with "
                                       "POINT_ID_POLICY_CLIENT"));
    }
    if (points.size() > header.point_count()) {
      return grpc::Status(
          grpc::StatusCode::INVALID_ARGUMENT,
          absl::StrCat("points: more than header.point_count = ",
                       header.point_count(), " points sent"));
    }
    ++chunk;
  }
  if (idle.timed_out()) {
    return grpc::Status(
        grpc::StatusCode::CANCELLED,
        "points: the client sent nothing for longer than the server's "
        "--stream_idle_timeout_seconds; session not created");
  }
  if (points.size() != header.point_count()) {
    return grpc::Status(
        grpc::StatusCode::INVALID_ARGUMENT,
        absl::StrCat("points: ", points.size(), " points sent, header says ",
                     header.point_count()));
  }
  if (client_ids) {
    absl::flat_hash_map<uint64_t, uint64_t> seen;
    seen.reserve(ids.size());
    for (uint64_t i = 0; i < ids.size(); ++i) {
      auto [it, fresh] = seen.emplace(ids[i], i);
      if (!fresh) {
        return grpc::Status(
            grpc::StatusCode::INVALID_ARGUMENT,
            absl::StrCat("points.ids: id ", ids[i], " given to points ",
                         it->second, " and ", i));
      }
    }
  }
  core::TriangulationOptions opt;
  if (header.options().threads() > registry_->limits().max_threads) {
    return grpc::Status(
        grpc::StatusCode::INVALID_ARGUMENT,
        absl::StrCat("options.threads: ", header.options().threads(),
                     " exceeds the limit of ", registry_->limits().max_threads,
                     " (0 = the server's default)"));
  }
  const uint32_t threads = header.options().threads()
                               ? header.options().threads()
                               : registry_->limits().default_threads;
  opt.num_threads = static_cast<int>(threads);
  if (on_device) {
    opt.executor = core::Executor::kDevice;
    opt.device_backend = limits.device;
  }
  // A client that cancels (or whose deadline passes) while the
  // triangulation is built stops the build within tens of milliseconds.
  const core::CancelToken cancel(
      [this, ctx] { return stop_all_.load() || ctx->IsCancelled(); },
      ToSteadyDeadline(ctx->deadline()));
  auto tri = core::Triangulation::Create(points, opt, &cancel);
  if (!tri.ok()) return ToGrpc(tri.status());
  // A deadline that passed after the build's last poll: the client has
  // given up, so no session is added behind its back.
  if (absl::Status c = cancel.Check("creation"); !c.ok()) return ToGrpc(c);
  const uint64_t max_results =
      header.options().max_query_results()
          ? std::min(header.options().max_query_results(),
                     registry_->limits().max_query_results)
          : registry_->limits().max_query_results;
  constexpr uint64_t kMaxTtl = uint64_t{100} * 365 * 24 * 3600;
  if (header.options().idle_ttl_seconds() > kMaxTtl) {
    return grpc::Status(
        grpc::StatusCode::INVALID_ARGUMENT,
        absl::StrCat(
            "options.idle_ttl_seconds: ", header.options().idle_ttl_seconds(),
            " exceeds 100 years (0: the server's default)"));
  }
  auto session = std::make_shared<Session>(
      id, std::move(*tri), backend, max_results, threads,
      client_ids ? std::make_shared<const PointIdMap>(std::move(ids)) : nullptr,
      std::move(*memory), budget_);
  {
    Tenant t = *tenant;
    SessionRegistry* registry = registry_;
    session->set_growth_limits(limits.max_points_per_session,
                               [registry, t, backend](uint64_t more) {
                                 return registry->CheckGrowth(more, backend, t);
                               });
  }
  session->set_idle_ttl(header.options().idle_ttl_seconds() > 0
                            ? header.options().idle_ttl_seconds()
                            : limits.default_idle_ttl_seconds);
  std::optional<absl::MutexLock> create_lock;
  if (store_ != nullptr) {
    create_lock.emplace(&create_mu_);
    // Durable: the first snapshot is on disk before the session exists.
    if (registry_->Get(session->name(), tenant->name).ok()) {
      return grpc::Status(
          grpc::StatusCode::ALREADY_EXISTS,
          absl::StrCat("session_id: ", session->name(), " already exists"));
    }
    session->set_tenant(tenant->name);
    const Session::Snapshot snap = session->Read();
    auto journal = store_->Create(session->Meta(0), *snap.tri);
    if (!journal.ok()) {
      return ToGrpc(
          absl::Status(journal.status().code(),
                       absl::StrCat("session not created: cannot persist it: ",
                                    journal.status().message())));
    }
    session->AttachJournal(*std::move(journal));
    absl::MutexLock lock(&broken_mu_);
    broken_.erase(SessionStore::Key(tenant->name, session->id()));
  }
  // Again just before it becomes visible (persisting may take a while).
  if (absl::Status c = cancel.Check("creation"); !c.ok()) {
    if (store_ != nullptr) {
      session->journal()->Close();
      store_->Remove(tenant->name, session->id()).IgnoreError();
    }
    return ToGrpc(c);
  }
  auto added = registry_->Add(session, *tenant);
  if (!added.ok()) {
    if (store_ != nullptr &&
        added.status().code() != absl::StatusCode::kAlreadyExists) {
      session->journal()->Close();
      store_->Remove(tenant->name, session->id()).IgnoreError();
    }
    return ToGrpc(added.status());
  }
  *response = Describe(**added);
  UpdateGauges();
  return grpc::Status::OK;
}

grpc::Status KinetriServiceImpl::GetSession(grpc::ServerContext* ctx,
                                            const v1::GetSessionRequest* req,
                                            v1::Session* response) {
  auto tenant = Caller(*ctx);
  if (!tenant.ok()) return ToGrpc(tenant.status());
  auto s = Lookup(req->name(), tenant->name);
  if (!s.ok()) return ToGrpc(s.status());
  *response = Describe(**s);
  return grpc::Status::OK;
}

grpc::Status KinetriServiceImpl::ListSessions(
    grpc::ServerContext* ctx, const v1::ListSessionsRequest* req,
    v1::ListSessionsResponse* response) {
  auto tenant = Caller(*ctx);
  if (!tenant.ok()) return ToGrpc(tenant.status());
  if (req->page_size() < 0) {
    return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                        "page_size: must be >= 0");
  }
  const size_t page =
      req->page_size() == 0 ? 50 : std::min<size_t>(req->page_size(), 1000);
  std::string after;
  if (!req->page_token().empty()) {
    auto id = DecodePageToken(req->page_token());
    if (!id.ok()) return ToGrpc(id.status());
    after = *id;
  }
  auto list = registry_->List(after, page + 1, tenant->name);
  for (size_t i = 0; i < list.size() && i < page; ++i) {
    *response->add_sessions() = Describe(*list[i]);
  }
  if (list.size() > page) {
    response->set_next_page_token(EncodePageToken(list[page - 1]->id()));
  }
  return grpc::Status::OK;
}

grpc::Status KinetriServiceImpl::DeleteSession(
    grpc::ServerContext* ctx, const v1::DeleteSessionRequest* req,
    google::protobuf::Empty*) {
  auto tenant = Caller(*ctx);
  if (!tenant.ok()) return ToGrpc(tenant.status());
  auto session = Lookup(req->name(), tenant->name);
  if (!session.ok() && store_ != nullptr &&
      session.status().code() == absl::StatusCode::kDataLoss) {
    // A session whose snapshot is corrupt: deleting drops its files.
    auto id = ParseSessionName(req->name(), "name");
    if (!id.ok()) return ToGrpc(id.status());
    {
      absl::MutexLock lock(&broken_mu_);
      broken_.erase(SessionStore::Key(tenant->name, *id));
    }
    return ToGrpc(store_->Remove(tenant->name, *id));
  }
  const absl::Status st = registry_->Remove(req->name(), tenant->name);
  if (st.ok() && session.ok() && (*session)->journal() != nullptr) {
    (*session)->journal()->Close();
    store_->Remove(tenant->name, (*session)->id()).IgnoreError();
  }
  UpdateGauges();
  return ToGrpc(st);
}

grpc::Status KinetriServiceImpl::StreamStepsFromBytes(
    grpc::ServerContext* ctx,
    grpc::ServerReaderWriter<v1::StepResponse, grpc::ByteBuffer>* stream) {
  auto tenant = Caller(*ctx);
  if (!tenant.ok()) return ToGrpc(tenant.status());
  std::shared_ptr<Session> session;
  StepAssembler assembler;
  v1::StepRequest req;
  IdleWatchdog::Registration idle(watchdog_, ctx);
  MessageReader<v1::StepRequest,
                grpc::ServerReaderWriter<v1::StepResponse, grpc::ByteBuffer>>
      messages(stream);
  while (true) {
    absl::StatusOr<bool> got = messages.Read(&req);
    if (!got.ok()) {
      // Corrupt bytes: the open step (if any) is not applied; steps already
      // acknowledged stay.
      return ToGrpc(got.status());
    }
    if (!*got) break;
    idle.Touch();
    if (ctx->IsCancelled()) {
      return grpc::Status(grpc::StatusCode::CANCELLED, "cancelled");
    }
    if (!session) {
      if (req.session().empty()) {
        return grpc::Status(
            grpc::StatusCode::INVALID_ARGUMENT,
            "session: required on the first message of the stream");
      }
      auto s = Lookup(req.session(), tenant->name);
      if (!s.ok()) return ToGrpc(s.status());
      session = *s;
    } else if (!req.session().empty() && req.session() != session->name()) {
      return grpc::Status(
          grpc::StatusCode::INVALID_ARGUMENT,
          absl::StrCat("session: \"", req.session(), "\" differs from ",
                       session->name(), " used earlier on this stream"));
    }
    absl::Status st = assembler.Add(req);
    if (!st.ok()) return ToGrpc(st);
    // A step moves and removes each point at most once, and adds at most
    // the session's limit: a stream that never ends its step cannot make
    // the server buffer more than one step's worth.
    if (assembler.size() > session->point_count() ||
        assembler.removed() > session->point_count()) {
      return grpc::Status(
          grpc::StatusCode::INVALID_ARGUMENT,
          absl::StrCat("step ", assembler.step(), ": more than ",
                       session->point_count(),
                       " values or removed points (the session's point "
                       "count) before end_of_step; not applied"));
    }
    if (assembler.added() > registry_->limits().max_points_per_session) {
      return grpc::Status(
          grpc::StatusCode::RESOURCE_EXHAUSTED,
          absl::StrCat("step ", assembler.step(), ": more than ",
                       registry_->limits().max_points_per_session,
                       " points added (the limit per session); not applied"));
    }
    if (!req.end_of_step()) continue;
    const uint64_t step = assembler.step();
    const std::string request_id = assembler.request_id();
    absl::StatusOr<AssembledStep> batch = assembler.Take(*session);
    if (!batch.ok()) return ToGrpc(batch.status());
    v1::StepResponse resp;
    // A client that cancels (or whose deadline passes) mid-step stops it;
    // the session stays at its previous step.
    const core::CancelToken cancel(
        [this, ctx] { return stop_all_.load() || ctx->IsCancelled(); },
        ToSteadyDeadline(ctx->deadline()));
    bool replayed = false;
    auto report = session->ApplyStep(
        step, std::move(batch->batch),
        session->has_client_ids() ? &batch->client_ids : nullptr, &cancel,
        nullptr, request_id, &replayed);
    session->Touch();
    if (!report.ok()) return ToGrpc(report.status());
    // A resent step (same request_id) gets its original acknowledgement.
    if (!replayed) metrics_->ObserveStep(session->backend(), *report);
    resp.set_step(step);
    *resp.mutable_stats() = ToProto(*report);
    if (!session->has_client_ids() && report->added_points > 0) {
      resp.mutable_stats()->set_first_added_id(report->num_points -
                                               report->added_points);
    }
    if (!stream->Write(resp)) break;  // client went away; step is applied
  }
  if (idle.timed_out()) {
    return grpc::Status(
        grpc::StatusCode::CANCELLED,
        absl::StrCat(
            "the client sent nothing for longer than the server's "
            "--stream_idle_timeout_seconds",
            assembler.empty() ? "" : "; the open step was not applied"));
  }
  if (!assembler.empty()) {
    // The stream ended inside a step: it was never applied.
    return grpc::Status(
        grpc::StatusCode::INVALID_ARGUMENT,
        absl::StrCat("step ", assembler.step(),
                     ": stream ended before end_of_step; not applied"));
  }
  return grpc::Status::OK;
}

grpc::Status KinetriServiceImpl::QueryFromBytes(grpc::ServerContext* ctx,
                                                BytesStream* stream) {
  MessageReader<v1::QueryRequest, BytesStream> messages(stream);
  v1::QueryRequest req;
  absl::StatusOr<bool> got = messages.Read(&req);
  if (!got.ok()) return ToGrpc(got.status());
  if (!*got) {
    return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                        "Query: no query was sent");
  }
  return RunQuery(ctx, req, [stream](const grpc::ByteBuffer& b) {
    return stream->Write(b);
  });
}

grpc::Status KinetriServiceImpl::StreamQueryFromBytes(grpc::ServerContext* ctx,
                                                      BytesStream* stream) {
  auto tenant = Caller(*ctx);
  if (!tenant.ok()) return ToGrpc(tenant.status());
  // The first message is the query; the others add targets of the same
  // kind. Targets are held until the client half-closes: bounded by
  // --max_points and reserved from the memory budget as they arrive.
  v1::QueryRequest req, more;
  IdleWatchdog::Registration idle(watchdog_, ctx);
  MessageReader<v1::QueryRequest, BytesStream> messages(stream);
  absl::StatusOr<bool> got = messages.Read(&req);
  if (!got.ok()) return ToGrpc(got.status());
  if (!*got) {
    return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                        "StreamQuery: no query was sent");
  }
  if (!req.has_positions() && !req.has_point_ids()) {
    return grpc::Status(
        grpc::StatusCode::INVALID_ARGUMENT,
        "targets: StreamQuery streams positions or point_ids (all_points "
        "needs no stream: use Query)");
  }
  const uint64_t max_targets = registry_->limits().max_points_per_session;
  MemoryBudget::Reservation held;
  auto targets = [&] {
    return req.has_positions() ? uint64_t(req.positions().xy_size() / 2)
                               : uint64_t(req.point_ids().ids_size() +
                                          req.point_ids().client_ids_size());
  };
  while (true) {
    const uint64_t count = targets();
    if (count > max_targets) {
      return grpc::Status(
          grpc::StatusCode::RESOURCE_EXHAUSTED,
          absl::StrCat("targets: more than ", max_targets,
                       " in one query (the server's --max_points)"));
    }
    // 16 bytes per target held, 2x for the answer's bookkeeping.
    const uint64_t need = 32 * count;
    if (need > held.bytes()) {
      absl::Status r = budget_->GrowTo(
          &held, std::max<uint64_t>(need, held.bytes() + (8 << 20)),
          "StreamQuery targets");
      if (!r.ok()) return ToGrpc(r);
    }
    got = messages.Read(&more);
    if (!got.ok()) return ToGrpc(got.status());
    if (!*got) break;
    idle.Touch();
    if (ctx->IsCancelled()) {
      return grpc::Status(grpc::StatusCode::CANCELLED, "cancelled");
    }
    if (!more.session().empty() && more.session() != req.session()) {
      return grpc::Status(
          grpc::StatusCode::INVALID_ARGUMENT,
          "session: every message of a StreamQuery names the same session");
    }
    if (more.has_all_points() ||
        (req.has_positions() && more.has_point_ids()) ||
        (req.has_point_ids() && more.has_positions())) {
      return grpc::Status(
          grpc::StatusCode::INVALID_ARGUMENT,
          "targets: every message of a StreamQuery carries the same kind of "
          "targets as the first");
    }
    if (more.has_positions()) {
      if (more.positions().xy_size() % 2 != 0) {
        return grpc::Status(
            grpc::StatusCode::INVALID_ARGUMENT,
            absl::StrCat("positions.xy: ", more.positions().xy_size(),
                         " coordinates is odd (expected x, y pairs)"));
      }
      req.mutable_positions()->mutable_xy()->Add(more.positions().xy().begin(),
                                                 more.positions().xy().end());
    } else if (more.has_point_ids()) {
      req.mutable_point_ids()->mutable_ids()->Add(
          more.point_ids().ids().begin(), more.point_ids().ids().end());
      req.mutable_point_ids()->mutable_client_ids()->Add(
          more.point_ids().client_ids().begin(),
          more.point_ids().client_ids().end());
    }
  }
  if (idle.timed_out()) {
    return grpc::Status(grpc::StatusCode::CANCELLED,
                        "the client sent nothing for longer than the server's "
                        "--stream_idle_timeout_seconds");
  }
  return RunQuery(ctx, req, [stream](const grpc::ByteBuffer& b) {
    return stream->Write(b);
  });
}

grpc::Status KinetriServiceImpl::RunQuery(
    grpc::ServerContext* ctx, const v1::QueryRequest& request,
    const std::function<bool(const grpc::ByteBuffer&)>& write) {
  const v1::QueryRequest* req = &request;
  auto tenant = Caller(*ctx);
  if (!tenant.ok()) return (ToGrpc(tenant.status()));
  auto s = Lookup(req->session(), tenant->name);
  if (!s.ok()) return (ToGrpc(s.status()));
  Session& session = **s;
  std::string op;
  switch (req->kind()) {
    case v1::QUERY_KIND_NEAREST:
      op = "nearest";
      break;
    case v1::QUERY_KIND_K_NEAREST:
      op = "k_nearest";
      if (req->k() <= 0) {
        return (grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                             absl::StrCat("k: ", req->k(), " must be > 0")));
      }
      break;
    case v1::QUERY_KIND_RADIUS:
      op = "radius";
      break;
    default:
      return (grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                           "kind: must be NEAREST, K_NEAREST or RADIUS"));
  }
  std::vector<core::Vec2> positions;
  if (req->has_positions()) {
    absl::Status st =
        AppendPoints(req->positions().xy(), "positions.xy", &positions);
    if (!st.ok()) return (ToGrpc(st));
  } else if (!req->has_point_ids() && !req->has_all_points()) {
    return (
        grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                     "targets: set one of point_ids, positions, all_points"));
  }
  // The query stops within milliseconds once the client cancels or its
  // deadline passes (polled per row and inside long rows).
  const core::CancelToken cancel(
      [this, ctx] { return stop_all_.load() || ctx->IsCancelled(); },
      ToSteadyDeadline(ctx->deadline()));
  core::QueryLimits limits;
  limits.max_total_results = session.max_query_results();
  limits.cancel = &cancel;
  // The current step, immutable while this call holds it: no lock is held
  // while rows are computed or streamed, and steps never wait for them.
  const Session::Snapshot snap = session.Read();
  const core::Triangulation& t = *snap.tri;
  // An answer's memory is reserved from the budget before it is allocated:
  // the targets' ids here, each block's rows before they are computed and
  // its results as they are kept (core::QueryLimits::admit, per 256K).
  MemoryBudget::Reservation targets_memory;
  std::vector<uint32_t> ids;
  if (req->has_all_points()) {
    if (absl::Status s = budget_->GrowTo(&targets_memory,
                                         sizeof(uint32_t) * uint64_t{t.size()},
                                         "query targets");
        !s.ok()) {
      return ToGrpc(s);
    }
    ids.resize(t.size());
    for (uint32_t i = 0; i < t.size(); ++i) ids[i] = i;
  } else if (req->has_point_ids()) {
    auto resolved = ResolvePointIds(req->point_ids(), snap.ids.get());
    if (!resolved.ok()) return (ToGrpc(resolved.status()));
    ids = std::move(*resolved);
  }
  const bool by_id = !req->has_positions();
  const bool radius = req->kind() == v1::QUERY_KIND_RADIUS;
  const int k = req->kind() == v1::QUERY_KIND_K_NEAREST ? req->k() : 1;
  const uint64_t total_rows = by_id ? ids.size() : positions.size();
  // Every argument is checked on the whole request before any row is sent.
  {
    absl::Status st = by_id ? core::CheckQueryIds(t, ids)
                            : core::CheckQueryPositions(positions);
    if (st.ok() && radius) st = core::CheckQueryRadius(req->radius());
    if (!st.ok()) {
      if (st.code() == absl::StatusCode::kNotFound && req->has_point_ids()) {
        st = absl::NotFoundError(absl::StrCat("point_ids.", st.message()));
      }
      return (ToGrpc(st));
    }
  }
  const bool all_nearest = !radius && by_id && req->has_all_points() &&
                           k == 1 && req->exclude_self();
  if (!radius && !all_nearest &&
      static_cast<uint64_t>(k) * total_rows > limits.max_total_results) {
    return (
        grpc::Status(grpc::StatusCode::RESOURCE_EXHAUSTED,
                     absl::StrCat("k: ", k, " results for each of ", total_rows,
                                  " queries exceed the limit of ",
                                  limits.max_total_results)));
  }
  const uint32_t rows_per_chunk =
      req->rows_per_chunk() ? req->rows_per_chunk() : 16384;
  // At most 196608 results per message: 18 bytes each at worst (a client
  // id and a distance) keeps every message under 4 MiB.
  constexpr uint32_t kResultsPerChunk = 196608;
  const uint32_t results_per_chunk =
      req->results_per_chunk() == 0
          ? kResultsPerChunk
          : std::min(req->results_per_chunk(), kResultsPerChunk);
  // Rows are computed a block at a time and each block is sent before the
  // next is computed: memory follows the block, not the whole answer, and a
  // client that stops reading stops the computation (Write blocks under
  // flow control).
  const uint64_t block_rows = all_nearest
                                  ? std::max<uint64_t>(total_rows, 1)
                                  : std::max<uint64_t>(rows_per_chunk, 65536);
  const std::vector<uint64_t>* cids =
      snap.ids != nullptr ? &snap.ids->ids() : nullptr;
  uint64_t produced = 0;
  double compute_seconds = 0.0;
  for (uint64_t first = 0; first < total_rows || first == 0;
       first += block_rows) {
    const uint64_t count = std::min(block_rows, total_rows - first);
    // What is left of the answer's limit for this block (0: no limit). Once
    // earlier blocks used it all, the block may still answer rows without
    // results: it runs under a limit of 1, and any result is refused below.
    const uint64_t limit = session.max_query_results();
    limits.max_total_results =
        limit == 0 ? 0
                   : std::max<uint64_t>(limit - std::min(produced, limit), 1);
    absl::StatusOr<core::NeighborLists> result;
    const absl::Span<const uint32_t> id_block =
        by_id ? absl::MakeConstSpan(ids).subspan(first, count)
              : absl::Span<const uint32_t>();
    const absl::Span<const core::Vec2> pos_block =
        by_id ? absl::Span<const core::Vec2>()
              : absl::MakeConstSpan(positions).subspan(first, count);
    MemoryBudget::Reservation block_memory;
    const uint64_t row_bytes = count * MemoryBudget::kQueryBytesPerRow;
    const uint64_t result_bytes =
        MemoryBudget::QueryBytesPerResult(!radius || req->include_distances());
    // All nearest neighbours: one result per row, known now.
    if (absl::Status s = budget_->GrowTo(
            &block_memory, row_bytes + (all_nearest ? count * result_bytes : 0),
            "query rows");
        !s.ok()) {
      return ToGrpc(s);
    }
    bool memory_refused = false;
    limits.admit = [&](uint64_t results) {
      absl::Status s = budget_->GrowTo(
          &block_memory, row_bytes + results * result_bytes, "query answer");
      memory_refused = !s.ok();
      return s;
    };
    // The answer's chunks, each written (serialized) before it is sent.
    std::optional<ChunkCursor> chunks;
    grpc::ByteBuffer next_bytes;
    bool has_next = false;
    auto encode_next = [&] {
      // The chunk's bytes, written directly (no message object), handed
      // to gRPC without a copy.
      auto wire = std::make_unique<std::string>();
      has_next = chunks->NextBytes(wire.get());
      if (has_next) {
        std::string* owned = wire.release();
        grpc::Slice slice(
            owned->data(), owned->size(),
            [](void* s) { delete static_cast<std::string*>(s); }, owned);
        next_bytes = grpc::ByteBuffer(&slice, 1);
      }
    };
    auto compute = [&] {
      const auto start = Clock::now();
      if (radius) {
        core::RowOptions rows;
        rows.distances = req->include_distances();
        rows.batch_queries = total_rows;
        result = by_id ? core::WithinRadiusOfPoints(
                             t, id_block, req->radius(), req->exclude_self(),
                             req->max_results_per_row(), limits, rows)
                       : core::WithinRadius(t, pos_block, req->radius(),
                                            req->max_results_per_row(), limits,
                                            rows);
      } else if (all_nearest) {
        result = core::AllNearestNeighbors(t);
      } else {
        // The whole batch plans (a cell index for many rows, kept for
        // the step), not each block.
        core::RowOptions rows;
        rows.batch_queries = total_rows;
        result = by_id ? core::KNearestOfPoints(
                             t, id_block, k, req->exclude_self(), limits, rows)
                       : core::KNearest(t, pos_block, k, limits, rows);
      }
      compute_seconds +=
          std::chrono::duration<double>(Clock::now() - start).count();
      // The first chunk is written in the same turn on the query thread
      // (each hand-off to it and back costs a wake-up: about as much as
      // writing the chunk of 10K radius rows).
      if (result.ok()) {
        chunks.emplace(*result, count, first, total_rows, snap.step,
                       req->include_distances(), cids, rows_per_chunk,
                       results_per_chunk, req->encoding());
        encode_next();
      }
    };
    if (query_pool_ != nullptr) {
      // On the query threads, below the priority of steps; a call that is
      // cancelled while it waits for one is not computed.
      absl::Status waited = query_pool_->Run(cancel, "query", compute);
      if (!waited.ok()) return (ToGrpc(waited));
    } else {
      compute();
    }
    const bool over_limit =
        result.ok()
            ? limit != 0 && produced + result->ids.size() > limit
            : result.status().code() == absl::StatusCode::kResourceExhausted &&
                  !memory_refused;
    if (over_limit) {
      return (grpc::Status(
          grpc::StatusCode::RESOURCE_EXHAUSTED,
          absl::StrCat("query stopped: its rows hold more than ", limit,
                       " results in all (the limit); ask fewer targets, a "
                       "smaller k or radius, or set max_results_per_row")));
    }
    if (!result.ok()) return (ToGrpc(result.status()));
    produced += result->ids.size();
    // Later chunks are written on the query threads as well, one at a time
    // as the previous one is sent; this thread only hands the bytes to
    // gRPC.
    while (has_next) {
      if (ctx->IsCancelled()) {
        return grpc::Status(grpc::StatusCode::CANCELLED, "cancelled");
      }
      const grpc::ByteBuffer bytes = std::move(next_bytes);
      if (!write(bytes)) {
        return grpc::Status(grpc::StatusCode::CANCELLED,
                            "the client stopped reading");
      }
      if (chunks->done()) break;
      if (query_pool_ != nullptr) {
        absl::Status waited = query_pool_->Run(cancel, "query", encode_next);
        if (!waited.ok()) return (ToGrpc(waited));
      } else {
        encode_next();
      }
    }
    if (total_rows == 0) break;
  }
  metrics_->ObserveQuery(op, session.backend(), compute_seconds);
  return grpc::Status::OK;
}

grpc::Status KinetriServiceImpl::ExportTriangulation(
    grpc::ServerContext* ctx, const v1::ExportTriangulationRequest* req,
    grpc::ServerWriter<v1::ExportTriangulationResponse>* writer) {
  auto tenant = Caller(*ctx);
  if (!tenant.ok()) return ToGrpc(tenant.status());
  auto s = Lookup(req->session(), tenant->name);
  if (!s.ok()) return ToGrpc(s.status());
  // Streamed from the step's snapshot, held to the end (a step meanwhile
  // builds on a copy, or waits if the budget has no room for one, as it
  // does for a query): nothing is copied but the chunk being written, and
  // the call checks for cancellation at least every 1M triangle slots.
  const Session::Snapshot snap = (*s)->Read();
  const core::Triangulation& tri = *snap.tri;
  // A reader that stops reading holds the snapshot: cancelled once no
  // message has gone out for --stream_idle_timeout_seconds.
  IdleWatchdog::Registration idle(watchdog_, ctx);
  constexpr uint32_t kPollSlots = 1u << 20;
  const uint32_t slots = tri.num_triangle_slots();
  uint64_t total_triangles = 0;
  for (uint32_t lo = 0; lo < slots; lo += std::min(kPollSlots, slots - lo)) {
    if (ctx->IsCancelled()) {
      return grpc::Status(grpc::StatusCode::CANCELLED, "cancelled");
    }
    total_triangles +=
        tri.CountTriangles(lo, lo + std::min(kPollSlots, slots - lo));
  }
  static const std::vector<uint64_t> kNoIds;
  const std::vector<uint64_t>& cids =
      snap.ids != nullptr ? snap.ids->ids() : kNoIds;
  // At most 100000 points and triangles per message (under 4 MiB).
  constexpr size_t kMaxPerChunk = 100000;
  const size_t per =
      req->triangles_per_chunk()
          ? std::min<size_t>(req->triangles_per_chunk(), kMaxPerChunk)
          : kMaxPerChunk;
  const size_t num_points = tri.size();
  size_t p = 0;
  uint64_t t = 0;
  uint32_t slot = 0;
  std::vector<std::array<uint32_t, 3>> tris;
  do {
    if (ctx->IsCancelled()) {
      return grpc::Status(grpc::StatusCode::CANCELLED, "cancelled");
    }
    v1::ExportTriangulationResponse r;
    r.set_step(snap.step);
    r.set_first_point(p);
    r.set_total_points(num_points);
    r.set_total_triangles(total_triangles);
    const size_t pend = std::min(num_points, p + per);
    for (; p < pend; ++p) {
      const core::Vec2 xy = tri.Position(static_cast<uint32_t>(p));
      r.add_xy(xy.x);
      r.add_xy(xy.y);
      if (!cids.empty()) r.add_point_ids(cids[p]);
    }
    tris.clear();
    while (tris.size() < per && slot < slots) {
      // A bounded stretch of slots per poll, also through free runs.
      const uint32_t before = slot;
      tri.AppendTriangles(&slot, per - tris.size(), &tris);
      if (slot == before) break;
      if (ctx->IsCancelled()) {
        return grpc::Status(grpc::StatusCode::CANCELLED, "cancelled");
      }
    }
    for (const auto& tr : tris) {
      for (uint32_t v : tr) r.add_triangles(v);
    }
    t += tris.size();
    if (!writer->Write(r)) break;
    idle.Touch();
  } while (p < num_points || (t < total_triangles && slot < slots));
  if (idle.timed_out()) {
    return grpc::Status(grpc::StatusCode::CANCELLED,
                        "the client stopped reading for longer than "
                        "--stream_idle_timeout_seconds");
  }
  return grpc::Status::OK;
}

}  // namespace kinetri::server
