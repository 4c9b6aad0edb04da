// The one place where protobuf messages and core types are converted.
#include "server/convert.h"

#include "absl/strings/str_cat.h"

namespace kinetri::server {

absl::Status AppendPoints(const google::protobuf::RepeatedField<double>& xy,
                          const std::string& field,
                          std::vector<core::Vec2>* out) {
  if (xy.size() % 2 != 0) {
    return absl::InvalidArgumentError(absl::StrCat(
        field, ": ", xy.size(), " coordinates is odd (expected x, y pairs)"));
  }
  out->reserve(out->size() + xy.size() / 2);
  for (int i = 0; i < xy.size(); i += 2) out->push_back({xy[i], xy[i + 1]});
  return absl::OkStatus();
}

absl::Status StepAssembler::Add(const v1::StepRequest& chunk) {
  const v1::DisplacementMode mode =
      chunk.mode() == v1::DISPLACEMENT_MODE_UNSPECIFIED
          ? v1::DISPLACEMENT_MODE_DELTA
          : chunk.mode();
  if (chunk.ids_size() > 0 && chunk.client_ids_size() > 0) {
    return absl::InvalidArgumentError(
        "ids, client_ids: a chunk names points with one of them, not both");
  }
  if (chunk.request_id().size() > 128) {
    return absl::InvalidArgumentError(absl::StrCat(
        "request_id: ", chunk.request_id().size(), " bytes; at most 128"));
  }
  if (!chunk.request_id().empty()) {
    if (!request_id_.empty() && chunk.request_id() != request_id_) {
      return absl::InvalidArgumentError("request_id: changes within one step");
    }
    request_id_ = chunk.request_id();
  }
  const bool client = chunk.client_ids_size() > 0;
  const bool sparse = chunk.ids_size() > 0 || client;
  // (Chunks with only points that leave or join carry no moves: the first
  // chunk with moves says whether the step is dense or sparse.)
  const bool moves = chunk.xy_size() > 0 || chunk.ids_size() > 0 ||
                     chunk.client_ids_size() > 0;
  if (moves && !moves_seen_) {
    moves_seen_ = true;
    sparse_ = sparse;
    client_ = client;
  } else if (moves && sparse != sparse_) {
    return absl::InvalidArgumentError(
        "ids: a step is either dense (no ids) or sparse (ids in every "
        "chunk)");
  }
  if (chunks_ == 0) {
    step_ = chunk.step();
    mode_ = mode;
  } else {
    if (chunk.step() != step_) {
      return absl::InvalidArgumentError(
          absl::StrCat("step: chunk of step ", chunk.step(), " inside step ",
                       step_, " (send end_of_step on the last chunk)"));
    }
    if (mode != mode_) {
      return absl::InvalidArgumentError("mode: changes within one step");
    }
  }
  const size_t before = values_.size();
  absl::Status s = AppendPoints(chunk.xy(), "xy", &values_);
  if (!s.ok()) return s;
  s = AppendPoints(chunk.add_xy(), "add_xy", &add_);
  if (!s.ok()) return s;
  remove_ids_.insert(remove_ids_.end(), chunk.remove_ids().begin(),
                     chunk.remove_ids().end());
  remove_client_ids_.insert(remove_client_ids_.end(),
                            chunk.remove_client_ids().begin(),
                            chunk.remove_client_ids().end());
  add_client_ids_.insert(add_client_ids_.end(), chunk.add_client_ids().begin(),
                         chunk.add_client_ids().end());
  if (sparse_ && moves) {
    if (client != client_) {
      return absl::InvalidArgumentError(
          "client_ids: every chunk of a step uses the same kind of ids");
    }
    const size_t named = client ? chunk.client_ids_size() : chunk.ids_size();
    if (named != values_.size() - before) {
      return absl::InvalidArgumentError(
          absl::StrCat(client ? "client_ids: " : "ids: ", named, " ids for ",
                       values_.size() - before, " xy pairs in a chunk"));
    }
    if (client) {
      client_ids_.insert(client_ids_.end(), chunk.client_ids().begin(),
                         chunk.client_ids().end());
    } else {
      ids_.insert(ids_.end(), chunk.ids().begin(), chunk.ids().end());
    }
  }
  ++chunks_;
  return absl::OkStatus();
}

absl::StatusOr<AssembledStep> StepAssembler::Take(const Session& session) {
  const bool client = client_;
  AssembledStep out;
  std::vector<uint64_t> client_ids = std::move(client_ids_);
  client_ids_.clear();
  client_ = false;
  sparse_ = false;
  moves_seen_ = false;
  std::vector<uint32_t> remove_ids = std::move(remove_ids_);
  std::vector<uint64_t> remove_client_ids = std::move(remove_client_ids_);
  std::vector<uint64_t> add_client_ids = std::move(add_client_ids_);
  remove_ids_.clear();
  remove_client_ids_.clear();
  add_client_ids_.clear();
  core::DisplacementBatch& b = out.batch;
  b.add = std::move(add_);
  add_.clear();
  b.mode = mode_ == v1::DISPLACEMENT_MODE_ABSOLUTE
               ? core::DisplacementBatch::Mode::kAbsolute
               : core::DisplacementBatch::Mode::kDelta;
  b.ids = std::move(ids_);
  b.values = std::move(values_);
  ids_.clear();
  values_.clear();
  chunks_ = 0;
  request_id_.clear();
  if (client && !session.has_client_ids()) {
    return absl::InvalidArgumentError(
        "client_ids: this session numbers points sequentially; use ids");
  }
  if (!b.ids.empty() && session.has_client_ids()) {
    return absl::InvalidArgumentError(
        "ids: this session uses client ids (POINT_ID_POLICY_CLIENT); use "
        "client_ids");
  }
  if (session.has_client_ids()) {
    if (!remove_ids.empty()) {
      return absl::InvalidArgumentError(
          "remove_ids: this session uses client ids (POINT_ID_POLICY_CLIENT); "
          "use remove_client_ids");
    }
    if (add_client_ids.size() != b.add.size()) {
      return absl::InvalidArgumentError(absl::StrCat(
          "add_client_ids: ", add_client_ids.size(), " ids for ", b.add.size(),
          " added points (POINT_ID_POLICY_CLIENT names each point)"));
    }
    out.client_ids.moved = std::move(client_ids);
    out.client_ids.removed = std::move(remove_client_ids);
    out.client_ids.added = std::move(add_client_ids);
  } else {
    if (!remove_client_ids.empty() || !add_client_ids.empty()) {
      return absl::InvalidArgumentError(
          "remove_client_ids, add_client_ids: this session numbers points "
          "sequentially; use remove_ids (added points are numbered after "
          "the others)");
    }
    b.remove = std::move(remove_ids);
  }
  return out;
}

absl::StatusOr<std::vector<uint32_t>> ResolvePointIds(const v1::PointIds& ids,
                                                      const PointIdMap* map) {
  if (map != nullptr) {
    if (ids.ids_size() > 0) {
      return absl::InvalidArgumentError(
          "point_ids.ids: this session uses client ids; use "
          "point_ids.client_ids");
    }
    std::vector<uint32_t> out(ids.client_ids_size());
    for (int i = 0; i < ids.client_ids_size(); ++i) {
      auto in = map->IndexOf(ids.client_ids(i),
                             absl::StrCat("point_ids.client_ids[", i, "]"));
      if (!in.ok()) return in.status();
      out[i] = *in;
    }
    return out;
  }
  if (ids.client_ids_size() > 0) {
    return absl::InvalidArgumentError(
        "point_ids.client_ids: this session numbers points sequentially");
  }
  return std::vector<uint32_t>(ids.ids().begin(), ids.ids().end());
}

v1::StepStats ToProto(const core::StepReport& r) {
  v1::StepStats s;
  s.set_path(core::UpdatePathName(r.path));
  s.set_moved_points(r.moved_points);
  s.set_substeps(r.substeps);
  s.set_reinserted(r.reinserted);
  s.set_interior_fix_flips(r.flips.interior_fix);
  s.set_hull_absorb_flips(r.flips.hull_absorb);
  s.set_hull_release_flips(r.flips.hull_release);
  s.set_delaunay_flips(r.flips.delaunay);
  s.set_fallback_reason(r.fallback_reason);
  s.set_update_seconds(r.seconds);
  s.set_removed_points(r.removed_points);
  s.set_point_count(r.num_points);
  s.set_added_points(r.added_points);
  return s;
}

ChunkCursor::ChunkCursor(const core::NeighborLists& lists, uint64_t count,
                         uint64_t global_first, uint64_t total_rows,
                         uint64_t step, bool distances,
                         const std::vector<uint64_t>* client_ids,
                         uint64_t rows_per_chunk, uint64_t results_per_chunk)
    : lists_(lists),
      count_(count),
      global_first_(global_first),
      total_rows_(total_rows),
      step_(step),
      distances_(distances),
      client_ids_(client_ids),
      rows_per_chunk_(std::max<uint64_t>(rows_per_chunk, 1)),
      results_per_chunk_(std::max<uint64_t>(results_per_chunk, 1)),
      start_(count > 0 ? lists.offsets[0] : 0) {}

bool ChunkCursor::Next(v1::QueryResponse* r) {
  if (done_) return false;
  const auto& off = lists_.offsets;
  r->Clear();
  r->set_step(step_);
  r->set_first_row(global_first_ + row_);
  r->set_total_rows(total_rows_);
  r->add_offsets(0);
  const uint64_t limit = start_ + results_per_chunk_;
  uint64_t end = start_;  // one past the chunk's last result
  uint64_t rows = 0;
  while (row_ + rows < count_ && rows < rows_per_chunk_ &&
         off[row_ + rows + 1] <= limit) {
    end = off[row_ + rows + 1];
    r->add_offsets(end - start_);
    if (lists_.truncated[row_ + rows]) r->add_truncated_rows(rows);
    ++rows;
  }
  if (rows == 0 && row_ < count_) {
    // The row does not fit: as much of it as does, continued next.
    end = limit;
    r->add_offsets(end - start_);
    r->set_last_row_continues(true);
  }
  if (client_ids_ != nullptr) {
    for (uint64_t k = start_; k < end; ++k) {
      r->add_client_ids((*client_ids_)[lists_.ids[k]]);
    }
  } else {
    r->mutable_ids()->Add(lists_.ids.begin() + start_,
                          lists_.ids.begin() + end);
  }
  if (distances_) {
    r->mutable_distances()->Add(lists_.distances.begin() + start_,
                                lists_.distances.begin() + end);
  }
  row_ += rows;
  start_ = end;
  done_ = row_ >= count_;
  return true;
}

}  // namespace kinetri::server
