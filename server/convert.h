// The one place where protobuf messages and core types are converted.
#ifndef KINETRI_SERVER_CONVERT_H_
#define KINETRI_SERVER_CONVERT_H_

#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "core/queries.h"
#include "core/triangulation.h"
#include "kinetri/v1/kinetri.pb.h"

namespace kinetri::server {

// Appends interleaved xy pairs to `out`; INVALID_ARGUMENT (naming `field`)
// for an odd count.
absl::Status AppendPoints(const google::protobuf::RepeatedField<double>& xy,
                          const std::string& field,
                          std::vector<core::Vec2>* out);

// Accumulates the chunks of one step into a core batch.
class StepAssembler {
 public:
  // Adds one chunk; the first chunk fixes mode and dense/sparse.
  absl::Status Add(const v1::StepRequest& chunk);
  bool empty() const { return chunks_ == 0; }
  uint64_t step() const { return step_; }
  // The assembled batch; resets the assembler.
  core::DisplacementBatch Take();

 private:
  uint64_t chunks_ = 0;
  uint64_t step_ = 0;
  bool sparse_ = false;
  v1::DisplacementMode mode_ = v1::DISPLACEMENT_MODE_DELTA;
  std::vector<uint32_t> ids_;
  std::vector<core::Vec2> values_;
};

v1::StepStats ToProto(const core::StepReport& report);

// Splits CSR rows [0, n) into response chunks of at most `rows_per_chunk`.
std::vector<v1::QueryResponse> ToChunks(const core::NeighborLists& lists,
                                        uint64_t step, bool distances,
                                        uint32_t rows_per_chunk);

}  // namespace kinetri::server

#endif  // KINETRI_SERVER_CONVERT_H_
