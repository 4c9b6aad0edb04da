// The device executor's pool of temporary storage (part of the device
// source, see core/device/round_executor.inl): every Thrust algorithm of the
// executor takes its scratch (sort buffers, selection counts, reduction
// partials) from here through Policy(), so after the first rounds no call
// allocates device memory. Without it each algorithm pays a cudaMalloc and
// a synchronizing cudaFree (on the H200 of docs/DEVICE.md a few
// microseconds each: not what made the first GPU runs slow).
//
// Blocks come in power-of-two size classes (at least 256 bytes) and go back
// to their class's free list; Trim() hands cached blocks back to the device
// beyond a byte budget. Safe for concurrent callers.
#ifndef KINETRI_DEVICE_NS
#error "define KINETRI_DEVICE_NS before including scratch_pool.inl"
#endif
#ifndef KINETRI_CORE_DEVICE_SCRATCH_POOL_INL_
#define KINETRI_CORE_DEVICE_SCRATCH_POOL_INL_

#include <thrust/execution_policy.h>
#include <thrust/memory.h>

#include <bit>
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <mutex>
#include <new>
#include <utility>
#include <vector>

namespace kinetri::core::device {
namespace KINETRI_DEVICE_NS {
namespace {

namespace pthr = THRUST_NS_QUALIFIER;

class ScratchPool {
 public:
  // Thrust's allocator interface (see Policy()).
  using value_type = char;

  ScratchPool() = default;
  ScratchPool(const ScratchPool&) = delete;
  ScratchPool& operator=(const ScratchPool&) = delete;
  ~ScratchPool() {
    try {
      Trim(0);
    } catch (...) {  // a device already in error: nothing more to free
    }
  }

  char* allocate(std::ptrdiff_t n) {
    const int c = ClassOf(static_cast<size_t>(n));
    if (c >= kClasses) throw std::bad_alloc();
    {
      std::lock_guard<std::mutex> lock(mu_);
      if (!free_[c].empty()) {
        char* p = free_[c].back();
        free_[c].pop_back();
        cached_bytes_ -= size_t{1} << c;
        return p;
      }
    }
    char* p = Raw(size_t{1} << c);
    if (p == nullptr) {  // give the cached blocks back, then try once more
      Trim(0);
      p = Raw(size_t{1} << c);
      if (p == nullptr) throw std::bad_alloc();
    }
    std::lock_guard<std::mutex> lock(mu_);
    held_bytes_ += size_t{1} << c;
    return p;
  }

  void deallocate(char* p, size_t n) {
    const int c = ClassOf(n);
    std::lock_guard<std::mutex> lock(mu_);
    free_[c].push_back(p);
    cached_bytes_ += size_t{1} << c;
  }

  // Frees cached blocks, largest first, until at most `keep` bytes stay
  // cached.
  void Trim(size_t keep) {
    std::lock_guard<std::mutex> lock(mu_);
    for (int c = kClasses - 1; c >= 0 && cached_bytes_ > keep; --c) {
      while (!free_[c].empty() && cached_bytes_ > keep) {
        pthr::free(pthr::device, pthr::device_pointer_cast(free_[c].back()));
        free_[c].pop_back();
        cached_bytes_ -= size_t{1} << c;
        held_bytes_ -= size_t{1} << c;
      }
    }
  }

  // Device bytes the pool holds (in use and cached).
  size_t bytes() const {
    std::lock_guard<std::mutex> lock(mu_);
    return held_bytes_;
  }

 private:
  static constexpr int kClasses = 64;
  static constexpr int kMinClass = 8;  // 256 bytes

  static int ClassOf(size_t n) {
    const int c = n <= 1 ? 0 : std::bit_width(n - 1);
    return c < kMinClass ? kMinClass : c;
  }

  static char* Raw(size_t bytes) {
    try {
      return pthr::malloc<char>(pthr::device, bytes).get();
    } catch (const std::exception&) {
      return nullptr;
    }
  }

