// The C++ client's decoder of query answers (client/cpp/answer_reader.h)
// against protobuf's own parser: for every encoding protobuf accepts
// (canonical, unpacked, split, reordered, with unknown fields, over-long
// varints) the rows are the ones protobuf's message gives, reassembled the
// way the client did before; what protobuf rejects is rejected; the
// server's chunk writer round-trips through it. All of it in both answer
// encodings (varint and fixed-width offsets and ids).
#include "client/cpp/answer_reader.h"

#include <gtest/gtest.h>

#include <cstdint>
#include <cstring>
#include <random>
#include <string>
#include <vector>

#include "core/query_types.h"
#include "kinetri/v1/kinetri.pb.h"
#include "server/convert.h"

namespace kinetri {
namespace {

// The client's reassembly before AnswerReader, on parsed messages (the
// fixed-width fields read as the varint ones; a chunk with values in both
// fields of a pair is refused).
struct Reference {
  Neighbors out;
  bool first = true;
  bool continues = false;
  Reference() { out.offsets.push_back(0); }
  bool Append(const v1::QueryResponse& chunk) {
    if (!first && chunk.step() != out.step) return false;
    if ((chunk.offsets_size() > 0 && chunk.fixed_offsets_size() > 0) ||
        (chunk.ids_size() > 0 && chunk.fixed_ids_size() > 0) ||
        (chunk.client_ids_size() > 0 && chunk.fixed_client_ids_size() > 0)) {
      return false;
    }
    if (continues) out.offsets.pop_back();
    if (chunk.first_row() != out.offsets.size() - 1) return false;
    first = false;
    continues = chunk.last_row_continues();
    out.step = chunk.step();
    const uint64_t base = out.ids.size() + out.client_ids.size();
    const uint64_t row0 = out.offsets.size() - 1;
    for (int i = 1; i < chunk.offsets_size(); ++i) {
      out.offsets.push_back(base + chunk.offsets(i));
    }
    for (int i = 1; i < chunk.fixed_offsets_size(); ++i) {
      out.offsets.push_back(base + chunk.fixed_offsets(i));
    }
    out.ids.insert(out.ids.end(), chunk.ids().begin(), chunk.ids().end());
    out.ids.insert(out.ids.end(), chunk.fixed_ids().begin(),
                   chunk.fixed_ids().end());
    out.client_ids.insert(out.client_ids.end(), chunk.client_ids().begin(),
                          chunk.client_ids().end());
    out.client_ids.insert(out.client_ids.end(),
                          chunk.fixed_client_ids().begin(),
                          chunk.fixed_client_ids().end());
    out.distances.insert(out.distances.end(), chunk.distances().begin(),
                         chunk.distances().end());
    for (uint32_t r : chunk.truncated_rows()) {
      out.truncated_rows.push_back(row0 + r);
    }
    return true;
  }
};

void ExpectSame(const Neighbors& a, const Neighbors& b) {
  EXPECT_EQ(a.step, b.step);
  EXPECT_EQ(a.offsets, b.offsets);
  EXPECT_EQ(a.ids, b.ids);
  EXPECT_EQ(a.client_ids, b.client_ids);
  EXPECT_EQ(a.truncated_rows, b.truncated_rows);
  // Bit for bit (NaNs included).
  ASSERT_EQ(a.distances.size(), b.distances.size());
  for (size_t i = 0; i < a.distances.size(); ++i) {
    uint64_t x, y;
    std::memcpy(&x, &a.distances[i], 8);
    std::memcpy(&y, &b.distances[i], 8);
    ASSERT_EQ(x, y) << "distance " << i;
  }
}

// A value of 1 to `max_bytes` varint bytes, each length about as likely.
uint64_t AnyLength(std::mt19937_64& rng, int max_bytes) {
  const int bits = 7 * (1 + static_cast<int>(rng() % max_bytes));
  const uint64_t v = rng();
  return bits >= 64 ? v : v & ((uint64_t{1} << bits) - 1);
}

// One chunk of `rows` rows starting at first_row, values of every length;
// offsets and ids in the fixed-width fields when `fixed`.
v1::QueryResponse RandomChunk(std::mt19937_64& rng, uint64_t step,
                              uint64_t first_row, int rows, bool client_ids,
                              bool fixed = false) {
  v1::QueryResponse c;
  c.set_step(step);
  c.set_first_row(first_row);
  c.set_total_rows(first_row + rows + 5);
  auto add_offset = [&](uint64_t v) {
    if (fixed) {
      c.add_fixed_offsets(static_cast<uint32_t>(v));
    } else {
      c.add_offsets(v);
    }
  };
  add_offset(0);
  uint64_t n = 0;
  for (int r = 0; r < rows; ++r) {
    const int len = static_cast<int>(rng() % 40);
    for (int k = 0; k < len; ++k) {
      const uint64_t id = AnyLength(rng, client_ids ? 10 : 5);
      if (client_ids && fixed) {
        c.add_fixed_client_ids(id);
      } else if (client_ids) {
        c.add_client_ids(id);
      } else if (fixed) {
        c.add_fixed_ids(static_cast<uint32_t>(id));
      } else {
        c.add_ids(static_cast<uint32_t>(id));
      }
      double d;
      const uint64_t bits = rng();
      std::memcpy(&d, &bits, 8);  // any bit pattern, NaNs included
      c.add_distances(d);
    }
    n += static_cast<uint64_t>(len);
    add_offset(n);
    if (rng() % 7 == 0) c.add_truncated_rows(static_cast<uint32_t>(r));
  }
  return c;
}

absl::Status AppendAll(AnswerReader* reader,
                       const std::vector<std::string>& chunks) {
  for (const std::string& c : chunks) {
    if (absl::Status s = reader->Append(c); !s.ok()) return s;
  }
  return absl::OkStatus();
}

TEST(AnswerReader, CanonicalChunksEqualProtobuf) {
  std::mt19937_64 rng(7);
  for (int trial = 0; trial < 200; ++trial) {
    const bool client_ids = trial % 3 == 0;
    const uint64_t step = AnyLength(rng, 10);
    std::vector<std::string> bytes;
    Reference ref;
    uint64_t row = 0;
    bool continues = false;
    const int chunks = 1 + static_cast<int>(rng() % 4);
    for (int i = 0; i < chunks; ++i) {
      if (continues) --row;  // the split row goes on in this chunk
      const int rows = static_cast<int>(rng() % 300);
      v1::QueryResponse c =
          RandomChunk(rng, step, row, rows, client_ids, rng() % 2 == 0);
      continues = rows > 0 && i + 1 < chunks && rng() % 2 == 0;
      c.set_last_row_continues(continues);
      row += static_cast<uint64_t>(rows);
      bytes.push_back(c.SerializeAsString());
      ASSERT_TRUE(ref.Append(c));
    }
    AnswerReader reader;
    ASSERT_TRUE(AppendAll(&reader, bytes).ok());
    ExpectSame(reader.rows(), ref.out);
  }
}

// Hand-written protobuf wire format.
void Varint(std::string* s, uint64_t v, int extra_bytes = 0) {
  for (int i = 0; i < extra_bytes; ++i) {  // over-long: 0x80 groups first
    s->push_back(static_cast<char>((v & 0x7f) | 0x80));
    v >>= 7;
  }
  while (v >= 0x80) {
    s->push_back(static_cast<char>((v & 0x7f) | 0x80));
    v >>= 7;
  }
  s->push_back(static_cast<char>(v));
}
void Tag(std::string* s, uint32_t field, uint32_t type) {
  Varint(s, (uint64_t{field} << 3) | type);
}
void Fixed64(std::string* s, uint64_t v) {
  char b[8];
  std::memcpy(b, &v, 8);
  s->append(b, 8);
}
void Packed(std::string* s, uint32_t field, const std::vector<uint64_t>& vs) {
  std::string body;
  for (uint64_t v : vs) Varint(&body, v);
  Tag(s, field, 2);
  Varint(s, body.size());
  *s += body;
}

// The fields of `c` written in a random legal way: random order, repeated
// fields split into packed runs and single (unpacked) values, over-long
// varints, unknown fields of every wire type between them.
std::string AnyEncoding(std::mt19937_64& rng, const v1::QueryResponse& c) {
  std::vector<std::string> parts;
  auto scalar = [&](uint32_t field, uint64_t v) {
    if (v == 0 && rng() % 2) return;
    std::string p;
    Tag(&p, field, 0);
    Varint(&p, v, static_cast<int>(rng() % 3));
    parts.push_back(p);
  };
  scalar(1, c.step());
  scalar(2, c.first_row());
  scalar(7, c.total_rows());
  scalar(9, c.last_row_continues() ? 1 : 0);
  // Repeated varint fields: runs in order (their order within a field
  // matters; runs of different fields may interleave).
  auto runs = [&](uint32_t field, std::vector<uint64_t> vs) {
    std::vector<std::string> field_parts;
    size_t i = 0;
    while (i < vs.size()) {
      const size_t len = 1 + rng() % 50;
      std::vector<uint64_t> run(vs.begin() + static_cast<std::ptrdiff_t>(i),
                                vs.begin() + static_cast<std::ptrdiff_t>(
                                                 std::min(vs.size(), i + len)));
      std::string p;
      if (rng() % 3 == 0) {
        for (uint64_t v : run) {
          Tag(&p, field, 0);
          Varint(&p, v, static_cast<int>(rng() % 2));
        }
      } else {
        Packed(&p, field, run);
      }
      field_parts.push_back(p);
      i += run.size();
    }
    return field_parts;
  };
  std::vector<std::vector<std::string>> lists;
  lists.push_back(
      runs(3, std::vector<uint64_t>(c.offsets().begin(), c.offsets().end())));
  lists.push_back(
      runs(4, std::vector<uint64_t>(c.ids().begin(), c.ids().end())));
  lists.push_back(runs(6, std::vector<uint64_t>(c.truncated_rows().begin(),
                                                c.truncated_rows().end())));
  lists.push_back(runs(
      8, std::vector<uint64_t>(c.client_ids().begin(), c.client_ids().end())));
  // Fixed-width fields: packed runs and single values.
  auto fixed_runs = [&](uint32_t field, size_t width,
                        const std::vector<uint64_t>& vs) {
    std::vector<std::string> field_parts;
    size_t i = 0;
    while (i < vs.size()) {
      const size_t end = std::min(vs.size(), i + 1 + rng() % 50);
      std::string p;
      if (rng() % 3 == 0) {
        for (size_t k = i; k < end; ++k) {
          Tag(&p, field, width == 8 ? 1 : 5);
          p.append(reinterpret_cast<const char*>(&vs[k]), width);
        }
      } else {
        Tag(&p, field, 2);
        Varint(&p, width * (end - i));
        for (size_t k = i; k < end; ++k) {
          p.append(reinterpret_cast<const char*>(&vs[k]), width);
        }
      }
      field_parts.push_back(p);
      i = end;
    }
    return field_parts;
  };
  lists.push_back(fixed_runs(10, 4,
                             std::vector<uint64_t>(c.fixed_offsets().begin(),
                                                   c.fixed_offsets().end())));
  lists.push_back(fixed_runs(
      11, 4,
      std::vector<uint64_t>(c.fixed_ids().begin(), c.fixed_ids().end())));
  lists.push_back(
      fixed_runs(12, 8,
                 std::vector<uint64_t>(c.fixed_client_ids().begin(),
                                       c.fixed_client_ids().end())));
  {
    std::vector<std::string> d;
    int i = 0;
    while (i < c.distances_size()) {
      const int len = 1 + static_cast<int>(rng() % 50);
      const int end = std::min(c.distances_size(), i + len);
      std::string p;
      if (rng() % 3 == 0) {
        for (int k = i; k < end; ++k) {
          uint64_t bits;
          const double v = c.distances(k);
          std::memcpy(&bits, &v, 8);
          Tag(&p, 5, 1);
          Fixed64(&p, bits);
        }
      } else {
        Tag(&p, 5, 2);
        Varint(&p, 8 * static_cast<uint64_t>(end - i));
        p.append(reinterpret_cast<const char*>(c.distances().data() + i),
                 8 * static_cast<size_t>(end - i));
      }
      d.push_back(p);
      i = end;
    }
    lists.push_back(d);
  }
  // Merge the lists' parts in a random interleaving, keeping each list's
  // order, with the scalars and unknown fields anywhere.
  std::vector<std::string> merged = parts;
  std::shuffle(merged.begin(), merged.end(), rng);
  std::vector<size_t> next(lists.size(), 0);
  std::string out;
  size_t scalar_i = 0;
  while (true) {
    std::vector<size_t> open;
    for (size_t l = 0; l < lists.size(); ++l) {
      if (next[l] < lists[l].size()) open.push_back(l);
    }
    if (open.empty() && scalar_i == merged.size()) break;
    const uint64_t pick = rng() % 8;
    if (pick == 0) {  // an unknown field
      const uint32_t field = 13 + static_cast<uint32_t>(rng() % 100000);
      switch (rng() % 4) {
        case 0:
          Tag(&out, field, 0);
          Varint(&out, rng());
          break;
        case 1:
          Tag(&out, field, 1);
          Fixed64(&out, rng());
          break;
        case 2: {
          Tag(&out, field, 2);
          const size_t len = rng() % 20;
          Varint(&out, len);
          for (size_t k = 0; k < len; ++k) {
            out.push_back(static_cast<char>(rng()));
          }
          break;
        }
        default:
          Tag(&out, field, 5);
          out.append(4, static_cast<char>(rng()));
      }
    } else if (pick == 1 && scalar_i < merged.size()) {
      out += merged[scalar_i++];
    } else if (!open.empty()) {
      const size_t l = open[rng() % open.size()];
      out += lists[l][next[l]++];
    } else if (scalar_i < merged.size()) {
      out += merged[scalar_i++];
    }
  }
  return out;
}

TEST(AnswerReader, AnyLegalEncodingEqualsProtobuf) {
  std::mt19937_64 rng(11);
  for (int trial = 0; trial < 300; ++trial) {
    const v1::QueryResponse c =
        RandomChunk(rng, AnyLength(rng, 10), 0, static_cast<int>(rng() % 60),
                    trial % 2 == 0, trial % 4 >= 2);
    const std::string bytes = AnyEncoding(rng, c);
    v1::QueryResponse parsed;
    ASSERT_TRUE(parsed.ParseFromString(bytes));
    Reference ref;
    ASSERT_TRUE(ref.Append(parsed));
    AnswerReader reader;
    ASSERT_TRUE(reader.Append(bytes).ok());
    ExpectSame(reader.rows(), ref.out);
  }
}

TEST(AnswerReader, Uint32FieldsKeepTheLow32BitsOfLongerVarints) {
  // A 10-byte varint in a uint32 field (how another writer may encode a
  // value it holds as 64 bits): protobuf keeps the low 32 bits.
  std::string bytes;
  Tag(&bytes, 3, 2);
  Varint(&bytes, 2);
  bytes += std::string("\x00\x02", 2);  // offsets 0, 2
  std::string ids;
  Varint(&ids, 0xFFFFFFFF00000005ull);
  Varint(&ids, 7, 6);  // 7 in 7 bytes
  Tag(&bytes, 4, 2);
  Varint(&bytes, ids.size());
  bytes += ids;
  v1::QueryResponse parsed;
  ASSERT_TRUE(parsed.ParseFromString(bytes));
  AnswerReader reader;
  ASSERT_TRUE(reader.Append(bytes).ok());
  ASSERT_EQ(parsed.ids_size(), 2);
  EXPECT_EQ(reader.rows().ids,
            (std::vector<uint32_t>{parsed.ids(0), parsed.ids(1)}));
  EXPECT_EQ(reader.rows().ids, (std::vector<uint32_t>{5, 7}));
}

TEST(AnswerReader, EmptyPackedFieldsAddNothing) {
  // Legal, if no writer of ours sends them: packed fields of 0 bytes.
  const std::string bytes("\x1a\x00\x22\x00\x2a\x00\x32\x00\x42\x00", 10);
  v1::QueryResponse parsed;
  ASSERT_TRUE(parsed.ParseFromString(bytes));
  AnswerReader reader;
  ASSERT_TRUE(reader.Append(bytes).ok());
  EXPECT_EQ(reader.rows().offsets, std::vector<uint64_t>{0});
  EXPECT_TRUE(reader.rows().ids.empty());
  EXPECT_TRUE(reader.rows().distances.empty());
  EXPECT_TRUE(reader.rows().client_ids.empty());
  EXPECT_TRUE(reader.rows().truncated_rows.empty());
}

TEST(AnswerReader, AChunkUsesOneEncodingPerField) {
  // Offsets, ids or client ids in both their varint and their fixed-width
  // field: no writer sends that, and which order they join in would be a
  // guess, so it is refused; an empty field of the other encoding is not.
  v1::QueryResponse c;
  c.add_offsets(0);
  c.add_offsets(2);
  c.add_ids(4);
  c.add_ids(5);
  {
    v1::QueryResponse both = c;
    both.add_fixed_ids(6);
    both.set_offsets(1, 3);
    AnswerReader reader;
    EXPECT_EQ(reader.Append(both.SerializeAsString()).code(),
              absl::StatusCode::kInternal);
  }
  {
    v1::QueryResponse both = c;
    both.add_fixed_offsets(0);
    AnswerReader reader;
    EXPECT_FALSE(reader.Append(both.SerializeAsString()).ok());
  }
  {
    v1::QueryResponse both;
    both.add_fixed_offsets(0);
    both.add_fixed_offsets(2);
    both.add_client_ids(1);
    both.add_fixed_client_ids(2);
    AnswerReader reader;
    EXPECT_FALSE(reader.Append(both.SerializeAsString()).ok());
  }
  {
    // Varint offsets with fixed-width ids: one encoding per field is kept.
    v1::QueryResponse mixed;
    mixed.add_offsets(0);
    mixed.add_offsets(2);
    mixed.add_fixed_ids(7);
    mixed.add_fixed_ids(8);
    std::string bytes = mixed.SerializeAsString();
    bytes += std::string("\x22\x00\x5a\x00", 4);  // empty ids, fixed ids
    AnswerReader reader;
    ASSERT_TRUE(reader.Append(bytes).ok());
    EXPECT_EQ(reader.rows().offsets, (std::vector<uint64_t>{0, 2}));
    EXPECT_EQ(reader.rows().ids, (std::vector<uint32_t>{7, 8}));
  }
}

TEST(AnswerReader, MalformedBytesAreRejected) {
  auto rejected = [](const std::string& bytes) {
    AnswerReader reader;
    return !reader.Append(bytes).ok();
  };
  std::string s;
  // A varint of 11 bytes.
  s.assign(10, '\x80');
  s.push_back('\x01');
  EXPECT_TRUE(rejected(std::string("\x08", 1) + s));      // step = <11 bytes>
  EXPECT_TRUE(rejected(std::string("\x22\x0b", 2) + s));  // in packed ids
  EXPECT_TRUE(rejected(std::string("\x22\x0d", 2) + s + "\x01\x02"));
  // A packed field whose last varint runs past the field.
  EXPECT_TRUE(rejected(std::string("\x22\x02\x01\x81", 4) + "\x08\x01"));
  // A length past the end.
  EXPECT_TRUE(rejected(std::string("\x22\x05\x01\x02", 4)));
  // Packed doubles that are not a multiple of 8 bytes.
  EXPECT_TRUE(rejected(std::string("\x2a\x03\x01\x02\x03", 5)));
  // A truncated fixed64 and fixed32.
  EXPECT_TRUE(rejected(std::string("\x29\x01\x02", 3)));
  EXPECT_TRUE(rejected(std::string("\x6d\x01", 2)));  // field 13, fixed32
  // Packed fixed-width offsets, ids and client ids that are not whole
  // values.
  EXPECT_TRUE(rejected(std::string("\x52\x03\x01\x02\x03", 5)));
  EXPECT_TRUE(rejected(std::string("\x5a\x05\x01\x02\x03\x04\x05", 7)));
  EXPECT_TRUE(rejected(std::string("\x62\x04\x01\x02\x03\x04", 6)));
  // Field number 0, wire types 6 and 7, groups (not used by the protocol).
  EXPECT_TRUE(rejected(std::string("\x00\x01", 2)));
  EXPECT_TRUE(rejected(std::string("\x0e\x01", 2)));
  EXPECT_TRUE(rejected(std::string("\x0f\x01", 2)));
  EXPECT_TRUE(rejected(std::string("\x6b\x6c", 2)));  // field 13 group
  // A tag whose varint never ends.
  EXPECT_TRUE(rejected(std::string("\x80", 1)));
}

TEST(AnswerReader, EveryPrefixAndCorruptionIsSafe) {
  // Cut or damaged bytes never read out of bounds (ASan in CI) and are
  // never accepted where protobuf rejects them; where both accept, the
  // rows are protobuf's.
  std::mt19937_64 rng(5);
  for (int trial = 0; trial < 40; ++trial) {
    const v1::QueryResponse c = RandomChunk(
        rng, 9, 0, 1 + static_cast<int>(rng() % 12), trial % 2, trial % 4 >= 2);
    const std::string full = AnyEncoding(rng, c);
    for (size_t cut = 0; cut <= full.size(); ++cut) {
      std::string bytes = full.substr(0, cut);
      if (trial % 2 == 1 && !bytes.empty()) {
        bytes[rng() % bytes.size()] = static_cast<char>(rng());
      }
      AnswerReader reader;
      const bool ok = reader.Append(bytes).ok();
      v1::QueryResponse parsed;
      const bool pb = parsed.ParseFromString(bytes);
      if (!ok) continue;
      ASSERT_TRUE(pb) << "accepted bytes protobuf rejects, cut " << cut;
      Reference ref;
      if (!ref.Append(parsed)) continue;  // a row the chunk does not start
      ExpectSame(reader.rows(), ref.out);
    }
  }
}

TEST(AnswerReader, ChunksMustContinueTheAnswer) {
  v1::QueryResponse a;
  a.set_step(3);
  a.add_offsets(0);
  a.add_offsets(1);
  a.add_ids(5);
  v1::QueryResponse b = a;
  b.set_first_row(1);
  {
    AnswerReader reader;
    ASSERT_TRUE(reader.Append(a.SerializeAsString()).ok());
    ASSERT_TRUE(reader.Append(b.SerializeAsString()).ok());
    EXPECT_EQ(reader.rows().offsets, (std::vector<uint64_t>{0, 1, 2}));
    EXPECT_EQ(reader.rows().ids, (std::vector<uint32_t>{5, 5}));
  }
  {
    v1::QueryResponse other_step = b;
    other_step.set_step(4);
    AnswerReader reader;
    ASSERT_TRUE(reader.Append(a.SerializeAsString()).ok());
    const absl::Status s = reader.Append(other_step.SerializeAsString());
    EXPECT_EQ(s.code(), absl::StatusCode::kInternal);
    EXPECT_NE(s.message().find("mixes steps 3 and 4"), std::string::npos);
  }
  {
    v1::QueryResponse gap = b;
    gap.set_first_row(2);
    AnswerReader reader;
    ASSERT_TRUE(reader.Append(a.SerializeAsString()).ok());
    const absl::Status s = reader.Append(gap.SerializeAsString());
    EXPECT_EQ(s.code(), absl::StatusCode::kInternal);
    EXPECT_NE(s.message().find("starts at row 2, expected 1"),
              std::string::npos);
  }
}

TEST(AnswerReader, ByteBuffersInManySlicesEqualOneString) {
  std::mt19937_64 rng(3);
  const std::string bytes =
      RandomChunk(rng, 1, 0, 500, false).SerializeAsString();
  std::vector<grpc::Slice> slices;
  for (size_t i = 0; i < bytes.size();) {
    const size_t len = std::min(bytes.size() - i, 1 + rng() % 4000);
    slices.emplace_back(bytes.data() + i, len);
    i += len;
  }
  ASSERT_GT(slices.size(), 1u);
  grpc::ByteBuffer buffer(slices.data(), slices.size());
  AnswerReader from_slices, from_string;
  ASSERT_TRUE(from_slices.Append(buffer).ok());
  ASSERT_TRUE(from_string.Append(bytes).ok());
  ExpectSame(from_slices.rows(), from_string.rows());
  grpc::Slice one(bytes.data(), bytes.size());
  AnswerReader from_one;
  ASSERT_TRUE(from_one.Append(grpc::ByteBuffer(&one, 1)).ok());
  ExpectSame(from_one.rows(), from_string.rows());
}

TEST(AnswerReader, ReadsTheServersChunks) {
  // The server's writer (server/convert.h) cutting rows into chunks, split
  // rows included, with internal or client ids, read back into the rows.
  std::mt19937_64 rng(13);
  for (int trial = 0; trial < 80; ++trial) {
    const bool by_client = trial % 2 == 1;
    const v1::AnswerEncoding encoding =
        trial % 4 >= 2 ? v1::ANSWER_ENCODING_FIXED : v1::ANSWER_ENCODING_VARINT;
    std::vector<uint64_t> client_map(1000);
    for (uint64_t& id : client_map) id = rng() >> (rng() % 64);
    core::NeighborLists l;
    l.offsets.push_back(0);
    const int rows = 1 + static_cast<int>(rng() % 400);
    std::vector<uint64_t> truncated;
    for (int r = 0; r < rows; ++r) {
      const int len = static_cast<int>(rng() % 30);
      for (int k = 0; k < len; ++k) {
        l.ids.push_back(by_client
                            ? static_cast<uint32_t>(rng() % 1000)
                            : static_cast<uint32_t>(rng() >> (rng() % 64)));
        l.distances.push_back(static_cast<double>(rng() % 1000) / 7.0);
      }
      l.offsets.push_back(l.ids.size());
      l.truncated.push_back(rng() % 9 == 0);
      if (l.truncated.back()) truncated.push_back(static_cast<uint64_t>(r));
    }
    server::ChunkCursor cursor(l, static_cast<uint64_t>(rows), 0,
                               static_cast<uint64_t>(rows), 17, true,
                               by_client ? &client_map : nullptr,
                               1 + rng() % 100, 1 + rng() % 200, encoding);
    AnswerReader reader;
    std::string wire;
    while (cursor.NextBytes(&wire)) {
      ASSERT_TRUE(reader.Append(wire).ok());
    }
    const Neighbors& got = reader.rows();
    EXPECT_EQ(got.step, 17u);
    EXPECT_EQ(got.offsets, l.offsets);
    if (by_client) {
      std::vector<uint64_t> want;
      for (uint32_t id : l.ids) want.push_back(client_map[id]);
      EXPECT_EQ(got.client_ids, want);
      EXPECT_TRUE(got.ids.empty());
    } else {
      EXPECT_EQ(got.ids, l.ids);
    }
    EXPECT_EQ(got.distances, l.distances);
    EXPECT_EQ(got.truncated_rows, truncated);
  }
}

}  // namespace
}  // namespace kinetri
