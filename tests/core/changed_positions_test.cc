// device::ChangedPositions: the positions an attempt sends to the device as
// changes, found in parallel blocks.
#include "core/device/changed_positions.h"

#include <gtest/gtest.h>
#include <tbb/task_arena.h>

#include <cmath>
#include <cstdint>
#include <cstring>
#include <random>
#include <vector>

namespace kinetri::core::device {
namespace {

// The serial scan it replaced.
void Serial(const std::vector<Vec2>& now, const std::vector<Vec2>& mirror,
            std::vector<uint32_t>* index, std::vector<Vec2>* value) {
  for (size_t i = 0; i < now.size(); ++i) {
    if (std::memcmp(&now[i], &mirror[i], sizeof(Vec2)) != 0) {
      index->push_back(static_cast<uint32_t>(i));
      value->push_back(now[i]);
    }
  }
}

TEST(ChangedPositions, FindsEveryChangedEntryInOrder) {
  std::mt19937_64 rng(1);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  for (const size_t n : {size_t{0}, size_t{1}, size_t{1000}, size_t{300001}}) {
    std::vector<Vec2> mirror(n);
    for (Vec2& p : mirror) p = {u(rng), u(rng)};
    for (const size_t changes : {size_t{0}, size_t{1}, n / 50, n / 5}) {
      std::vector<Vec2> now = mirror;
      for (size_t k = 0; k < changes && n > 0; ++k) {
        const size_t i = rng() % n;
        // (The smallest change too: one unit in the last place.)
        now[i].x =
            (k % 3 == 0) ? std::nextafter(now[i].x, 2.0) : now[i].x + u(rng);
      }
      std::vector<uint32_t> want_index, index{7};
      std::vector<Vec2> want_value, value;
      Serial(now, mirror, &want_index, &want_value);
      const size_t most = n / 4 + 1;
      ASSERT_TRUE(ChangedPositions(now, mirror, most, &index, &value))
          << n << " " << changes;
      EXPECT_EQ(index, want_index) << n << " " << changes;
      ASSERT_EQ(value.size(), want_value.size());
      for (size_t k = 0; k < value.size(); ++k) {
        EXPECT_EQ(std::memcmp(&value[k], &want_value[k], sizeof(Vec2)), 0);
      }
      // One thread finds the same.
      std::vector<uint32_t> one_index;
      std::vector<Vec2> one_value;
      tbb::task_arena(1).execute([&] {
        ASSERT_TRUE(
            ChangedPositions(now, mirror, most, &one_index, &one_value));
      });
      EXPECT_EQ(one_index, want_index);
    }
  }
}

// Bits, not values: -0.0 differs from 0.0, and a NaN equal bit for bit does
// not differ.
TEST(ChangedPositions, ComparesBits) {
  std::vector<Vec2> mirror = {{0.0, 1.0}, {std::nan(""), 2.0}, {3.0, 4.0}};
  std::vector<Vec2> now = mirror;
  now[0].x = -0.0;
  std::vector<uint32_t> index;
  std::vector<Vec2> value;
  ASSERT_TRUE(ChangedPositions(now, mirror, 3, &index, &value));
  EXPECT_EQ(index, std::vector<uint32_t>{0});
}

// More than `most` changes: false, whatever the split.
TEST(ChangedPositions, MoreThanMostIsRefused) {
  const size_t n = 200000;
  std::vector<Vec2> mirror(n, Vec2{0.5, 0.5});
  std::vector<Vec2> now = mirror;
  for (size_t i = 0; i < n; i += 3) now[i].y = 0.25;  // 66,667 changes
  std::vector<uint32_t> index;
  std::vector<Vec2> value;
  EXPECT_FALSE(ChangedPositions(now, mirror, n / 4 - 1, &index, &value));
  EXPECT_FALSE(ChangedPositions(now, mirror, 66666, &index, &value));
  tbb::task_arena(1).execute([&] {
    EXPECT_FALSE(ChangedPositions(now, mirror, 66666, &index, &value));
  });
  ASSERT_TRUE(ChangedPositions(now, mirror, 66667, &index, &value));
  EXPECT_EQ(index.size(), 66667u);
  EXPECT_EQ(index.back(), 199998u);
}

// Looking only where the caller wrote: the changed entries among them, in
// their order; an entry written with its old value is no change; more than
// `most` changes are refused.
TEST(ChangedPositions, AtTheWrittenEntriesOnly) {
  std::mt19937_64 rng(3);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  const size_t n = 5000;
  std::vector<Vec2> mirror(n);
  for (Vec2& p : mirror) p = {u(rng), u(rng)};
  std::vector<Vec2> now = mirror;
  std::vector<uint32_t> written;
  std::vector<uint32_t> want_index;
  std::vector<Vec2> want_value;
  for (uint32_t i = 7; i < n; i += 13) {
    written.push_back(i);
    if (i % 2 == 0) continue;  // written with its old value
    now[i].y = std::nextafter(now[i].y, 2.0);
    want_index.push_back(i);
    want_value.push_back(now[i]);
  }
  std::vector<uint32_t> index;
  std::vector<Vec2> value;
  ASSERT_TRUE(ChangedPositionsAt(now, mirror, written, n, &index, &value));
  EXPECT_EQ(index, want_index);
  ASSERT_EQ(value.size(), want_value.size());
  for (size_t k = 0; k < value.size(); ++k) {
    EXPECT_EQ(std::memcmp(&value[k], &want_value[k], sizeof(Vec2)), 0);
  }
  // The whole pass agrees.
  std::vector<uint32_t> all_index;
  std::vector<Vec2> all_value;
  ASSERT_TRUE(ChangedPositions(now, mirror, n, &all_index, &all_value));
  EXPECT_EQ(all_index, want_index);
  // A change outside the list is not seen there (the caller's promise).
  now[0].x += 1.0;
  ASSERT_TRUE(ChangedPositionsAt(now, mirror, written, n, &index, &value));
  EXPECT_EQ(index, want_index);
  // At most `most`.
  EXPECT_FALSE(ChangedPositionsAt(now, mirror, written, want_index.size() - 1,
                                  &index, &value));
  EXPECT_TRUE(ChangedPositionsAt(now, mirror, written, want_index.size(),
                                 &index, &value));
}

}  // namespace
}  // namespace kinetri::core::device
