// The server's memory budget: reservations, growth and release.
#include "server/memory_budget.h"

#include <gtest/gtest.h>

#include <utility>

namespace kinetri::server {
namespace {

TEST(MemoryBudget, ReservesGrowsAndReleases) {
  MemoryBudget budget(1000);
  auto a = budget.Reserve(600, "a");
  ASSERT_TRUE(a.ok()) << a.status();
  EXPECT_EQ(budget.used(), 600u);
  // 500 more does not fit: refused with what it was for, nothing taken.
  auto b = budget.Reserve(500, "b");
  EXPECT_EQ(b.status().code(), absl::StatusCode::kResourceExhausted);
  EXPECT_NE(b.status().message().find("b: needs"), std::string::npos)
      << b.status();
  EXPECT_EQ(budget.used(), 600u);
  // Growth takes the difference; a refused growth leaves it as it was;
  // growing to less changes nothing.
  MemoryBudget::Reservation grown;
  EXPECT_TRUE(budget.GrowTo(&grown, 100, "g").ok());
  EXPECT_TRUE(budget.GrowTo(&grown, 300, "g").ok());
  EXPECT_EQ(grown.bytes(), 300u);
  EXPECT_EQ(budget.used(), 900u);
  const absl::Status refused = budget.GrowTo(&grown, 500, "answer");
  EXPECT_EQ(refused.code(), absl::StatusCode::kResourceExhausted);
  EXPECT_NE(refused.message().find("answer"), std::string::npos) << refused;
  EXPECT_EQ(grown.bytes(), 300u);
  EXPECT_EQ(budget.used(), 900u);
  EXPECT_TRUE(budget.GrowTo(&grown, 200, "g").ok());
  EXPECT_EQ(budget.used(), 900u);
  // Moves carry the bytes; destruction and Release return them.
  MemoryBudget::Reservation moved = std::move(grown);
  EXPECT_EQ(moved.bytes(), 300u);
  EXPECT_EQ(budget.used(), 900u);
  { MemoryBudget::Reservation gone = std::move(moved); }
  EXPECT_EQ(budget.used(), 600u);
  a->Release();
  EXPECT_EQ(budget.used(), 0u);
}

TEST(MemoryBudget, NoLimitAdmitsEverything) {
  MemoryBudget budget(0);
  MemoryBudget::Reservation r;
  EXPECT_TRUE(budget.GrowTo(&r, uint64_t{1} << 50, "huge").ok());
  EXPECT_EQ(budget.used(), uint64_t{1} << 50);
}

}  // namespace
}  // namespace kinetri::server
