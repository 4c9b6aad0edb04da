// The device grid on the CUDA backend (nvcc, Thrust's CUDA system).
#define THRUST_CUB_WRAPPED_NAMESPACE kinetri_thrust_cuda
#define KINETRI_DEVICE_NS cuda_build

#include "bench/device_grid.inl"

namespace kinetri::bench {

std::unique_ptr<DeviceGrid> MakeCudaGrid() { return cuda_build::MakeGrid(); }

}  // namespace kinetri::bench
