// The CUDA build of the device executor (core/device/round_executor.inl
// compiled by nvcc). Linked only where CUDA is built (kinetri::device_cuda).
#ifndef KINETRI_CORE_DEVICE_CUDA_BACKEND_H_
#define KINETRI_CORE_DEVICE_CUDA_BACKEND_H_

namespace kinetri::core::device {

// Registers DeviceBackend::kCuda with MakeDeviceExecutor (available when a
// GPU is present). Idempotent.
void RegisterCudaBackend();

}  // namespace kinetri::core::device

#endif  // KINETRI_CORE_DEVICE_CUDA_BACKEND_H_
