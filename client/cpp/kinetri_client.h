// C++ client for kinetri.v1.KinetriService: hides chunking, streaming and
// CSR reassembly. Depends only on the generated proto/ code.
#ifndef KINETRI_CLIENT_CPP_KINETRI_CLIENT_H_
#define KINETRI_CLIENT_CPP_KINETRI_CLIENT_H_

#include <grpcpp/grpcpp.h>

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "kinetri/v1/kinetri.grpc.pb.h"

namespace kinetri {

// Results of a query: row i holds ids[offsets[i] .. offsets[i+1]).
struct Neighbors {
  uint64_t step = 0;  // the state that answered
  std::vector<uint64_t> offsets;
  std::vector<uint32_t> ids;
  std::vector<double> distances;  // empty unless requested
  std::vector<uint64_t> truncated_rows;
  // POINT_ID_POLICY_CLIENT sessions: neighbours as client ids (ids empty).
  std::vector<uint64_t> client_ids;
  size_t rows() const { return offsets.empty() ? 0 : offsets.size() - 1; }
};

struct Mesh {
  uint64_t step = 0;
  std::vector<double> xy;           // interleaved positions, by id
  std::vector<uint32_t> triangles;  // index triples, counter-clockwise
  std::vector<uint64_t> point_ids;  // client ids of the positions, if any
};

// Points that leave and join with a step (after its moves; see
// StepRequest). Sequential sessions name leaving points in remove_ids and
// number joining points after the others (StepStats.first_added_id);
// POINT_ID_POLICY_CLIENT sessions use remove_client_ids and name each
// joining point in add_client_ids.
struct PointChanges {
  std::vector<uint32_t> remove_ids;
  std::vector<uint64_t> remove_client_ids;
  std::vector<double> add_xy;  // interleaved x, y
  std::vector<uint64_t> add_client_ids;
  bool empty() const {
    return remove_ids.empty() && remove_client_ids.empty() && add_xy.empty();
  }
};

// Sends one batch per simulation step on a long-lived stream.
class StepStream {
 public:
  // `token`: bearer token for the call ("" for none). The call carries
  // the session's routing header (see kSessionHeader).
  StepStream(v1::KinetriService::Stub* stub, std::string session,
             uint64_t first_step, size_t chunk_values,
             const std::string& token = "");
  ~StepStream();

  // Dense displacements (one x, y pair per point, in id order).
  absl::StatusOr<v1::StepResponse> MoveBy(const std::vector<double>& dxy);
  // Sparse displacements.
  absl::StatusOr<v1::StepResponse> MoveBy(const std::vector<uint32_t>& ids,
                                          const std::vector<double>& dxy);
  // Sparse displacements naming points by client id
  // (POINT_ID_POLICY_CLIENT sessions).
  absl::StatusOr<v1::StepResponse> MoveByClientIds(
      const std::vector<uint64_t>& client_ids, const std::vector<double>& dxy);
  // Absolute positions (dense if ids is empty).
  absl::StatusOr<v1::StepResponse> MoveTo(const std::vector<uint32_t>& ids,
                                          const std::vector<double>& xy);
  // Points leave and join with the next step (sent with its moves).
  void SetNextChanges(PointChanges changes) {
    next_changes_ = std::move(changes);
  }
  // A step in which points only leave and join (nothing moves).
  absl::StatusOr<v1::StepResponse> Change(PointChanges changes);
  // Names the next step (StepRequest.request_id): resending a step the
  // server already applied under this name (its acknowledgement was lost)
  // returns the original acknowledgement and applies nothing.
  void SetNextRequestId(std::string request_id) {
    next_request_id_ = std::move(request_id);
  }
  // Half-closes the stream and returns its final status.
  absl::Status Finish();
  uint64_t next_step() const { return next_step_; }

