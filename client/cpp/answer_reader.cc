#include "client/cpp/answer_reader.h"

#include <algorithm>
#include <bit>
#include <cstdint>
#include <cstring>
#include <vector>

#include "absl/strings/str_cat.h"

#if defined(__SSE2__)
#include <emmintrin.h>
#endif

namespace kinetri {

static_assert(std::endian::native == std::endian::little,
              "packed doubles are copied as they are on the wire");

namespace {

// Protobuf wire types.
constexpr uint32_t kVarint = 0;
constexpr uint32_t kFixed64 = 1;
constexpr uint32_t kLengthDelimited = 2;
constexpr uint32_t kStartGroup = 3;
constexpr uint32_t kFixed32 = 5;

// QueryResponse's fields (proto/kinetri/v1/kinetri.proto).
enum Field : uint32_t {
  kStep = 1,
  kFirstRow = 2,
  kOffsets = 3,
  kIds = 4,
  kDistances = 5,
  kTruncatedRows = 6,
  kTotalRows = 7,
  kClientIds = 8,
  kLastRowContinues = 9,
  kFixedOffsets = 10,
  kFixedIds = 11,
  kFixedClientIds = 12,
};

// Reads the varint at *p (before end) and advances *p past it; false when
// it runs past end or over 10 bytes. For tags and single values; packed
// fields go through AppendPacked.
bool ReadVarint(const char** p, const char* end, uint64_t* value) {
  uint64_t v = 0;
  const char* q = *p;
  for (int shift = 0; shift < 70 && q < end; shift += 7) {
    const auto byte = static_cast<uint8_t>(*q++);
    v |= uint64_t{byte & 0x7fu} << shift;
    if (byte < 0x80) {
      *value = v;
      *p = q;
      return true;
    }
  }
  return false;
}

// Bit i set where byte i of [b, b + n) (n <= 64) ends a varint (is below
// 0x80).
uint64_t StopMask(const uint8_t* b, size_t n) {
  uint64_t m = 0;
#if defined(__SSE2__)
  if (n == 64) {
    for (int i = 0; i < 4; ++i) {
      const __m128i x =
          _mm_loadu_si128(reinterpret_cast<const __m128i*>(b + 16 * i));
      m |= uint64_t{static_cast<uint16_t>(~_mm_movemask_epi8(x))} << (16 * i);
    }
    return m;
  }
#endif
  for (size_t i = 0; i < n; ++i) m |= uint64_t{b[i] < 0x80} << i;
  return m;
}

// The value of the varint of `len` bytes at b (its last byte < 0x80).
// kFast: the longest varint read by one 8-byte load (5 for 32-bit fields,
// whose values need at most 5 bytes; 8 otherwise) when 8 bytes are there.
template <int kFast>
bool VarintAt(const uint8_t* b, size_t len, size_t avail, uint64_t* value) {
  if (len <= kFast && avail >= 8) {
    uint64_t w;
    std::memcpy(&w, b, 8);
    // Byte i's low 7 bits move to bits [7i, 7i + 7).
    uint64_t v = (w & 0x7full) | ((w >> 1) & (0x7full << 7)) |
                 ((w >> 2) & (0x7full << 14)) | ((w >> 3) & (0x7full << 21)) |
                 ((w >> 4) & (0x7full << 28));
    if constexpr (kFast > 5) {
      v |= ((w >> 5) & (0x7full << 35)) | ((w >> 6) & (0x7full << 42)) |
           ((w >> 7) & (0x7full << 49));
    }
    *value = v & ((uint64_t{1} << (7 * len)) - 1);
    return true;
  }
  if (len > 10) return false;
  uint64_t v = 0;
  for (size_t i = 0; i < len; ++i) v |= uint64_t{b[i] & 0x7fu} << (7 * i);
  *value = v;
  return true;
}

// Appends the packed varints of [p, end) to out, each through f. The ends
// of the varints come from a bit mask of the bytes below 0x80, 64 bytes at
// a time; walking its set bits, each value is read by one load and a few
// shifts, independent of the one before (a byte loop, or one load per
// varint at the end of the last, is a chain of dependent loads and
// mispredicted exits: 4-5 ns a value, against about 1-2 here).
template <int kFast, typename T, typename F>
bool AppendPacked(const char* p, const char* end, std::vector<T>* out, F f) {
  const auto* b = reinterpret_cast<const uint8_t*>(p);
  const size_t size = static_cast<size_t>(end - p);
  if (size == 0) return true;
  if (b[size - 1] >= 0x80) return false;  // the last varint runs past end
  size_t n = 0;
  for (size_t block = 0; block < size; block += 64) {
    n += static_cast<size_t>(
        std::popcount(StopMask(b + block, std::min<size_t>(64, size - block))));
  }
  const size_t old = out->size();
  out->resize(old + n);
  T* dst = out->data() + old;
  size_t start = 0;
  for (size_t block = 0; block < size; block += 64) {
    uint64_t m = StopMask(b + block, std::min<size_t>(64, size - block));
    while (m != 0) {
      const size_t stop = block + static_cast<size_t>(std::countr_zero(m));
      m &= m - 1;
      uint64_t v;
      if (!VarintAt<kFast>(b + start, stop - start + 1, size - start, &v)) {
        return false;
      }
      *dst++ = f(v);
      start = stop + 1;
    }
  }
  return true;
}

// The bytes of a fixed-width field's values of `width` bytes: the one value
// of an unpacked field (wire type `single`) or a packed run; 0 when the
// wire type is neither (an unknown field), -1 when a packed run is not a
// whole number of values.
int64_t FixedBytes(uint32_t type, uint32_t single, size_t width,
                   const char* body, const char* body_end) {
  if (type == single) return static_cast<int64_t>(width);
  if (type != kLengthDelimited) return 0;
  const auto bytes = static_cast<size_t>(body_end - body);
  return bytes % width == 0 ? static_cast<int64_t>(bytes) : -1;
}

// Appends the values of a fixed-width field (T on the wire, little-endian)
// to out; false when a packed run is not a whole number of values.
template <typename T>
bool AppendFixed(uint32_t type, uint32_t single, const char* body,
                 const char* body_end, std::vector<T>* out) {
  const int64_t bytes = FixedBytes(type, single, sizeof(T), body, body_end);
  if (bytes <= 0) return bytes == 0;
  const size_t old = out->size();
  out->resize(old + static_cast<size_t>(bytes) / sizeof(T));
  std::memcpy(out->data() + old, body, static_cast<size_t>(bytes));
  return true;
}

absl::Status Malformed(const char* what) {
  return absl::InternalError(
      absl::StrCat("query answer: not a valid QueryResponse (", what, ")"));
}

}  // namespace

AnswerReader::AnswerReader() { out_.offsets.push_back(0); }

absl::Status AnswerReader::Append(const grpc::ByteBuffer& chunk) {
  grpc::Slice single;
  if (chunk.TrySingleSlice(&single).ok()) {
    return Append(absl::string_view(
        reinterpret_cast<const char*>(single.begin()), single.size()));
  }
  std::vector<grpc::Slice> slices;
  if (!chunk.Dump(&slices).ok()) return Malformed("unreadable buffer");
  joined_.clear();
  joined_.reserve(chunk.Length());
  for (const grpc::Slice& s : slices) {
    joined_.append(reinterpret_cast<const char*>(s.begin()), s.size());
  }
  return Append(absl::string_view(joined_));
}

absl::Status AnswerReader::Append(absl::string_view chunk) {
  // A row split across chunks continues where it left off: its end offset
  // is replaced, not followed.
  if (continues_) out_.offsets.pop_back();
  const uint64_t row0 = out_.offsets.size() - 1;
  // Offsets are local to the chunk: they count from the results so far.
  const uint64_t base = out_.ids.size() + out_.client_ids.size();
  const size_t offsets_before = out_.offsets.size();
  uint64_t step = 0, first_row = 0;
  bool continues = false;
  // Values read from the varint and the fixed-width field of offsets, ids
  // and client ids: a chunk may use one of each pair only.
  size_t varint_values[3] = {0, 0, 0}, fixed_values[3] = {0, 0, 0};

  const char* p = chunk.data();
  const char* const end = p + chunk.size();
  while (p < end) {
    uint64_t tag;
    if (!ReadVarint(&p, end, &tag) || tag > UINT32_MAX) {
      return Malformed("bad tag");
    }
    const auto field = static_cast<uint32_t>(tag >> 3);
    const auto type = static_cast<uint32_t>(tag & 7);
    if (field == 0) return Malformed("field number 0");
    const char* body = p;
    const char* body_end = nullptr;
    uint64_t v = 0;
    switch (type) {
      case kVarint:
        if (!ReadVarint(&p, end, &v)) return Malformed("bad varint");
        break;
      case kFixed64:
        if (end - p < 8) return Malformed("truncated fixed64");
        p += 8;
        break;
      case kFixed32:
        if (end - p < 4) return Malformed("truncated fixed32");
        p += 4;
        break;
      case kLengthDelimited: {
        uint64_t len;
        if (!ReadVarint(&p, end, &len) ||
            len > static_cast<uint64_t>(end - p)) {
          return Malformed("bad length");
        }
        body = p;
        body_end = p + len;
        p = body_end;
        break;
      }
      case kStartGroup:
        return Malformed("groups are not used by this protocol");
      default:
        return Malformed("bad wire type");
    }
    // A known field in a wire type it cannot have is unknown, as protobuf
    // has it; unknown fields are skipped.
    bool ok = true;
    const size_t sizes[3] = {out_.offsets.size(), out_.ids.size(),
                             out_.client_ids.size()};
    switch (field) {
      case kStep:
        if (type == kVarint) step = v;
        break;
      case kFirstRow:
        if (type == kVarint) first_row = v;
        break;
      case kLastRowContinues:
        if (type == kVarint) continues = v != 0;
        break;
      case kTotalRows:
        break;
      case kOffsets:
        if (type == kVarint) {
          out_.offsets.push_back(base + v);
        } else if (type == kLengthDelimited) {
          ok = AppendPacked<8>(body, body_end, &out_.offsets,
                               [base](uint64_t x) { return base + x; });
        }
        break;
      case kIds:
        if (type == kVarint) {
          out_.ids.push_back(static_cast<uint32_t>(v));
        } else if (type == kLengthDelimited) {
          ok = AppendPacked<5>(body, body_end, &out_.ids, [](uint64_t x) {
            return static_cast<uint32_t>(x);
          });
        }
        break;
      case kClientIds:
        if (type == kVarint) {
          out_.client_ids.push_back(v);
        } else if (type == kLengthDelimited) {
          ok = AppendPacked<8>(body, body_end, &out_.client_ids,
                               [](uint64_t x) { return x; });
        }
        break;
      case kTruncatedRows:
        if (type == kVarint) {
          out_.truncated_rows.push_back(row0 + static_cast<uint32_t>(v));
        } else if (type == kLengthDelimited) {
          ok = AppendPacked<5>(
              body, body_end, &out_.truncated_rows,
              [row0](uint64_t x) { return row0 + static_cast<uint32_t>(x); });
        }
        break;
      case kDistances:
        if (!AppendFixed(type, kFixed64, body, body_end, &out_.distances)) {
          return Malformed("packed doubles");
        }
        break;
      case kFixedOffsets: {
        const int64_t bytes = FixedBytes(type, kFixed32, 4, body, body_end);
        if (bytes < 0) return Malformed("packed fixed32 offsets");
        const size_t n = static_cast<size_t>(bytes) / 4;
        const size_t old = out_.offsets.size();
        out_.offsets.resize(old + n);
        for (size_t i = 0; i < n; ++i) {
          uint32_t x;
          std::memcpy(&x, body + 4 * i, 4);
          out_.offsets[old + i] = base + x;
        }
        break;
      }
      case kFixedIds:
        if (!AppendFixed(type, kFixed32, body, body_end, &out_.ids)) {
          return Malformed("packed fixed32 ids");
        }
        break;
      case kFixedClientIds:
        if (!AppendFixed(type, kFixed64, body, body_end, &out_.client_ids)) {
          return Malformed("packed fixed64 client ids");
        }
        break;
      default:
        break;
    }
    if (!ok) return Malformed("bad packed varints");
    const size_t grown[3] = {out_.offsets.size() - sizes[0],
                             out_.ids.size() - sizes[1],
                             out_.client_ids.size() - sizes[2]};
    for (int i = 0; i < 3; ++i) {
      const bool fixed_field = field >= kFixedOffsets;
      (fixed_field ? fixed_values : varint_values)[i] += grown[i];
    }
  }
  for (int i = 0; i < 3; ++i) {
    if (varint_values[i] > 0 && fixed_values[i] > 0) {
      return Malformed(
          "offsets, ids or client ids both as varints and fixed-width");
    }
  }
  // The chunk's first offset (0) starts the row before it, already here.
  if (out_.offsets.size() > offsets_before) {
    out_.offsets.erase(out_.offsets.begin() +
                       static_cast<std::ptrdiff_t>(offsets_before));
  }
  // Every chunk of one answer comes from the same step, rows in order.
  if (!first_ && step != out_.step) {
    return absl::InternalError(
        absl::StrCat("query answer mixes steps ", out_.step, " and ", step));
  }
  if (first_row != row0) {
    return absl::InternalError(absl::StrCat("query chunk starts at row ",
                                            first_row, ", expected ", row0));
  }
  first_ = false;
  continues_ = continues;
  out_.step = step;
  return absl::OkStatus();
}

}  // namespace kinetri
