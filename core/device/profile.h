// KINETRI_DEVICE_PROFILE, read once per process (docs/DEVICE.md): unset or
// 0, nothing is printed; 1, each device executor prints its totals when it
// is destroyed, with the time of each call site of the update path
// (CallSiteClock below); 2, also a line per attempt and per query call (so
// a run cut off by a time limit still leaves its numbers). Host code only.
#ifndef KINETRI_CORE_DEVICE_PROFILE_H_
#define KINETRI_CORE_DEVICE_PROFILE_H_

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <map>
#include <vector>

namespace kinetri::core::device {

inline int DeviceProfileLevel() {
  static const int level = [] {
    const char* v = std::getenv("KINETRI_DEVICE_PROFILE");
    if (v == nullptr || v[0] == '\0' || v[0] == '0') return 0;
    return v[0] == '2' ? 2 : 1;
  }();
  return level;
}

// Where a single-threaded driver's time goes, by source line: Mark(line) at
// each device algorithm's call site gives the time since the previous mark
// to the previous line (the algorithm called there and the host work after
// it, up to the next call); Stop() closes the last one. Marks cost nothing
// while the profile is off.
class CallSiteClock {
 public:
  void Mark(int line) {
    if (DeviceProfileLevel() == 0) return;
    const auto now = std::chrono::steady_clock::now();
    Close(now);
    line_ = line;
    since_ = now;
  }
  void Stop() {
    if (DeviceProfileLevel() == 0) return;
    Close(std::chrono::steady_clock::now());
    line_ = kNone;
  }
  // The `top` lines with the most time, one per line of `out`.
  void Print(std::FILE* out, const char* file, int top) const {
    std::vector<std::pair<int, Site>> sites(by_line_.begin(), by_line_.end());
    std::sort(sites.begin(), sites.end(), [](const auto& a, const auto& b) {
      return a.second.seconds > b.second.seconds;
    });
    if (static_cast<int>(sites.size()) > top) sites.resize(top);
    for (const auto& [line, site] : sites) {
      std::fprintf(out,
                   "[device profile]   %s:%d: %llu calls, %.1f ms, %.1f us "
                   "each\n",
                   file, line, static_cast<unsigned long long>(site.calls),
                   1e3 * site.seconds, 1e6 * site.seconds / site.calls);
    }
  }

 private:
  static constexpr int kNone = -1;
  struct Site {
    unsigned long long calls = 0;
    double seconds = 0.0;
  };
  void Close(std::chrono::steady_clock::time_point now) {
    if (line_ == kNone) return;
    Site& site = by_line_[line_];
    ++site.calls;
    site.seconds += std::chrono::duration<double>(now - since_).count();
  }
  int line_ = kNone;
  std::chrono::steady_clock::time_point since_;
  std::map<int, Site> by_line_;
};

}  // namespace kinetri::core::device

#endif  // KINETRI_CORE_DEVICE_PROFILE_H_
