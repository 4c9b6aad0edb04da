// The one place where protobuf messages and core types are converted.
#ifndef KINETRI_SERVER_CONVERT_H_
#define KINETRI_SERVER_CONVERT_H_

#include <cstdint>
#include <functional>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "core/queries.h"
#include "core/triangulation.h"
#include "kinetri/v1/kinetri.pb.h"
#include "server/session_registry.h"

namespace kinetri::server {

// Appends interleaved xy pairs to `out`; INVALID_ARGUMENT (naming `field`)
// for an odd count.
absl::Status AppendPoints(const google::protobuf::RepeatedField<double>& xy,
                          const std::string& field,
                          std::vector<core::Vec2>* out);

// One step as received: the core batch (dense ids) and, for
// POINT_ID_POLICY_CLIENT sessions, the client ids it names (resolved by
// Session::ApplyStep against the step before).
struct AssembledStep {
  core::DisplacementBatch batch;
  StepClientIds client_ids;
};

// Accumulates the chunks of one step into a core batch.
class StepAssembler {
 public:
  // Adds one chunk; the first chunk fixes mode and dense/sparse.
  absl::Status Add(const v1::StepRequest& chunk);
  bool empty() const { return chunks_ == 0; }
  // Values (xy pairs) received so far for this step.
  uint64_t size() const { return values_.size(); }
  // Points removed and added so far in this step.
  uint64_t removed() const {
    return remove_ids_.size() + remove_client_ids_.size();
  }
  uint64_t added() const { return add_.size(); }
  uint64_t step() const { return step_; }
  // The step's request_id ("" if none was sent).
  const std::string& request_id() const { return request_id_; }
  // The assembled step (INVALID_ARGUMENT for the wrong kind of ids for the
  // session's policy); resets the assembler.
  absl::StatusOr<AssembledStep> Take(const Session& session);

 private:
  uint64_t chunks_ = 0;
  uint64_t step_ = 0;
  std::string request_id_;
  bool sparse_ = false;
  bool moves_seen_ = false;  // a chunk of this step carried moves
  v1::DisplacementMode mode_ = v1::DISPLACEMENT_MODE_DELTA;
  bool client_ = false;
  std::vector<uint32_t> ids_;
  std::vector<uint64_t> client_ids_;
  std::vector<core::Vec2> values_;
  std::vector<uint32_t> remove_ids_;
  std::vector<uint64_t> remove_client_ids_;
  std::vector<core::Vec2> add_;
  std::vector<uint64_t> add_client_ids_;
};

v1::StepStats ToProto(const core::StepReport& report);

// Cuts rows [0, count) of `lists` (rows global_first.. of an answer of
// total_rows rows) into response chunks of at most `rows_per_chunk` rows
// and `results_per_chunk` results: whole rows while they fit, a row with
// more results split across chunks (last_row_continues). Each chunk is
// built only when Next() is called (the answer is never held twice). With
// client_ids, result ids are the client's ids. `encoding` picks the
// fields of offsets and ids: fixed-width for ANSWER_ENCODING_FIXED,
// varints for any other value (one this server does not know included:
// every client reads varints).
class ChunkCursor {
 public:
  ChunkCursor(const core::NeighborLists& lists, uint64_t count,
              uint64_t global_first, uint64_t total_rows, uint64_t step,
              bool distances, const std::vector<uint64_t>* client_ids,
              uint64_t rows_per_chunk, uint64_t results_per_chunk,
              v1::AnswerEncoding encoding = v1::ANSWER_ENCODING_VARINT);
  // Writes the next chunk, a serialized QueryResponse, into *bytes (there
  // is always a first one, possibly with no rows); false once every chunk
  // has been written. The bytes are those protobuf writes for the message
  // (tests/server/convert_test.cc), but no message is built: copying the
  // rows into repeated fields and serializing those took 1.2-2 ms for the
  // 10K radius rows of kinetri-bench-service, a fifth of the query.
  bool NextBytes(std::string* bytes);
  // Whether every chunk has been written.
  bool done() const { return done_; }

 private:
  // The rows and results of the next chunk.
  struct Cut {
    uint64_t rows = 0;
    uint64_t end = 0;  // one past its last result
    bool continues = false;
  };
  Cut NextCut() const;
  void Advance(const Cut& cut);

  const core::NeighborLists& lists_;
  const uint64_t count_, global_first_, total_rows_, step_;
  const bool distances_;
  const bool fixed_;
  const std::vector<uint64_t>* client_ids_;
  const uint64_t rows_per_chunk_, results_per_chunk_;
  uint64_t row_ = 0;    // first row of the next chunk
  uint64_t start_ = 0;  // its first result
  bool done_ = false;
};

// Query targets of a PointIds message: client ids resolved through `ids`
// (POINT_ID_POLICY_CLIENT sessions), else sequential ids.
absl::StatusOr<std::vector<uint32_t>> ResolvePointIds(const v1::PointIds& ids,
                                                      const PointIdMap* map);

}  // namespace kinetri::server

#endif  // KINETRI_SERVER_CONVERT_H_
