// Host <-> device copies through pinned staging buffers (part of the device
// source, see core/device/round_executor.inl).
//
// A copy from pageable host memory (a std::vector) goes through the
// driver's own staging at a fraction of the bus's speed: on the H100 of
// docs/DEVICE.md's fifth lease, 5.5 GB/s for the 52 MB download of a 1M
// mesh, 9.4 ms of every successful attempt. Here every copy goes through two
// pinned chunks owned by the caller: while the device transfers one chunk,
// the host copies the next into (or the previous out of) the other, so the
// host's copy and the bus's transfer overlap. The transfers are queued on
// the caller's stream, in order with its algorithms.
//
// On CPU threads (the emulated backend) the same chunks are plain host
// memory and both halves of a copy are memcpy; its chunks are small, so
// that the tests, whose meshes are small, cross chunk boundaries too.
#ifndef KINETRI_DEVICE_NS
#error "define KINETRI_DEVICE_NS before including staging.inl"
#endif
#ifndef KINETRI_CORE_DEVICE_STAGING_INL_
#define KINETRI_CORE_DEVICE_STAGING_INL_

#include <thrust/system_error.h>

#include <algorithm>
#include <cstddef>
#include <cstring>
#include <new>

#include "core/device/scratch_pool.inl"

namespace kinetri::core::device {
namespace KINETRI_DEVICE_NS {
namespace {

#if THRUST_DEVICE_SYSTEM == THRUST_DEVICE_SYSTEM_CUDA
inline constexpr size_t kStagingChunkBytes = size_t{4} << 20;
static_assert(2 * kStagingChunkBytes <= kCudaHostFixedBytes);
#else
inline constexpr size_t kStagingChunkBytes = size_t{16} << 10;
static_assert(2 * kStagingChunkBytes <= kEmulatedHostFixedBytes);
#endif

class Staging {
 public:
  Staging() = default;
  Staging(const Staging&) = delete;
  Staging& operator=(const Staging&) = delete;
  Staging(Staging&& other) noexcept { Take(other); }
  Staging& operator=(Staging&& other) noexcept {
    if (this != &other) {
      Release();
      Take(other);
    }
    return *this;
  }
  ~Staging() { Release(); }

  // device[0, n) = host[0, n), queued on `stream` (work queued there after
  // it sees the data). `host` may be reused when this returns.
  template <typename T>
  void ToDevice(const T* host, size_t n, T* device, Stream stream) {
    Up(reinterpret_cast<const char*>(host), reinterpret_cast<char*>(device),
       n * sizeof(T), stream);
  }
  // host[0, n) = device[0, n) once the work queued on `stream` before it is
  // done; returns with `host` filled.
  template <typename T>
  void ToHost(const T* device, size_t n, T* host, Stream stream) {
    Down(reinterpret_cast<const char*>(device), reinterpret_cast<char*>(host),
         n * sizeof(T), stream);
  }

  // Pinned host memory held (two chunks once a copy ran).
  size_t bytes() const {
    return buf_[0] != nullptr ? 2 * kStagingChunkBytes : 0;
  }

 private:
  void Ensure() {
    if (buf_[0] != nullptr) return;
#if THRUST_DEVICE_SYSTEM == THRUST_DEVICE_SYSTEM_CUDA
    for (int b = 0; b < 2; ++b) {
      void* p = nullptr;
      Check(cudaMallocHost(&p, kStagingChunkBytes), "pinned staging");
      buf_[b] = static_cast<char*>(p);
      Check(cudaEventCreateWithFlags(&done_[b], cudaEventDisableTiming),
            "staging event");
    }
#else
    for (int b = 0; b < 2; ++b) buf_[b] = new char[kStagingChunkBytes];
#endif
  }

  void Take(Staging& other) {
    for (int b = 0; b < 2; ++b) {
      buf_[b] = other.buf_[b];
      other.buf_[b] = nullptr;
#if THRUST_DEVICE_SYSTEM == THRUST_DEVICE_SYSTEM_CUDA
      done_[b] = other.done_[b];
      other.done_[b] = nullptr;
#endif
    }
  }

