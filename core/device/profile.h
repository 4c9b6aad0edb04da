// KINETRI_DEVICE_PROFILE, read once per process (docs/DEVICE.md): unset or
// 0, nothing is printed; 1, each device executor prints its totals when it
// is destroyed; 2, also a line per attempt and per query call (so a run cut
// off by a time limit still leaves its numbers). Host code only.
#ifndef KINETRI_CORE_DEVICE_PROFILE_H_
#define KINETRI_CORE_DEVICE_PROFILE_H_

#include <cstdlib>

namespace kinetri::core::device {

inline int DeviceProfileLevel() {
  static const int level = [] {
    const char* v = std::getenv("KINETRI_DEVICE_PROFILE");
    if (v == nullptr || v[0] == '\0' || v[0] == '0') return 0;
    return v[0] == '2' ? 2 : 1;
  }();
  return level;
}

}  // namespace kinetri::core::device

#endif  // KINETRI_CORE_DEVICE_PROFILE_H_