  mutable std::mutex mu_;
  std::vector<char*> free_[kClasses];
  size_t held_bytes_ = 0;
  size_t cached_bytes_ = 0;
};

// The stream a caller's device work is queued on: on a GPU, each executor
// (each session) has its own (core/device/round_executor.inl), and the
// queries use the default one (Stream{}); on CPU threads a call is done
// when it returns and the stream is a placeholder.
#if THRUST_DEVICE_SYSTEM == THRUST_DEVICE_SYSTEM_CUDA
using Stream = cudaStream_t;
#else
using Stream = int;
#endif

// The execution policy of every Thrust call of the executor: the device
// system, with temporary storage from `pool`, on `stream`.
#if THRUST_DEVICE_SYSTEM == THRUST_DEVICE_SYSTEM_CUDA
using PoolPolicy = decltype(pthr::cuda::par(std::declval<ScratchPool&>())
                                .on(std::declval<Stream>()));
inline PoolPolicy Policy(ScratchPool& pool, Stream stream) {
  return pthr::cuda::par(pool).on(stream);
}
#else
using PoolPolicy = decltype(pthr::device(std::declval<ScratchPool&>()));
inline PoolPolicy Policy(ScratchPool& pool, Stream) {
  return pthr::device(pool);
}
#endif

// The same for calls whose results the host does not read: on the CUDA
// system they return without waiting for the device (Thrust's par_nosync;
// calls on one stream run in order, and a call that returns a value still
// waits for it); the TBB system always runs a call to its end. Drain()
// waits for everything queued on the stream so far.
#if THRUST_DEVICE_SYSTEM == THRUST_DEVICE_SYSTEM_CUDA
using NoWaitPolicy =
    decltype(pthr::cuda::par_nosync(std::declval<ScratchPool&>())
                 .on(std::declval<Stream>()));
inline NoWaitPolicy PolicyNoWait(ScratchPool& pool, Stream stream) {
  return pthr::cuda::par_nosync(pool).on(stream);
}
inline void Drain(Stream stream) {
  pthr::cuda_cub::throw_on_error(cudaStreamSynchronize(stream),
                                 "device executor: waiting for the device");
}
#else
using NoWaitPolicy = PoolPolicy;
inline NoWaitPolicy PolicyNoWait(ScratchPool& pool, Stream stream) {
  return Policy(pool, stream);
}
inline void Drain(Stream) {}
#endif

// The current GPU of this thread (0 on CPU threads), and making it current
// on another thread (the async forms' threads start on GPU 0).
inline int CurrentDevice() {
#if THRUST_DEVICE_SYSTEM == THRUST_DEVICE_SYSTEM_CUDA
  int device = 0;
  if (cudaGetDevice(&device) != cudaSuccess) return 0;
  return device;
#else
  return 0;
#endif
}
inline void UseDevice(int device) {
#if THRUST_DEVICE_SYSTEM == THRUST_DEVICE_SYSTEM_CUDA
  pthr::cuda_cub::throw_on_error(cudaSetDevice(device),
                                 "device executor: selecting its GPU");
#else
  (void)device;
#endif
}

// Orders device work after what a caller queued on its own stream (the
// _async forms' DeviceStream): a CallerMark is recorded on the caller's
// stream when the call is made, on the calling thread; Follow() makes
// `stream` wait for it, when the call's work begins. Null handle: nothing
// to wait for. On CPU threads the caller's work is done when its call
// returns: nothing to record.
class CallerMark {
 public:
  explicit CallerMark(void* caller_stream) {
#if THRUST_DEVICE_SYSTEM == THRUST_DEVICE_SYSTEM_CUDA
    if (caller_stream == nullptr) return;
    pthr::cuda_cub::throw_on_error(
        cudaEventCreateWithFlags(&event_, cudaEventDisableTiming),
        "device executor: the caller's stream");
    pthr::cuda_cub::throw_on_error(
        cudaEventRecord(event_, static_cast<cudaStream_t>(caller_stream)),
        "device executor: the caller's stream");
#else
    (void)caller_stream;
#endif
  }
  CallerMark(CallerMark&& o) noexcept {
#if THRUST_DEVICE_SYSTEM == THRUST_DEVICE_SYSTEM_CUDA
    event_ = o.event_;
    o.event_ = nullptr;
#else
    (void)o;
#endif
  }
  CallerMark(const CallerMark&) = delete;
  CallerMark& operator=(const CallerMark&) = delete;
  ~CallerMark() {
#if THRUST_DEVICE_SYSTEM == THRUST_DEVICE_SYSTEM_CUDA
    if (event_ != nullptr) cudaEventDestroy(event_);
#endif
  }
  void Follow(Stream stream) const {
#if THRUST_DEVICE_SYSTEM == THRUST_DEVICE_SYSTEM_CUDA
    if (event_ == nullptr) return;
    pthr::cuda_cub::throw_on_error(cudaStreamWaitEvent(stream, event_, 0),
                                   "device executor: the caller's stream");
#else
    (void)stream;
#endif
  }

 private:
#if THRUST_DEVICE_SYSTEM == THRUST_DEVICE_SYSTEM_CUDA
  cudaEvent_t event_ = nullptr;
#endif
};

}  // namespace
}  // namespace KINETRI_DEVICE_NS
}  // namespace kinetri::core::device

#endif  // KINETRI_CORE_DEVICE_SCRATCH_POOL_INL_
