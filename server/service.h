// gRPC implementation of kinetri.v1.KinetriService over the core.
#ifndef KINETRI_SERVER_SERVICE_H_
#define KINETRI_SERVER_SERVICE_H_

#include <atomic>
#include <functional>
#include <memory>
#include <string>

#include "absl/container/flat_hash_map.h"
#include "absl/synchronization/mutex.h"
#include "kinetri/v1/kinetri.grpc.pb.h"
#include "server/auth.h"
#include "server/idle_watchdog.h"
#include "server/memory_budget.h"
#include "server/metrics.h"
#include "server/persistence.h"
#include "server/query_pool.h"
#include "server/session_registry.h"

namespace kinetri::server {

// The gRPC service's full name (health checks may name it).
inline constexpr char kServiceName[] = "kinetri.v1.KinetriService";

class KinetriServiceImpl final : public v1::KinetriService::Service {
 public:
  // `watchdog` cancels step and creation streams that stop sending;
  // `budget` admits creations and step copies before they allocate.
  // `auth` (optional): bearer tokens and tenants; null: authentication
  // off.
  KinetriServiceImpl(SessionRegistry* registry, Metrics* metrics,
                     IdleWatchdog* watchdog, MemoryBudget* budget,
                     const TokenAuth* auth = nullptr);

  // Durable sessions: restores every session in `store` (before the server
  // starts serving) and persists new sessions and steps there from now on.
  struct RestoreReport {
    size_t sessions = 0;
    size_t unavailable = 0;
    uint64_t steps_replayed = 0;
    uint64_t journal_bytes_cut = 0;
    double seconds = 0.0;
  };
  RestoreReport EnableDurability(SessionStore* store);
  // Deletes the sessions whose idle TTL has passed (files included);
  // returns how many. The server calls it every second.
  size_t ExpireIdleSessions();
  // Durable sessions: snapshots every session whose journal has steps
  // (after the drain at shutdown); returns how many were written and
  // reports failures on stderr (their journals stay valid).
  size_t CheckpointAll();
  // Stops the work of every call in progress (their cancellation tokens
  // fire), for a shutdown whose grace has passed: gRPC's synchronous
  // handlers see a server-side cancellation only at their next read or
  // write, which a query computing a block of rows may not reach for
  // seconds.
  void StopAllWork() { stop_all_ = true; }
  // Query rows are computed on `pool` (server/query_pool.h: lower priority
  // than steps) from now on; null (the default): on the handler's thread.
  // Set before the server starts.
  void SetQueryPool(QueryPool* pool) { query_pool_ = pool; }

  // The streaming RPCs read their requests as bytes (server/message_reader.h:
  // a corrupt message is an error, never a clean end of the stream); the
  // constructor registers these in place of the generated typed handlers.
  grpc::Status CreateSessionFromBytes(
      grpc::ServerContext* ctx, grpc::ServerReader<grpc::ByteBuffer>* reader,
      v1::Session* response);
  grpc::Status GetSession(grpc::ServerContext* ctx,
                          const v1::GetSessionRequest* request,
                          v1::Session* response) override;
  grpc::Status ListSessions(grpc::ServerContext* ctx,
                            const v1::ListSessionsRequest* request,
                            v1::ListSessionsResponse* response) override;
  grpc::Status DeleteSession(grpc::ServerContext* ctx,
                             const v1::DeleteSessionRequest* request,
                             google::protobuf::Empty* response) override;
  grpc::Status StreamStepsFromBytes(
      grpc::ServerContext* ctx,
      grpc::ServerReaderWriter<v1::StepResponse, grpc::ByteBuffer>* stream);
  // Query and StreamQuery read and write bytes: their answers' chunks are
  // encoded on the query pool's threads.
  using BytesStream =
      grpc::ServerReaderWriter<grpc::ByteBuffer, grpc::ByteBuffer>;
  grpc::Status QueryFromBytes(grpc::ServerContext* ctx, BytesStream* stream);
  grpc::Status StreamQueryFromBytes(grpc::ServerContext* ctx,
                                    BytesStream* stream);
  grpc::Status ExportTriangulation(
      grpc::ServerContext* ctx, const v1::ExportTriangulationRequest* request,
      grpc::ServerWriter<v1::ExportTriangulationResponse>* writer) override;

 private:
  void UpdateGauges();
  // Query's work for a whole request (its targets assembled): checks, then
  // rows computed a block at a time and handed to `write` in chunks (false:
  // the client went away).
  grpc::Status RunQuery(
      grpc::ServerContext* ctx, const v1::QueryRequest& request,
      const std::function<bool(const grpc::ByteBuffer&)>& write);
  // registry_->Get, or DATA_LOSS for a session whose files are corrupt.
  absl::StatusOr<std::shared_ptr<Session>> Lookup(
      const std::string& name, const std::string& tenant) const;
  // The caller's tenant; UNAUTHENTICATED without a valid token.
  absl::StatusOr<Tenant> Caller(const grpc::ServerContext& ctx) const;

  SessionRegistry* registry_;
  Metrics* metrics_;
  IdleWatchdog* watchdog_;
  MemoryBudget* budget_;
  const TokenAuth* auth_;
  std::atomic<bool> stop_all_{false};
  QueryPool* query_pool_ = nullptr;
  SessionStore* store_ = nullptr;
  // Durable creations one at a time: the existence check, the first
  // snapshot and the registration must not interleave for one name.
  absl::Mutex create_mu_;
  mutable absl::Mutex broken_mu_;
  // "tenant@id" -> why it cannot be restored.
  absl::flat_hash_map<std::string, std::string> broken_
      ABSL_GUARDED_BY(broken_mu_);
};

}  // namespace kinetri::server

#endif  // KINETRI_SERVER_SERVICE_H_
