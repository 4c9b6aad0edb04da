// Query answers cut into response chunks (server/convert.h ChunkCursor):
// the bytes it writes parse as QueryResponse messages that hold the rows
// (whole rows while they fit, a longer row split with last_row_continues),
// and protobuf serializes those messages back to the same bytes, in the
// varint and the fixed-width encoding of offsets and ids.
#include "server/convert.h"

#include <gtest/gtest.h>

#include <cstdint>
#include <random>
#include <string>
#include <vector>

#include "core/query_types.h"
#include "kinetri/v1/kinetri.pb.h"

namespace kinetri::server {
namespace {

// Rows of up to max_row results; ids below id_bound (0: of every varint
// length up to 5 bytes).
core::NeighborLists RandomLists(uint64_t rows, uint64_t max_row,
                                uint32_t id_bound, uint64_t seed) {
  std::mt19937_64 rng(seed);
  core::NeighborLists l;
  l.offsets.push_back(0);
  for (uint64_t r = 0; r < rows; ++r) {
    const uint64_t len = rng() % (max_row + 1);
    for (uint64_t k = 0; k < len; ++k) {
      const uint32_t id = static_cast<uint32_t>(rng() >> (rng() % 64));
      l.ids.push_back(id_bound == 0 ? id : id % id_bound);
      l.distances.push_back(std::ldexp(double(rng() % 1000), -int(rng() % 40)));
    }
    l.offsets.push_back(l.ids.size());
    l.truncated.push_back(rng() % 5 == 0 ? 1 : 0);
  }
  return l;
}

struct Case {
  uint64_t rows, max_row, rows_per_chunk, results_per_chunk;
  bool distances, client_ids;
  bool fixed = false;  // ANSWER_ENCODING_FIXED
};

// A chunk's offsets, ids and client ids from the fields of its encoding;
// the other encoding's fields must be empty.
template <typename T, typename Repeated>
std::vector<T> Values(const Repeated& used, int other_size) {
  EXPECT_EQ(other_size, 0) << "a field of the other encoding has values";
  return std::vector<T>(used.begin(), used.end());
}

void Check(const Case& c, uint64_t seed) {
  SCOPED_TRACE(testing::Message()
               << "rows " << c.rows << " max_row " << c.max_row
               << " rows_per_chunk " << c.rows_per_chunk
               << " results_per_chunk " << c.results_per_chunk << " distances "
               << c.distances << " client " << c.client_ids << " fixed "
               << c.fixed);
  const core::NeighborLists l =
      RandomLists(c.rows, c.max_row, c.client_ids ? 5000 : 0, seed);
  std::vector<uint64_t> client;
  if (c.client_ids) {
    std::mt19937_64 rng(seed + 1);
    uint32_t most = 0;
    for (uint32_t id : l.ids) most = std::max(most, id);
    client.resize(uint64_t{most} + 1);
    for (uint64_t& x : client) x = rng() >> (rng() % 64);
  }
  const uint64_t first = 1000, total = c.rows + 2000, step = seed % 3;
  ChunkCursor cursor(
      l, c.rows, first, total, step, c.distances,
      c.client_ids ? &client : nullptr, c.rows_per_chunk, c.results_per_chunk,
      c.fixed ? v1::ANSWER_ENCODING_FIXED : v1::ANSWER_ENCODING_VARINT);
  // Rows put back together from the chunks.
  std::vector<uint64_t> ids, row_len;
  std::vector<double> distances;
  std::vector<uint64_t> truncated;
  uint64_t row = 0, chunks = 0;
  bool continuing = false;
  std::string bytes;
  while (cursor.NextBytes(&bytes)) {
    ++chunks;
    v1::QueryResponse m;
    ASSERT_TRUE(m.ParseFromString(bytes)) << "chunk " << chunks;
    std::string again;
    ASSERT_TRUE(m.SerializeToString(&again));
    ASSERT_EQ(again, bytes) << "chunk " << chunks;
    EXPECT_EQ(m.step(), step);
    EXPECT_EQ(m.total_rows(), total);
    EXPECT_EQ(m.first_row(), first + row);
    const std::vector<uint64_t> offsets =
        c.fixed ? Values<uint64_t>(m.fixed_offsets(), m.offsets_size())
                : Values<uint64_t>(m.offsets(), m.fixed_offsets_size());
    const std::vector<uint64_t> chunk_ids =
        c.client_ids
            ? (c.fixed
                   ? Values<uint64_t>(m.fixed_client_ids(), m.client_ids_size())
                   : Values<uint64_t>(m.client_ids(),
                                      m.fixed_client_ids_size()))
            : (c.fixed ? Values<uint64_t>(m.fixed_ids(), m.ids_size())
                       : Values<uint64_t>(m.ids(), m.fixed_ids_size()));
    EXPECT_EQ(m.ids_size() + m.fixed_ids_size() > 0 &&
                  m.client_ids_size() + m.fixed_client_ids_size() > 0,
              false);
    ASSERT_GE(offsets.size(), 1u);
    EXPECT_EQ(offsets[0], 0u);
    const uint64_t results = offsets.back();
    EXPECT_LE(results, c.results_per_chunk);
    EXPECT_LE(uint64_t(offsets.size() - 1), c.rows_per_chunk);
    ASSERT_EQ(chunk_ids.size(), results);
    ids.insert(ids.end(), chunk_ids.begin(), chunk_ids.end());
    ASSERT_EQ(uint64_t(m.distances_size()), c.distances ? results : 0);
    distances.insert(distances.end(), m.distances().begin(),
                     m.distances().end());
    for (uint32_t t : m.truncated_rows()) truncated.push_back(row + t);
    for (size_t k = 1; k < offsets.size(); ++k) {
      const uint64_t len = offsets[k] - offsets[k - 1];
      if (continuing && k == 1) {
        row_len.back() += len;
      } else {
        row_len.push_back(len);
      }
    }
    continuing = m.last_row_continues();
    row += offsets.size() - 1 - (continuing ? 1 : 0);
  }
  EXPECT_FALSE(continuing);
  EXPECT_GE(chunks, 1u);
  ASSERT_EQ(row_len.size(), c.rows);
  std::vector<uint64_t> want_truncated;
  for (uint64_t r = 0; r < c.rows; ++r) {
    ASSERT_EQ(row_len[r], l.offsets[r + 1] - l.offsets[r]) << "row " << r;
    if (l.truncated[r]) want_truncated.push_back(r);
  }
  EXPECT_EQ(truncated, want_truncated);
  ASSERT_EQ(ids.size(), l.ids.size());
  for (size_t k = 0; k < ids.size(); ++k) {
    ASSERT_EQ(ids[k], c.client_ids ? client[l.ids[k]] : l.ids[k]);
  }
  if (c.distances) {
    EXPECT_EQ(distances, l.distances);
  }
}

TEST(ChunkCursor, BytesAreTheQueryResponsesOfTheRows) {
  const Case cases[] = {
      {0, 4, 16, 100, true, false},   // no rows: one empty chunk
      {1, 0, 16, 100, false, false},  // one empty row
      {500, 12, 16384, 196608, true, false},
      {500, 12, 7, 196608, false, false},  // many chunks by rows
      {300, 40, 1000, 25, true, false},    // rows split across chunks
      {300, 40, 1000, 25, true, true},     // client ids, split rows
      {200, 3, 1, 2, true, true},
  };
  uint64_t seed = 1;
  for (Case c : cases) {
    Check(c, seed);
    c.fixed = true;
    Check(c, seed++);
  }
}

// Ids at every varint length boundary (1 to 5 bytes), each written as
// protobuf writes it.
TEST(ChunkCursor, IdsAtVarintLengthBoundaries) {
  core::NeighborLists l;
  l.offsets.push_back(0);
  for (int bits = 0; bits <= 32; ++bits) {
    const uint64_t at = uint64_t{1} << bits;
    for (uint64_t id : {at - 1, at, at + 1}) {
      if (id > UINT32_MAX) continue;
      l.ids.push_back(static_cast<uint32_t>(id));
      l.distances.push_back(static_cast<double>(id));
    }
    l.offsets.push_back(l.ids.size());
    l.truncated.push_back(0);
  }
  const uint64_t rows = l.offsets.size() - 1;
  ChunkCursor cursor(l, rows, 0, rows, 7, true, nullptr, 16384, 196608);
  std::string bytes;
  ASSERT_TRUE(cursor.NextBytes(&bytes));
  v1::QueryResponse want;
  want.set_step(7);
  want.set_total_rows(rows);
  want.mutable_offsets()->Add(l.offsets.begin(), l.offsets.end());
  want.mutable_ids()->Add(l.ids.begin(), l.ids.end());
  want.mutable_distances()->Add(l.distances.begin(), l.distances.end());
  EXPECT_EQ(bytes, want.SerializeAsString());
  EXPECT_FALSE(cursor.NextBytes(&bytes));
  // The same rows in fixed-width fields.
  ChunkCursor fixed(l, rows, 0, rows, 7, true, nullptr, 16384, 196608,
                    v1::ANSWER_ENCODING_FIXED);
  ASSERT_TRUE(fixed.NextBytes(&bytes));
  want.clear_offsets();
  want.clear_ids();
  want.mutable_fixed_offsets()->Add(l.offsets.begin(), l.offsets.end());
  want.mutable_fixed_ids()->Add(l.ids.begin(), l.ids.end());
  EXPECT_EQ(bytes, want.SerializeAsString());
  EXPECT_FALSE(fixed.NextBytes(&bytes));
}

TEST(ChunkCursor, FixedWidthClientIdsAndSplitRowsKeepProtobufsBytes) {
  // Client ids of every size, a row longer than a chunk, truncated rows:
  // each chunk is the bytes protobuf writes for the message it parses as
  // (Check above) and holds no varint offsets or ids.
  core::NeighborLists l;
  l.offsets = {0, 3, 40, 41};
  for (uint32_t i = 0; i < 41; ++i) {
    l.ids.push_back(i % 5);
    l.distances.push_back(i * 0.5);
  }
  l.truncated = {0, 1, 0};
  const std::vector<uint64_t> client = {0, 1, UINT64_MAX, uint64_t{1} << 40,
                                        127};
  ChunkCursor cursor(l, 3, 0, 3, 2, false, &client, 100, 16,
                     v1::ANSWER_ENCODING_FIXED);
  std::string bytes;
  std::vector<uint64_t> got;
  int chunks = 0;
  while (cursor.NextBytes(&bytes)) {
    ++chunks;
    v1::QueryResponse m;
    ASSERT_TRUE(m.ParseFromString(bytes));
    EXPECT_EQ(m.SerializeAsString(), bytes);
    EXPECT_EQ(m.offsets_size() + m.ids_size() + m.client_ids_size() +
                  m.fixed_ids_size() + m.distances_size(),
              0);
    got.insert(got.end(), m.fixed_client_ids().begin(),
               m.fixed_client_ids().end());
  }
  EXPECT_EQ(chunks, 4);  // 3 + 16 + 16 + 6 results
  std::vector<uint64_t> want;
  for (uint32_t id : l.ids) want.push_back(client[id]);
  EXPECT_EQ(got, want);
}

}  // namespace
}  // namespace kinetri::server
