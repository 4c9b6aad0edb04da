// The one place where protobuf messages and core types are converted.
#include "server/convert.h"

#include <algorithm>
#include <bit>
#include <cassert>
#include <cstdint>
#include <cstring>
#include <string>

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
                         uint64_t rows_per_chunk, uint64_t results_per_chunk,
                         v1::AnswerEncoding encoding)
    : lists_(lists),
      count_(count),
      global_first_(global_first),
      total_rows_(total_rows),
      step_(step),
      distances_(distances),
      fixed_(encoding == v1::ANSWER_ENCODING_FIXED),
      client_ids_(client_ids),
      rows_per_chunk_(std::max<uint64_t>(rows_per_chunk, 1)),
      // Offsets within a chunk are written as 32-bit varints.
      results_per_chunk_(
          std::clamp<uint64_t>(results_per_chunk, 1, uint64_t{UINT32_MAX})),
      start_(count > 0 ? lists.offsets[0] : 0) {}

ChunkCursor::Cut ChunkCursor::NextCut() const {
  const auto& off = lists_.offsets;
  const uint64_t limit = start_ + results_per_chunk_;
  Cut cut;
  cut.end = start_;
  while (row_ + cut.rows < count_ && cut.rows < rows_per_chunk_ &&
         off[row_ + cut.rows + 1] <= limit) {
    cut.end = off[row_ + cut.rows + 1];
    ++cut.rows;
  }
  if (cut.rows == 0 && row_ < count_) {
    // The row does not fit: as much of it as does, continued next.
    cut.end = limit;
    cut.continues = true;
  }
  return cut;
}

void ChunkCursor::Advance(const Cut& cut) {
  row_ += cut.rows;
  start_ = cut.end;
  done_ = row_ >= count_;
}

namespace {

// Protocol-buffer wire format: varints, tags and packed fields.
inline size_t VarintSize(uint64_t v) {
  // Bits used (1 for 0) -> ceil(bits / 7), as protobuf computes it: no
  // branch per byte (the values of an answer have mixed lengths).
  const uint32_t log2 = 63 - static_cast<uint32_t>(std::countl_zero(v | 1));
  return (log2 * 9 + 73) / 64;
}
inline char* PutVarint(char* p, uint64_t v) {
  while (v >= 0x80) {
    *p++ = static_cast<char>(v | 0x80);
    v >>= 7;
  }
  *p++ = static_cast<char>(v);
  return p;
}
// The same for 32-bit values, without a branch per byte: the bulk of an
// answer (ids and offsets, of mixed lengths, so the byte loop's exit was
// mispredicted about once per value). 10K radius rows of 4-12 results,
// warm: 0.78-0.81 ms to encode with the loops, 0.35-0.45 ms without.
// Writes 8 bytes at p (the buffer has kVarintSlack bytes after its end)
// and returns p + VarintSize(v).
constexpr size_t kVarintSlack = 8;
inline char* PutVarint32(char* p, uint32_t v) {
  const uint64_t w = v;
  // 7 bits per byte, low group first (little-endian store below)...
  uint64_t x = (w & 0x7f) | (w & 0x3f80) << 1 | (w & 0x1fc000) << 2 |
               (w & 0xfe00000) << 3 | (w & 0xf0000000) << 4;
  const size_t n = VarintSize(v);
  // ...and the continuation bit on every byte but the last.
  x |= uint64_t{0x8080808080} & ((uint64_t{1} << (8 * (n - 1))) - 1);
  std::memcpy(p, &x, sizeof(x));
  return p + n;
}
constexpr uint32_t kVarint = 0, kDelimited = 2;
constexpr uint64_t Tag(uint32_t field, uint32_t type) {
  return uint64_t{field} << 3 | type;
}
// A packed field of `payload` bytes (nothing when empty): its tag and
// length, for the size pass.
inline size_t PackedSize(uint32_t field, size_t payload) {
  return payload == 0 ? 0
                      : VarintSize(Tag(field, kDelimited)) +
                            VarintSize(payload) + payload;
}
inline char* PutPackedHeader(char* p, uint32_t field, size_t payload) {
  p = PutVarint(p, Tag(field, kDelimited));
  return PutVarint(p, payload);
}
// A scalar field (nothing when zero, as proto3 writes it).
inline size_t ScalarSize(uint32_t field, uint64_t v) {
  return v == 0 ? 0 : VarintSize(Tag(field, kVarint)) + VarintSize(v);
}
inline char* PutScalar(char* p, uint32_t field, uint64_t v) {
  if (v == 0) return p;
  p = PutVarint(p, Tag(field, kVarint));
  return PutVarint(p, v);
}

}  // namespace

