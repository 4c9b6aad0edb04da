// The emulated device backend: core/device/round_executor.inl compiled by
// the host compiler with Thrust's TBB device system, so the device
// executor's source runs on CPU threads in every CI run. Its Thrust lives in
// its own namespace (THRUST_CUB_WRAPPED_NAMESPACE) so it never shares a
// symbol with the CUDA build linked into the same binary.
#define THRUST_DEVICE_SYSTEM THRUST_DEVICE_SYSTEM_TBB
#define THRUST_CUB_WRAPPED_NAMESPACE kinetri_thrust_emulated
#define KINETRI_DEVICE_NS emulated

#include "core/device/round_executor.inl"

namespace kinetri::core::device {

std::unique_ptr<DeviceExecutor> MakeEmulatedExecutor() {
  return emulated::MakeExecutor(DeviceBackend::kEmulated);
}

}  // namespace kinetri::core::device