  void Release() {
#if THRUST_DEVICE_SYSTEM == THRUST_DEVICE_SYSTEM_CUDA
    for (int b = 0; b < 2; ++b) {
      if (buf_[b] == nullptr) continue;
      cudaEventSynchronize(done_[b]);
      cudaEventDestroy(done_[b]);
      cudaFreeHost(buf_[b]);
      buf_[b] = nullptr;
    }
#else
    for (int b = 0; b < 2; ++b) {
      delete[] buf_[b];
      buf_[b] = nullptr;
    }
#endif
  }

#if THRUST_DEVICE_SYSTEM == THRUST_DEVICE_SYSTEM_CUDA
  static void Check(cudaError_t e, const char* what) {
    if (e != cudaSuccess) {
      THRUST_NS_QUALIFIER::cuda_cub::throw_on_error(e, what);
    }
  }
#endif

  // Chunk k goes through buffer k % 2: the host fills it once the
  // transfer of chunk k - 2 out of it is done.
  void Up(const char* host, char* device, size_t bytes, Stream stream) {
    if (bytes == 0) return;
    Ensure();
    for (size_t off = 0, k = 0; off < bytes; off += kStagingChunkBytes, ++k) {
      const size_t len = std::min(kStagingChunkBytes, bytes - off);
      char* buf = buf_[k % 2];
#if THRUST_DEVICE_SYSTEM == THRUST_DEVICE_SYSTEM_CUDA
      Check(cudaEventSynchronize(done_[k % 2]), "staging: upload");
      std::memcpy(buf, host + off, len);
      Check(cudaMemcpyAsync(device + off, buf, len, cudaMemcpyHostToDevice,
                            stream),
            "staging: upload");
      Check(cudaEventRecord(done_[k % 2], stream), "staging: upload");
#else
      (void)stream;
      std::memcpy(buf, host + off, len);
      std::memcpy(device + off, buf, len);
#endif
    }
  }

  // Chunk k's transfer is queued, then chunk k - 1 (whose transfer was
  // queued before it) is copied out while chunk k crosses the bus.
  void Down(const char* device, char* host, size_t bytes, Stream stream) {
    if (bytes == 0) return;
    Ensure();
    size_t prev_off = 0, prev_len = 0;
    size_t k = 0;
    for (size_t off = 0; off < bytes; off += kStagingChunkBytes, ++k) {
      const size_t len = std::min(kStagingChunkBytes, bytes - off);
#if THRUST_DEVICE_SYSTEM == THRUST_DEVICE_SYSTEM_CUDA
      Check(cudaMemcpyAsync(buf_[k % 2], device + off, len,
                            cudaMemcpyDeviceToHost, stream),
            "staging: download");
      Check(cudaEventRecord(done_[k % 2], stream), "staging: download");
#else
      (void)stream;
      std::memcpy(buf_[k % 2], device + off, len);
#endif
      if (k > 0) CopyOut((k - 1) % 2, host + prev_off, prev_len);
      prev_off = off;
      prev_len = len;
    }
    CopyOut((k - 1) % 2, host + prev_off, prev_len);
  }

  void CopyOut(size_t b, char* to, size_t len) {
#if THRUST_DEVICE_SYSTEM == THRUST_DEVICE_SYSTEM_CUDA
    Check(cudaEventSynchronize(done_[b]), "staging: download");
#endif
    std::memcpy(to, buf_[b], len);
  }

  char* buf_[2] = {nullptr, nullptr};
#if THRUST_DEVICE_SYSTEM == THRUST_DEVICE_SYSTEM_CUDA
  cudaEvent_t done_[2] = {};
#endif
};

}  // namespace
}  // namespace KINETRI_DEVICE_NS
}  // namespace kinetri::core::device

#endif  // KINETRI_CORE_DEVICE_STAGING_INL_