bool ChunkCursor::NextBytes(std::string* bytes) {
  if (done_) return false;
  const auto& off = lists_.offsets;
  const Cut cut = NextCut();
  const uint64_t first_row = global_first_ + row_;
  // The fields of QueryResponse in field order (as protobuf writes them):
  // 1 step, 2 first_row, 3 offsets, 4 ids, 5 distances, 6 truncated_rows,
  // 7 total_rows, 8 client_ids, 9 last_row_continues, 10 fixed_offsets,
  // 11 fixed_ids, 12 fixed_client_ids; 3, 4 and 8 (varints) or 10, 11 and
  // 12 (fixed width) by the encoding.
  auto offset_at = [&](uint64_t k) {  // k in [0, offsets)
    if (k == 0) return uint64_t{0};
    if (k <= cut.rows) return off[row_ + k] - start_;
    return cut.end - start_;  // the continued row's part
  };
  const uint64_t num_offsets = 1 + cut.rows + (cut.continues ? 1 : 0);
  const uint64_t results = cut.end - start_;
  // Raw pointers: the writes below go through char*, which may alias
  // anything, so vector members would be reloaded for every value.
  const uint32_t* const ids = lists_.ids.data();
  const bool by_client = client_ids_ != nullptr;
  const uint64_t* const client = by_client ? client_ids_->data() : nullptr;
  // Offsets within a chunk are below results_per_chunk (< 2^32).
  size_t offsets_bytes = 0, ids_bytes = 0, client_bytes = 0;
  if (fixed_) {
    offsets_bytes = 4 * num_offsets;
    (by_client ? client_bytes : ids_bytes) = (by_client ? 8 : 4) * results;
  } else {
    for (uint64_t k = 0; k < num_offsets; ++k) {
      offsets_bytes += VarintSize(offset_at(k));
    }
    if (by_client) {
      for (uint64_t k = start_; k < cut.end; ++k) {
        client_bytes += VarintSize(client[ids[k]]);
      }
    } else {
      for (uint64_t k = start_; k < cut.end; ++k) {
        ids_bytes += VarintSize(ids[k]);
      }
    }
  }
  size_t truncated_bytes = 0;
  for (uint64_t k = 0; k < cut.rows; ++k) {
    if (lists_.truncated[row_ + k]) truncated_bytes += VarintSize(k);
  }
  const size_t distance_bytes = distances_ ? 8 * results : 0;
  // The fields' numbers by the encoding.
  const uint32_t offsets_field = fixed_ ? 10 : 3, ids_field = fixed_ ? 11 : 4,
                 client_field = fixed_ ? 12 : 8;
  const size_t size =
      ScalarSize(1, step_) + ScalarSize(2, first_row) +
      PackedSize(offsets_field, offsets_bytes) +
      PackedSize(ids_field, ids_bytes) + PackedSize(5, distance_bytes) +
      PackedSize(6, truncated_bytes) + ScalarSize(7, total_rows_) +
      PackedSize(client_field, client_bytes) + (cut.continues ? 2 : 0);
  bytes->resize(size + kVarintSlack);
  char* p = bytes->data();
  // Little-endian fixed-width values (doubles, fixed32, fixed64), as on
  // every supported host.
  static_assert(std::endian::native == std::endian::little);
  p = PutScalar(p, 1, step_);
  p = PutScalar(p, 2, first_row);
  if (!fixed_) {
    p = PutPackedHeader(p, 3, offsets_bytes);
    for (uint64_t k = 0; k < num_offsets; ++k) {
      p = PutVarint32(p, static_cast<uint32_t>(offset_at(k)));
    }
    if (ids_bytes > 0) {
      p = PutPackedHeader(p, 4, ids_bytes);
      for (uint64_t k = start_; k < cut.end; ++k) p = PutVarint32(p, ids[k]);
    }
  }
  if (distance_bytes > 0) {
    p = PutPackedHeader(p, 5, distance_bytes);
    std::memcpy(p, lists_.distances.data() + start_, distance_bytes);
    p += distance_bytes;
  }
  if (truncated_bytes > 0) {
    p = PutPackedHeader(p, 6, truncated_bytes);
    for (uint64_t k = 0; k < cut.rows; ++k) {
      if (lists_.truncated[row_ + k]) p = PutVarint(p, k);
    }
  }
  p = PutScalar(p, 7, total_rows_);
  if (!fixed_ && client_bytes > 0) {
    p = PutPackedHeader(p, 8, client_bytes);
    for (uint64_t k = start_; k < cut.end; ++k) {
      p = PutVarint(p, client[ids[k]]);
    }
  }
  if (cut.continues) {
    p = PutVarint(p, Tag(9, kVarint));
    *p++ = 1;
  }
  if (fixed_) {
    p = PutPackedHeader(p, 10, offsets_bytes);
    for (uint64_t k = 0; k < num_offsets; ++k) {
      const auto v = static_cast<uint32_t>(offset_at(k));
      std::memcpy(p, &v, 4);
      p += 4;
    }
    if (ids_bytes > 0) {
      p = PutPackedHeader(p, 11, ids_bytes);
      std::memcpy(p, ids + start_, ids_bytes);
      p += ids_bytes;
    }
    if (client_bytes > 0) {
      p = PutPackedHeader(p, 12, client_bytes);
      for (uint64_t k = start_; k < cut.end; ++k) {
        std::memcpy(p, &client[ids[k]], 8);
        p += 8;
      }
    }
  }
  assert(p == bytes->data() + size);
  (void)p;
  bytes->resize(size);  // drops the slack; keeps the buffer
  Advance(cut);
  return true;
}

}  // namespace kinetri::server
