// CallSiteClock (core/device/profile.h): time between marks goes to the
// line marked first, calls are counted per line, and the lines with the
// most time are printed first.
#include <gtest/gtest.h>

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <thread>

#include "core/device/profile.h"

namespace kinetri::core::device {
namespace {

void SleepMs(int ms) {
  std::this_thread::sleep_for(std::chrono::milliseconds(ms));
}

std::string Printed(const CallSiteClock& clock, int top) {
  char buf[4096] = {};
  std::FILE* f = fmemopen(buf, sizeof(buf) - 1, "w");
  clock.Print(f, "x.inl", top);
  std::fclose(f);
  return buf;
}

TEST(CallSiteClock, TimeGoesToTheLineMarkedBefore) {
  // The profile level is read once per process: set it before first use.
  setenv("KINETRI_DEVICE_PROFILE", "1", 1);
  ASSERT_EQ(DeviceProfileLevel(), 1);
  CallSiteClock clock;
  for (int i = 0; i < 2; ++i) {
    clock.Mark(10);
    SleepMs(30);
    clock.Mark(20);
    SleepMs(2);
    clock.Stop();
  }
  SleepMs(300);  // after Stop: counted nowhere
  const std::string out = Printed(clock, 16);
  const size_t l10 = out.find("x.inl:10: 2 calls");
  const size_t l20 = out.find("x.inl:20: 2 calls");
  ASSERT_NE(l10, std::string::npos) << out;
  ASSERT_NE(l20, std::string::npos) << out;
  EXPECT_LT(l10, l20) << "the line with the most time comes first:\n" << out;
  // Line 10 holds its two 30 ms sleeps; the 300 ms after Stop count
  // nowhere.
  double ms10 = 0, ms20 = 0;
  ASSERT_EQ(std::sscanf(out.c_str() + l10, "x.inl:10: 2 calls, %lf ms", &ms10),
            1);
  ASSERT_EQ(std::sscanf(out.c_str() + l20, "x.inl:20: 2 calls, %lf ms", &ms20),
            1);
  EXPECT_GE(ms10, 59.0);
  EXPECT_GE(ms20, 3.9);
  EXPECT_LT(ms10 + ms20, 300.0);
  // Only the top lines are printed.
  EXPECT_EQ(Printed(clock, 1).find("x.inl:20"), std::string::npos);
}

}  // namespace
}  // namespace kinetri::core::device
