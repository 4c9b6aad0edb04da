// One device failure on demand, for tests (DeviceExecutor::InjectFault):
// the device executor asks BeforeCall() before each device algorithm of its
// attempts and queries, and the armed call throws what the CUDA system
// throws when it fails: std::bad_alloc for exhausted memory, a
// std::runtime_error (as thrust::system_error is) for a failed call. The
// executor's ordinary error handling then runs: that is what it tests.
#ifndef KINETRI_CORE_DEVICE_FAULT_INJECTOR_H_
#define KINETRI_CORE_DEVICE_FAULT_INJECTOR_H_

#include <atomic>
#include <cstdint>
#include <mutex>
#include <new>
#include <stdexcept>

#include "core/device/device_executor.h"

namespace kinetri::core::device {

class FaultInjector {
 public:
  // Arms (Kind::kNone: disarms) one failure, `after_calls` device calls
  // from now (0: the next one).
  void Arm(const DeviceFault& fault) {
    std::lock_guard<std::mutex> lock(mu_);
    fault_ = fault;
    armed_.store(fault.kind != DeviceFault::Kind::kNone,
                 std::memory_order_relaxed);
  }
  bool armed() const { return armed_.load(std::memory_order_relaxed); }

  // Throws when this is the armed call; otherwise counts it. One relaxed
  // load when nothing is armed.
  void BeforeCall() {
    if (!armed_.load(std::memory_order_relaxed)) return;
    std::lock_guard<std::mutex> lock(mu_);
    if (fault_.kind == DeviceFault::Kind::kNone) return;
    if (fault_.after_calls > 0) {
      --fault_.after_calls;
      return;
    }
    const DeviceFault::Kind kind = fault_.kind;
    fault_.kind = DeviceFault::Kind::kNone;
    armed_.store(false, std::memory_order_relaxed);
    if (kind == DeviceFault::Kind::kOutOfMemory) throw std::bad_alloc();
    throw std::runtime_error("injected device fault");
  }

 private:
  std::atomic<bool> armed_{false};
  std::mutex mu_;
  DeviceFault fault_;
};

}  // namespace kinetri::core::device

#endif  // KINETRI_CORE_DEVICE_FAULT_INJECTOR_H_
