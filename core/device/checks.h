// KINETRI_DEVICE_CHECK, read once per process (docs/DEVICE.md): unset or 0,
// the device executor trusts what its caller tells it about the host's
// arrays (DeviceExecutor::PositionsWrittenAt, ChangedOnHost); 1, it checks each
// such promise by a pass of its own, and a broken one costs a whole comparison
// and counts as a resync (DeviceAttempt::resyncs), which the device test
// suites require to be zero. The tests run with it; a service does not.
// Host code only.
#ifndef KINETRI_CORE_DEVICE_CHECKS_H_
#define KINETRI_CORE_DEVICE_CHECKS_H_

#include <cstdlib>

namespace kinetri::core::device {

inline bool DeviceChecksOn() {
  static const bool on = [] {
    const char* v = std::getenv("KINETRI_DEVICE_CHECK");
    return v != nullptr && v[0] != '\0' && v[0] != '0';
  }();
  return on;
}

}  // namespace kinetri::core::device

#endif  // KINETRI_CORE_DEVICE_CHECKS_H_
