// The CUDA device backend: core/device/round_executor.inl compiled by nvcc
// with Thrust's CUDA device system.
#define THRUST_CUB_WRAPPED_NAMESPACE kinetri_thrust_cuda
#define KINETRI_DEVICE_NS cuda_build

#include <cuda_runtime.h>

#include "core/device/cuda_backend.h"
#include "core/device/round_executor.inl"

namespace kinetri::core::device {
namespace {

bool GpuPresent() {
  int count = 0;
  return cudaGetDeviceCount(&count) == cudaSuccess && count > 0;
}

uint64_t GpuFreeBytes() {
  size_t free_bytes = 0, total = 0;
  if (cudaMemGetInfo(&free_bytes, &total) != cudaSuccess) return 0;
  return free_bytes;
}

std::unique_ptr<DeviceExecutor> MakeCudaExecutor() {
  return cuda_build::MakeExecutor(DeviceBackend::kCuda);
}

}  // namespace

void RegisterCudaBackend() {
  RegisterDeviceBackend(DeviceBackend::kCuda, &MakeCudaExecutor, &GpuPresent,
                        &GpuFreeBytes);
}

}  // namespace kinetri::core::device
