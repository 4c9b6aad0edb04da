// C++ client for kinetri.v1.KinetriService: hides chunking, streaming and
// CSR reassembly. Depends only on the generated proto/ code.
#include "client/cpp/kinetri_client.h"

#include <algorithm>
#include <cstdlib>
#include <fstream>
#include <random>
#include <sstream>

#include "absl/strings/str_cat.h"
#include "absl/strings/string_view.h"
#include "client/cpp/answer_reader.h"

namespace kinetri {

absl::Status FromGrpc(const grpc::Status& s) {
  if (s.ok()) return absl::OkStatus();
  return absl::Status(static_cast<absl::StatusCode>(s.error_code()),
                      s.error_message());
}

namespace {

std::string Env(const char* name) {
  const char* v = std::getenv(name);
  return v != nullptr ? v : "";
}

// "/kinetri.v1.KinetriService/<method>", alive for the process (an
// RpcMethod keeps the pointer).
const char* MethodName(absl::string_view method) {
  static const auto* const names = new std::vector<std::string>{
      absl::StrCat("/", v1::KinetriService::service_full_name(), "/Query"),
      absl::StrCat("/", v1::KinetriService::service_full_name(),
                   "/StreamQuery")};
  return method == "Query" ? (*names)[0].c_str() : (*names)[1].c_str();
}

absl::StatusOr<std::string> ReadFile(const std::string& path,
                                     const char* what) {
  std::ifstream in(path, std::ios::binary);
  if (!in) {
    return absl::FailedPreconditionError(
        absl::StrCat(what, ": cannot read ", path));
  }
  std::ostringstream out;
  out << in.rdbuf();
  return out.str();
}

}  // namespace

std::string SessionRoutingKey(const std::string& name) {
  constexpr std::string_view kPrefix = "sessions/";
  std::string key = name.compare(0, kPrefix.size(), kPrefix) == 0
                        ? name.substr(kPrefix.size())
                        : name;
  // Only what can be a session id ([a-z0-9-]{1,63}); anything else is
  // refused by the server, and a huge name must not become a huge header.
  if (key.empty() || key.size() > 63) return "";
  for (const char c : key) {
    if (!((c >= 'a' && c <= 'z') || (c >= '0' && c <= '9') || c == '-')) {
      return "";
    }
  }
  return key;
}

std::string NewSessionId() {
  std::random_device device;  // getrandom(2) on Linux
  std::string id = "s-";
  constexpr char kHex[] = "0123456789abcdef";
  for (int i = 0; i < 4; ++i) {
    const uint32_t word = device();
    for (int shift = 28; shift >= 0; shift -= 4)
      id += kHex[(word >> shift) & 15];
  }
  return id;
}

ClientSecurity ClientSecurity::FromEnvironment() {
  ClientSecurity s;
  s.token = Env("KINETRI_TOKEN");
  s.ca_file = Env("KINETRI_CA");
  s.cert_file = Env("KINETRI_CERT");
  s.key_file = Env("KINETRI_KEY");
  s.server_name = Env("KINETRI_TLS_SERVER_NAME");
  return s;
}

Client::Client(const std::string& target, size_t chunk_points,
               const ClientSecurity& security)
    : token_(security.token), chunk_points_(std::max<size_t>(1, chunk_points)) {
  grpc::ChannelArguments args;
  args.SetMaxReceiveMessageSize(64 * 1024 * 1024);
  std::shared_ptr<grpc::ChannelCredentials> credentials =
      grpc::InsecureChannelCredentials();
  if (!security.ca_file.empty() || !security.cert_file.empty()) {
    grpc::SslCredentialsOptions ssl;
    if (!security.ca_file.empty()) {
      auto ca = ReadFile(security.ca_file, "CA file (KINETRI_CA)");
      if (ca.ok()) ssl.pem_root_certs = *ca;
      init_status_.Update(ca.status());
    }
    if (!security.cert_file.empty() || !security.key_file.empty()) {
      auto cert = ReadFile(security.cert_file, "client certificate");
      auto key = ReadFile(security.key_file, "client key");
      if (cert.ok() && key.ok()) {
        ssl.pem_cert_chain = *cert;
        ssl.pem_private_key = *key;
      }
      init_status_.Update(cert.status());
      init_status_.Update(key.status());
    }
    credentials = grpc::SslCredentials(ssl);
    if (!security.server_name.empty()) {
      args.SetSslTargetNameOverride(security.server_name);
    }
  }
  channel_ = grpc::CreateCustomChannel(target, credentials, args);
  stub_ = v1::KinetriService::NewStub(channel_);
  query_method_ = std::make_unique<grpc::internal::RpcMethod>(
      MethodName("Query"), grpc::internal::RpcMethod::SERVER_STREAMING,
      channel_);
  stream_query_method_ = std::make_unique<grpc::internal::RpcMethod>(
      MethodName("StreamQuery"), grpc::internal::RpcMethod::BIDI_STREAMING,
      channel_);
}

void Client::Prepare(grpc::ClientContext* ctx,
                     const std::string& session) const {
  if (!token_.empty()) ctx->AddMetadata("authorization", "Bearer " + token_);
  const std::string key = SessionRoutingKey(session);
  if (!key.empty()) ctx->AddMetadata(kSessionHeader, key);
}

absl::StatusOr<v1::Session> Client::CreateSession(
    const std::vector<double>& xy, const v1::SessionOptions& options,
    const std::string& session_id) {
  return CreateSessionWithIds(xy, {}, options, session_id);
}

absl::StatusOr<v1::Session> Client::CreateSessionWithIds(
    const std::vector<double>& xy, const std::vector<uint64_t>& client_ids,
    v1::SessionOptions options, const std::string& session_id) {
  if (!client_ids.empty()) {
    options.set_point_id_policy(v1::POINT_ID_POLICY_CLIENT);
    if (client_ids.size() * 2 != xy.size()) {
      return absl::InvalidArgumentError("client_ids: one id per point");
    }
  }
  if (xy.size() % 2) {
    return absl::InvalidArgumentError("xy: odd number of coordinates");
  }
  if (!init_status_.ok()) return init_status_;
  const std::string id = session_id.empty() ? NewSessionId() : session_id;
  grpc::ClientContext ctx;
  Prepare(&ctx, id);
  v1::Session session;
  auto writer = stub_->CreateSession(&ctx, &session);
  v1::CreateSessionRequest head;
  head.mutable_header()->set_session_id(id);
  *head.mutable_header()->mutable_options() = options;
  head.mutable_header()->set_point_count(xy.size() / 2);
  bool ok = writer->Write(head);
  const size_t step = 2 * chunk_points_;
  for (size_t i = 0; ok && i < xy.size(); i += step) {
    v1::CreateSessionRequest chunk;
    const size_t end = std::min(xy.size(), i + step);
    chunk.mutable_points()->mutable_xy()->Add(xy.begin() + i, xy.begin() + end);
    if (!client_ids.empty()) {
      chunk.mutable_points()->mutable_ids()->Add(client_ids.begin() + i / 2,
                                                 client_ids.begin() + end / 2);
    }
    ok = writer->Write(chunk);
  }
  writer->WritesDone();
  const grpc::Status st = writer->Finish();
  if (!st.ok()) return FromGrpc(st);
  return session;
}

absl::StatusOr<v1::Session> Client::GetSession(const std::string& name) {
  if (!init_status_.ok()) return init_status_;
  grpc::ClientContext ctx;
  Prepare(&ctx, name);
  v1::GetSessionRequest req;
  req.set_name(name);
  v1::Session s;
  const grpc::Status st = stub_->GetSession(&ctx, req, &s);
  if (!st.ok()) return FromGrpc(st);
  return s;
}

absl::StatusOr<std::vector<v1::Session>> Client::ListSessions() {
  std::vector<v1::Session> out;
  std::string token;
  do {
    if (!init_status_.ok()) return init_status_;
    grpc::ClientContext ctx;
    Prepare(&ctx);
    v1::ListSessionsRequest req;
    req.set_page_size(100);
    req.set_page_token(token);
    v1::ListSessionsResponse resp;
    const grpc::Status st = stub_->ListSessions(&ctx, req, &resp);
    if (!st.ok()) return FromGrpc(st);
    for (auto& s : *resp.mutable_sessions()) out.push_back(std::move(s));
    token = resp.next_page_token();
  } while (!token.empty());
  return out;
}

absl::Status Client::DeleteSession(const std::string& name) {
  if (!init_status_.ok()) return init_status_;
  grpc::ClientContext ctx;
  Prepare(&ctx, name);
  v1::DeleteSessionRequest req;
  req.set_name(name);
  google::protobuf::Empty empty;
  return FromGrpc(stub_->DeleteSession(&ctx, req, &empty));
}

absl::StatusOr<std::unique_ptr<StepStream>> Client::OpenSteps(
    const std::string& name, uint64_t first_step) {
  if (first_step == 0) {
    auto s = GetSession(name);
    if (!s.ok()) return s.status();
    first_step = s->step() + 1;
  }
  return std::make_unique<StepStream>(stub_.get(), name, first_step,
                                      2 * chunk_points_, token_);
}

namespace {

// Reads a query's answer (Query or StreamQuery) into CSR rows.
template <typename Reader>
absl::StatusOr<Neighbors> ReadAnswer(Reader* reader, grpc::ClientContext* ctx) {
  AnswerReader answer;
  grpc::ByteBuffer chunk;
  while (reader->Read(&chunk)) {
    if (absl::Status s = answer.Append(chunk); !s.ok()) {
      ctx->TryCancel();
      reader->Finish();
      return s;
    }
  }
  const grpc::Status st = reader->Finish();
  if (!st.ok()) return FromGrpc(st);
  return std::move(answer).Take();
}

}  // namespace

absl::StatusOr<Neighbors> Client::Query(const v1::QueryRequest& request) {
  if (!init_status_.ok()) return init_status_;
  // Answers in fixed-width fields unless the request names an encoding.
  const bool default_encoding =
      request.encoding() == v1::ANSWER_ENCODING_UNSPECIFIED;
  grpc::ClientContext ctx;
  Prepare(&ctx, request.session());
  // Values (coordinates or ids) per message: chunk_points positions.
  const size_t per = 2 * std::max<size_t>(chunk_points_, 1);
  const bool positions = request.has_positions();
  const size_t targets = positions ? request.positions().xy_size()
                         : request.has_point_ids()
                             ? request.point_ids().ids_size() +
                                   request.point_ids().client_ids_size()
                             : 0;
  if (targets <= per) {
    // (A copy of at most one message's targets, to name the encoding.)
    v1::QueryRequest named;
    if (default_encoding) {
      named = request;
      named.set_encoding(v1::ANSWER_ENCODING_FIXED);
    }
    std::unique_ptr<grpc::ClientReader<grpc::ByteBuffer>> reader(
        grpc::internal::ClientReaderFactory<grpc::ByteBuffer>::Create(
            channel_.get(), *query_method_, &ctx,
            default_encoding ? named : request));
    return ReadAnswer(reader.get(), &ctx);
  }
  // More targets than one message should carry: StreamQuery, the query
  // and its first targets first, the rest in messages of `per` values.
  std::unique_ptr<grpc::ClientReaderWriter<v1::QueryRequest, grpc::ByteBuffer>>
      stream(grpc::internal::ClientReaderWriterFactory<
             v1::QueryRequest, grpc::ByteBuffer>::Create(channel_.get(),
                                                         *stream_query_method_,
                                                         &ctx));
  for (size_t i = 0; i < targets; i += per) {
    const size_t end = std::min(targets, i + per);
    v1::QueryRequest part;
    if (i == 0) {
      part = request;
      if (default_encoding) part.set_encoding(v1::ANSWER_ENCODING_FIXED);
      if (positions) {
        part.mutable_positions()->mutable_xy()->Truncate(static_cast<int>(end));
      } else {
        auto* ids = part.mutable_point_ids();
        ids->clear_ids();
        ids->clear_client_ids();
      }
    }
    if (positions) {
      if (i > 0) {
        part.mutable_positions()->mutable_xy()->Add(
            request.positions().xy().begin() + i,
            request.positions().xy().begin() + end);
      }
    } else {
      const auto& all = request.point_ids();
      auto* ids = part.mutable_point_ids();
      if (all.ids_size() > 0) {
        ids->mutable_ids()->Add(all.ids().begin() + i, all.ids().begin() + end);
      } else {
        ids->mutable_client_ids()->Add(all.client_ids().begin() + i,
                                       all.client_ids().begin() + end);
      }
    }
    if (!stream->Write(part)) break;
  }
  stream->WritesDone();
  return ReadAnswer(stream.get(), &ctx);
}

namespace {
v1::QueryRequest Base(const std::string& name, v1::QueryKind kind) {
  v1::QueryRequest r;
  r.set_session(name);
  r.set_kind(kind);
  r.set_include_distances(true);
  r.set_encoding(v1::ANSWER_ENCODING_FIXED);
  return r;
}
}  // namespace

absl::StatusOr<Neighbors> Client::NearestOfAll(const std::string& name) {
  v1::QueryRequest r = Base(name, v1::QUERY_KIND_NEAREST);
  r.mutable_all_points();
  r.set_exclude_self(true);
  return Query(r);
}

absl::StatusOr<Neighbors> Client::KNearest(const std::string& name,
                                           const std::vector<double>& xy,
                                           int k) {
  v1::QueryRequest r = Base(name, v1::QUERY_KIND_K_NEAREST);
  r.set_k(k);
  r.mutable_positions()->mutable_xy()->Add(xy.begin(), xy.end());
  return Query(r);
}

absl::StatusOr<Neighbors> Client::KNearestOfPoints(
    const std::string& name, const std::vector<uint32_t>& ids, int k,
    bool exclude_self) {
  v1::QueryRequest r = Base(name, v1::QUERY_KIND_K_NEAREST);
  r.set_k(k);
  r.set_exclude_self(exclude_self);
  r.mutable_point_ids()->mutable_ids()->Add(ids.begin(), ids.end());
  return Query(r);
}

absl::StatusOr<Neighbors> Client::WithinRadius(const std::string& name,
                                               const std::vector<double>& xy,
                                               double radius,
                                               uint32_t max_per_row) {
  v1::QueryRequest r = Base(name, v1::QUERY_KIND_RADIUS);
  r.set_radius(radius);
  r.set_max_results_per_row(max_per_row);
  r.mutable_positions()->mutable_xy()->Add(xy.begin(), xy.end());
  return Query(r);
}

absl::StatusOr<Neighbors> Client::WithinRadiusOfPoints(
    const std::string& name, const std::vector<uint32_t>& ids, double radius,
    bool exclude_self, uint32_t max_per_row) {
  v1::QueryRequest r = Base(name, v1::QUERY_KIND_RADIUS);
  r.set_radius(radius);
  r.set_exclude_self(exclude_self);
  r.set_max_results_per_row(max_per_row);
  r.mutable_point_ids()->mutable_ids()->Add(ids.begin(), ids.end());
  return Query(r);
}

absl::StatusOr<Mesh> Client::Export(const std::string& name) {
  if (!init_status_.ok()) return init_status_;
  grpc::ClientContext ctx;
  Prepare(&ctx, name);
  v1::ExportTriangulationRequest req;
  req.set_session(name);
  auto reader = stub_->ExportTriangulation(&ctx, req);
  Mesh mesh;
  v1::ExportTriangulationResponse chunk;
  while (reader->Read(&chunk)) {
    mesh.step = chunk.step();
    mesh.xy.insert(mesh.xy.end(), chunk.xy().begin(), chunk.xy().end());
    mesh.triangles.insert(mesh.triangles.end(), chunk.triangles().begin(),
                          chunk.triangles().end());
    mesh.point_ids.insert(mesh.point_ids.end(), chunk.point_ids().begin(),
                          chunk.point_ids().end());
  }
  const grpc::Status st = reader->Finish();
  if (!st.ok()) return FromGrpc(st);
  return mesh;
}

StepStream::StepStream(v1::KinetriService::Stub* stub, std::string session,
                       uint64_t first_step, size_t chunk_values,
                       const std::string& token)
    : session_(std::move(session)),
      next_step_(first_step),
      chunk_values_(std::max<size_t>(2, chunk_values & ~size_t{1})) {
  if (!token.empty()) ctx_.AddMetadata("authorization", "Bearer " + token);
  const std::string key = SessionRoutingKey(session_);
  if (!key.empty()) ctx_.AddMetadata(kSessionHeader, key);
  stream_ = stub->StreamSteps(&ctx_);
}

StepStream::~StepStream() {
  if (!finished_) {
    ctx_.TryCancel();
    stream_->Finish().ok();
  }
}

absl::StatusOr<v1::StepResponse> StepStream::MoveBy(
    const std::vector<double>& dxy) {
  return Send(v1::DISPLACEMENT_MODE_DELTA, {}, dxy);
}

absl::StatusOr<v1::StepResponse> StepStream::MoveBy(
    const std::vector<uint32_t>& ids, const std::vector<double>& dxy) {
  return Send(v1::DISPLACEMENT_MODE_DELTA, ids, dxy);
}

absl::StatusOr<v1::StepResponse> StepStream::MoveByClientIds(
    const std::vector<uint64_t>& client_ids, const std::vector<double>& dxy) {
  return Send(v1::DISPLACEMENT_MODE_DELTA, {}, dxy, &client_ids);
}

absl::StatusOr<v1::StepResponse> StepStream::MoveTo(
    const std::vector<uint32_t>& ids, const std::vector<double>& xy) {
  return Send(v1::DISPLACEMENT_MODE_ABSOLUTE, ids, xy);
}

absl::StatusOr<v1::StepResponse> StepStream::Change(PointChanges changes) {
  next_changes_ = std::move(changes);
  return Send(v1::DISPLACEMENT_MODE_DELTA, {}, {});
}

absl::StatusOr<v1::StepResponse> StepStream::Send(
    v1::DisplacementMode mode, const std::vector<uint32_t>& ids,
    const std::vector<double>& xy, const std::vector<uint64_t>* client_ids) {
  if (finished_) return absl::FailedPreconditionError("stream finished");
  if (client_ids != nullptr && client_ids->size() * 2 != xy.size()) {
    return absl::InvalidArgumentError("xy: one (x, y) pair per client id");
  }
  if (!ids.empty() && ids.size() * 2 != xy.size()) {
    return absl::InvalidArgumentError(
        absl::StrCat("xy: ", xy.size(), " values for ", ids.size(), " ids"));
  }
  PointChanges changes = std::move(next_changes_);
  next_changes_ = {};
  if (changes.add_xy.size() % 2 != 0) {
    return absl::InvalidArgumentError(absl::StrCat(
        "add_xy: ", changes.add_xy.size(), " values is odd (x, y pairs)"));
  }
  if (!changes.add_client_ids.empty() &&
      2 * changes.add_client_ids.size() != changes.add_xy.size()) {
    return absl::InvalidArgumentError(
        absl::StrCat("add_client_ids: ", changes.add_client_ids.size(),
                     " ids for ", changes.add_xy.size() / 2, " points"));
  }
  // The moves first, then the leaving and joining points, each list cut
  // into chunks of at most chunk_values_ values.
  std::vector<v1::StepRequest> chunks;
  auto chunk = [&]() -> v1::StepRequest& {
    chunks.emplace_back();
    chunks.back().set_step(next_step_);
    chunks.back().set_mode(mode);
    return chunks.back();
  };
  for (size_t i = 0; i < xy.size(); i += chunk_values_) {
    v1::StepRequest& req = chunk();
    const size_t end = std::min(xy.size(), i + chunk_values_);
    req.mutable_xy()->Add(xy.begin() + i, xy.begin() + end);
    if (!ids.empty()) {
      req.mutable_ids()->Add(ids.begin() + i / 2, ids.begin() + end / 2);
    }
    if (client_ids != nullptr) {
      req.mutable_client_ids()->Add(client_ids->begin() + i / 2,
                                    client_ids->begin() + end / 2);
    }
  }
  for (size_t i = 0; i < changes.remove_ids.size(); i += chunk_values_) {
    const size_t end = std::min(changes.remove_ids.size(), i + chunk_values_);
    chunk().mutable_remove_ids()->Add(changes.remove_ids.begin() + i,
                                      changes.remove_ids.begin() + end);
  }
  for (size_t i = 0; i < changes.remove_client_ids.size(); i += chunk_values_) {
    const size_t end =
        std::min(changes.remove_client_ids.size(), i + chunk_values_);
    chunk().mutable_remove_client_ids()->Add(
        changes.remove_client_ids.begin() + i,
        changes.remove_client_ids.begin() + end);
  }
  for (size_t i = 0; i < changes.add_xy.size(); i += chunk_values_) {
    v1::StepRequest& req = chunk();
    const size_t end = std::min(changes.add_xy.size(), i + chunk_values_);
    req.mutable_add_xy()->Add(changes.add_xy.begin() + i,
                              changes.add_xy.begin() + end);
    if (!changes.add_client_ids.empty()) {
      req.mutable_add_client_ids()->Add(
          changes.add_client_ids.begin() + i / 2,
          changes.add_client_ids.begin() + end / 2);
    }
  }
  if (chunks.empty()) chunk();
  chunks.front().set_session(session_);
  chunks.front().set_request_id(next_request_id_);
  chunks.back().set_end_of_step(true);
  for (const v1::StepRequest& req : chunks) {
    if (!stream_->Write(req)) break;
  }
  next_request_id_.clear();
  v1::StepResponse resp;
  if (!stream_->Read(&resp)) {
    finished_ = true;
    stream_->WritesDone();
    const grpc::Status st = stream_->Finish();
    return st.ok() ? absl::UnavailableError("step stream closed by the server")
                   : FromGrpc(st);
  }
  ++next_step_;
  return resp;
}

absl::Status StepStream::Finish() {
  if (finished_) return absl::OkStatus();
  finished_ = true;
  stream_->WritesDone();
  return FromGrpc(stream_->Finish());
}

}  // namespace kinetri
