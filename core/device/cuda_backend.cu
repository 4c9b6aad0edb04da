// The CUDA device backend: core/device/round_executor.inl compiled by nvcc
// with Thrust's CUDA device system.
#define THRUST_CUB_WRAPPED_NAMESPACE kinetri_thrust_cuda
#define KINETRI_DEVICE_NS cuda_build

#include <cuda_runtime.h>

#include <cstdio>
#include <cstdlib>

#include "core/device/cuda_backend.h"
#include "core/device/profile.h"
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
  // The exact predicates keep their expansions in per-thread local memory
  // (the exact in-circle's frame is about 45 KiB). The driver raises the
  // per-thread stack to what a launch needs (seen on an H200: 1,024 ->
  // 45,504 bytes at the first such launch; docs/DEVICE.md), so the limit is
  // left alone by default. KINETRI_CUDA_STACK_BYTES sets it once per
  // process, to measure what a fixed limit changes.
  static const cudaError_t stack_limit = [] {
    size_t bytes = 0;
    if (const char* env = std::getenv("KINETRI_CUDA_STACK_BYTES")) {
      bytes = std::strtoull(env, nullptr, 10);
    }
    const cudaError_t e = bytes != 0
                              ? cudaDeviceSetLimit(cudaLimitStackSize, bytes)
                              : cudaSuccess;
    if (DeviceProfileLevel() > 0) {
      size_t now = 0;
      cudaDeviceGetLimit(&now, cudaLimitStackSize);
      std::fprintf(stderr,
                   "[device profile] stack limit: asked %zu bytes (%s), now "
                   "%zu bytes\n",
                   bytes, cudaGetErrorString(e), now);
    }
    return e;
  }();
  (void)stack_limit;
  return cuda_build::MakeExecutor(DeviceBackend::kCuda);
}

}  // namespace

void RegisterCudaBackend() {
  RegisterDeviceBackend(DeviceBackend::kCuda, &MakeCudaExecutor, &GpuPresent,
                        &GpuFreeBytes);
}

}  // namespace kinetri::core::device
