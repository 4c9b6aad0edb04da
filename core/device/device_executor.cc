// Registry of the device backends compiled into this binary.
#include "core/device/device_executor.h"

#include <atomic>
#include <cstdint>

#include "absl/strings/str_cat.h"

namespace kinetri::core::device {

#ifdef KINETRI_DEVICE_EMULATED
// Defined in core/device/emulated_backend.cc.
std::unique_ptr<DeviceExecutor> MakeEmulatedExecutor();
#endif

namespace {

struct Entry {
  std::atomic<DeviceExecutorFactory> make{nullptr};
  std::atomic<bool (*)()> available{nullptr};
  std::atomic<uint64_t (*)()> free_bytes{nullptr};
};

bool Always() { return true; }

Entry* Registry() {
  static Entry entries[2];
#ifdef KINETRI_DEVICE_EMULATED
  static const bool emulated = [] {
    entries[0].make = &MakeEmulatedExecutor;
    entries[0].available = &Always;
    return true;
  }();
  (void)emulated;
#endif
  return entries;
}

Entry& Of(DeviceBackend backend) {
  return Registry()[backend == DeviceBackend::kEmulated ? 0 : 1];
}

}  // namespace

const char* DeviceBackendName(DeviceBackend backend) {
  return backend == DeviceBackend::kEmulated ? "emulated" : "cuda";
}

LoopControl DefaultLoopControl(DeviceBackend backend) {
  LoopControl c;
  c.capacity = backend == DeviceBackend::kCuda ? 65536 : 1024;
  c.rounds_per_check = 8;
  return c;
}

void RegisterDeviceBackend(DeviceBackend backend, DeviceExecutorFactory make,
                           bool (*available)(), uint64_t (*free_bytes)()) {
  Entry& e = Of(backend);
  e.available = available;
  e.free_bytes = free_bytes;
  e.make = make;
}

uint64_t DeviceFreeBytes(DeviceBackend backend) {
  auto* free_bytes = Of(backend).free_bytes.load();
  return free_bytes != nullptr ? free_bytes() : UINT64_MAX;
}

bool DeviceBackendAvailable(DeviceBackend backend) {
  Entry& e = Of(backend);
  auto* available = e.available.load();
  return e.make.load() != nullptr && available != nullptr && available();
}

absl::StatusOr<std::unique_ptr<DeviceExecutor>> MakeDeviceExecutor(
    DeviceBackend backend) {
  if (!DeviceBackendAvailable(backend)) {
    return absl::FailedPreconditionError(absl::StrCat(
        "device backend '", DeviceBackendName(backend), "' is not available",
        backend == DeviceBackend::kCuda
            ? " (built without CUDA, not registered, or no GPU present)"
            : " (built without the CCCL headers)"));
  }
  return Of(backend).make.load()();
}

}  // namespace kinetri::core::device
