// POINT_ID_POLICY_CLIENT sessions: the client's 64-bit id of each point and
// back.
#include "server/point_id_map.h"

#include <utility>

#include "absl/strings/str_cat.h"

namespace kinetri::server {

PointIdMap::PointIdMap(std::vector<uint64_t> ids) : ids_(std::move(ids)) {
  index_.reserve(ids_.size());
  for (uint32_t i = 0; i < ids_.size(); ++i) index_.emplace(ids_[i], i);
}

absl::StatusOr<uint32_t> PointIdMap::IndexOf(uint64_t id,
                                             const std::string& field) const {
  auto it = index_.find(id);
  if (it == index_.end()) {
    return absl::NotFoundError(
        absl::StrCat(field, " = ", id, ": no such point"));
  }
  return it->second;
}

absl::StatusOr<std::shared_ptr<const PointIdMap>> PointIdMap::After(
    const std::vector<uint32_t>& removed,
    const std::vector<uint64_t>& added) const {
  std::vector<uint8_t> gone(ids_.size(), 0);
  for (uint32_t i : removed) gone[i] = 1;
  absl::flat_hash_map<uint64_t, size_t> fresh;
  fresh.reserve(added.size());
  for (size_t j = 0; j < added.size(); ++j) {
    auto [it, inserted] = fresh.emplace(added[j], j);
    if (!inserted) {
      return absl::InvalidArgumentError(absl::StrCat(
          "add_client_ids[", j, "] = ", added[j],
          " appears twice (also add_client_ids[", it->second, "])"));
    }
    auto old = index_.find(added[j]);
    if (old != index_.end() && !gone[old->second]) {
      return absl::AlreadyExistsError(absl::StrCat(
          "add_client_ids[", j, "] = ", added[j],
          ": the session already has a point with this id (remove it in the "
          "same step to replace it)"));
    }
  }
  std::vector<uint64_t> ids;
  ids.reserve(ids_.size() - removed.size() + added.size());
  for (size_t i = 0; i < ids_.size(); ++i) {
    if (!gone[i]) ids.push_back(ids_[i]);
  }
  ids.insert(ids.end(), added.begin(), added.end());
  return std::make_shared<const PointIdMap>(std::move(ids));
}

}  // namespace kinetri::server