 private:
  absl::StatusOr<v1::StepResponse> Send(
      v1::DisplacementMode mode, const std::vector<uint32_t>& ids,
      const std::vector<double>& xy,
      const std::vector<uint64_t>* client_ids = nullptr);
  grpc::ClientContext ctx_;
  std::unique_ptr<grpc::ClientReaderWriter<v1::StepRequest, v1::StepResponse>>
      stream_;
  std::string session_;
  uint64_t next_step_;
  size_t chunk_values_;
  PointChanges next_changes_;
  std::string next_request_id_;
  bool finished_ = false;
};

// How a client proves who it is and checks the server (docs/SECURITY.md).
struct ClientSecurity {
  std::string token;        // bearer token sent with every call
  std::string ca_file;      // TLS when set: PEM CA bundle the server's
                            // certificate must chain to
  std::string cert_file;    // PEM client certificate (mutual TLS)
  std::string key_file;     // its private key
  std::string server_name;  // expected name in the server's certificate
                            // (default: the target's host)
  // From KINETRI_TOKEN, KINETRI_CA, KINETRI_CERT, KINETRI_KEY and
  // KINETRI_TLS_SERVER_NAME (unset: empty, i.e. plaintext, no token).
  static ClientSecurity FromEnvironment();
};

// Every call about one session carries its id in this header, so that a
// proxy in front of several servers (nginx `hash $http_kinetri_session
// consistent`, deploy/README.md) sends all of a session's calls, its
// creation included, to the replica that owns it.
inline constexpr char kSessionHeader[] = "kinetri-session";

// The routing key of a session: its id ("sessions/{id}" -> "{id}"); "" (no
// header) for what cannot be a session id ([a-z0-9-]{1,63}).
std::string SessionRoutingKey(const std::string& name);

// A new session id, as the server would make one: "s-" + 128 random bits in
// hex. CreateSession uses it when the caller names no session, so that the
// creation is routed by the same key as every later call.
std::string NewSessionId();

class Client {
 public:
  // target: "host:port". Points per message chunk: 1/4 of the 4 MiB limit.
  // Unreadable TLS files make every call fail with FAILED_PRECONDITION.
  explicit Client(
      const std::string& target, size_t chunk_points = 131072,
      const ClientSecurity& security = ClientSecurity::FromEnvironment());

  // An empty session_id gets NewSessionId().
  absl::StatusOr<v1::Session> CreateSession(const std::vector<double>& xy,
                                            const v1::SessionOptions& options,
                                            const std::string& session_id = "");
  // POINT_ID_POLICY_CLIENT: names point i `client_ids[i]`.
  absl::StatusOr<v1::Session> CreateSessionWithIds(
      const std::vector<double>& xy, const std::vector<uint64_t>& client_ids,
      v1::SessionOptions options, const std::string& session_id = "");
  absl::StatusOr<v1::Session> GetSession(const std::string& name);
  // The sessions of the server this client reaches (behind a proxy: of the
  // replica that calls without a session header go to).
  absl::StatusOr<std::vector<v1::Session>> ListSessions();
  absl::Status DeleteSession(const std::string& name);

  // Opens a step stream that continues after the session's current step,
  // or at `first_step` (e.g. to resend a step whose acknowledgement was
  // lost, under its request id).
  absl::StatusOr<std::unique_ptr<StepStream>> OpenSteps(
      const std::string& name, uint64_t first_step = 0);

  // Runs a query (its targets and options set by the caller) and collects
  // every chunk. Targets beyond one message (chunk_points positions or
  // 2 x chunk_points ids) go by StreamQuery, cut into messages. The answer
  // comes in fixed-width fields (ANSWER_ENCODING_FIXED: cheaper to write
  // and read) unless the request names an encoding; either is read.
  // The other calls below ask for distances and fixed-width answers.
  absl::StatusOr<Neighbors> Query(const v1::QueryRequest& request);
  absl::StatusOr<Neighbors> NearestOfAll(const std::string& name);
  absl::StatusOr<Neighbors> KNearest(const std::string& name,
                                     const std::vector<double>& xy, int k);
  absl::StatusOr<Neighbors> KNearestOfPoints(const std::string& name,
                                             const std::vector<uint32_t>& ids,
                                             int k, bool exclude_self);
  absl::StatusOr<Neighbors> WithinRadius(const std::string& name,
                                         const std::vector<double>& xy,
                                         double r, uint32_t max_per_row = 0);
  absl::StatusOr<Neighbors> WithinRadiusOfPoints(
      const std::string& name, const std::vector<uint32_t>& ids, double r,
      bool exclude_self, uint32_t max_per_row = 0);

  absl::StatusOr<Mesh> Export(const std::string& name);

  v1::KinetriService::Stub* stub() { return stub_.get(); }
  // Adds the bearer token, and the routing header of `session` (a name or
  // id; "" for calls about no session), to a context made for stub().
  void Prepare(grpc::ClientContext* ctx, const std::string& session = "") const;

 private:
  absl::Status init_status_;  // TLS files that could not be read
  std::string token_;
  std::shared_ptr<grpc::Channel> channel_;
  std::unique_ptr<v1::KinetriService::Stub> stub_;
  // Query and StreamQuery with the answer's chunks as bytes (decoded by
  // AnswerReader instead of protobuf's parser).
  std::unique_ptr<const grpc::internal::RpcMethod> query_method_;
  std::unique_ptr<const grpc::internal::RpcMethod> stream_query_method_;
  size_t chunk_points_;
};

// grpc::Status -> absl::Status (same code and message).
absl::Status FromGrpc(const grpc::Status& s);

}  // namespace kinetri

#endif  // KINETRI_CLIENT_CPP_KINETRI_CLIENT_H_
