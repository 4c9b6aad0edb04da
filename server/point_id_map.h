// POINT_ID_POLICY_CLIENT sessions: the client's 64-bit id of each point and
// back.
#ifndef KINETRI_SERVER_POINT_ID_MAP_H_
#define KINETRI_SERVER_POINT_ID_MAP_H_

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "absl/container/flat_hash_map.h"
#include "absl/status/statusor.h"

namespace kinetri::server {

// The client ids a step of a POINT_ID_POLICY_CLIENT session names: points
// that move (StepRequest.client_ids), leave and join.
struct StepClientIds {
  std::vector<uint64_t> moved;
  std::vector<uint64_t> removed;
  std::vector<uint64_t> added;
};

// Immutable: a step whose points join or leave makes a new map, and readers
// of the step before keep the old one with their snapshot.
class PointIdMap {
 public:
  // `ids`: one distinct id per point, in the core's (dense) order.
  explicit PointIdMap(std::vector<uint64_t> ids);

  const std::vector<uint64_t>& ids() const { return ids_; }
  size_t size() const { return ids_.size(); }
  // NOT_FOUND naming `field` when the id is unknown.
  absl::StatusOr<uint32_t> IndexOf(uint64_t id, const std::string& field) const;
  // The map after the points at `removed` (dense indices, distinct) leave
  // and points with the ids `added` join: the remaining ids keep their
  // order, the added ones follow (core::DisplacementBatch's numbering).
  // ALREADY_EXISTS for an added id held by a point that stays;
  // INVALID_ARGUMENT for an id added twice.
  absl::StatusOr<std::shared_ptr<const PointIdMap>> After(
      const std::vector<uint32_t>& removed,
      const std::vector<uint64_t>& added) const;

 private:
  std::vector<uint64_t> ids_;
  absl::flat_hash_map<uint64_t, uint32_t> index_;
};

}  // namespace kinetri::server

#endif  // KINETRI_SERVER_POINT_ID_MAP_H_
