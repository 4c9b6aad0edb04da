// CUDA-only helpers: error conversion and an owning device buffer.
#ifndef KINETRI_CORE_DEVICE_DEVICE_BUFFER_H_
#define KINETRI_CORE_DEVICE_DEVICE_BUFFER_H_

#include <cuda_runtime.h>

#include <cstddef>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"

namespace kinetri::core::cuda {

inline absl::Status Check(cudaError_t e, const char* what) {
  if (e == cudaSuccess) return absl::OkStatus();
  return absl::InternalError(
      absl::StrCat("CUDA ", what, ": ", cudaGetErrorString(e)));
}

// Device buffer of T.
template <typename T>
struct Buffer {
  Buffer() = default;
  Buffer(const Buffer&) = delete;
  Buffer& operator=(const Buffer&) = delete;
  T* ptr = nullptr;
  size_t size = 0;
  absl::Status Allocate(size_t n) {
    if (ptr) cudaFree(ptr);
    ptr = nullptr;
    size = n;
    if (n == 0) return absl::OkStatus();
    return Check(cudaMalloc(&ptr, n * sizeof(T)), "malloc");
  }
  absl::Status Upload(const T* host, size_t n) {
    absl::Status s = Allocate(n);
    if (!s.ok() || n == 0) return s;
    return Check(cudaMemcpy(ptr, host, n * sizeof(T), cudaMemcpyHostToDevice),
                 "upload");
  }
  absl::Status Download(T* host, size_t n) const {
    if (n == 0) return absl::OkStatus();
    return Check(cudaMemcpy(host, ptr, n * sizeof(T), cudaMemcpyDeviceToHost),
                 "download");
  }
  ~Buffer() {
    if (ptr) cudaFree(ptr);
  }
};

}  // namespace kinetri::core::cuda

#endif  // KINETRI_CORE_DEVICE_DEVICE_BUFFER_H_
