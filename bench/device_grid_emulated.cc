// The device grid on the emulated backend (Thrust's TBB device system).
#define THRUST_DEVICE_SYSTEM THRUST_DEVICE_SYSTEM_TBB
#define THRUST_CUB_WRAPPED_NAMESPACE kinetri_thrust_emulated
#define KINETRI_DEVICE_NS emulated

#include "bench/device_grid.inl"

namespace kinetri::bench {

#ifdef KINETRI_BENCH_CUDA
std::unique_ptr<DeviceGrid> MakeCudaGrid();  // device_grid_cuda.cu
#endif

std::unique_ptr<DeviceGrid> MakeDeviceGrid(
    core::device::DeviceBackend backend) {
  if (!core::device::DeviceBackendAvailable(backend)) return nullptr;
  switch (backend) {
    case core::device::DeviceBackend::kEmulated:
      return emulated::MakeGrid();
    case core::device::DeviceBackend::kCuda:
#ifdef KINETRI_BENCH_CUDA
      return MakeCudaGrid();
#else
      return nullptr;
#endif
  }
  return nullptr;
}

}  // namespace kinetri::bench
