// kinetri-device-probe: what one device algorithm costs on this GPU, and
// what changes it. The device executor runs about 25 Thrust algorithms per
// round on small worklists, so its speed on small meshes is this cost times
// the number of algorithms (KINETRI_DEVICE_PROFILE=1 prints that number).
// On the project's H200 (docs/DEVICE.md) a round cost milliseconds per
// algorithm where a plain launch and synchronization cost 11 us; this
// program times each suspect alone: Thrust algorithms with and without a
// caching allocator, a kernel whose functor holds a large local array (as
// the exact predicates do), before and after raising the stack limit (as
// core/device/cuda_backend.cu did, to 96 KiB, before it left the limit to
// the driver).
//
// Usage: kinetri-device-probe [--stack=BYTES] [--reps=N]
#include <cuda_runtime.h>
#include <thrust/copy.h>
#include <thrust/device_vector.h>
#include <thrust/execution_policy.h>
#include <thrust/for_each.h>
#include <thrust/iterator/counting_iterator.h>
#include <thrust/memory.h>
#include <thrust/sort.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <functional>
#include <map>
#include <string>
#include <vector>

namespace {

using Clock = std::chrono::steady_clock;

// Median microseconds of `reps` runs of fn (after one warm-up run, whose
// time is reported separately as the first call).
struct Timing {
  double first_us;
  double median_us;
};
Timing Time(int reps, const std::function<void()>& fn) {
  auto t0 = Clock::now();
  fn();
  const double first =
      std::chrono::duration<double, std::micro>(Clock::now() - t0).count();
  std::vector<double> us;
  for (int i = 0; i < reps; ++i) {
    t0 = Clock::now();
    fn();
    us.push_back(
        std::chrono::duration<double, std::micro>(Clock::now() - t0).count());
  }
  std::sort(us.begin(), us.end());
  return {first, us[us.size() / 2]};
}

// A caching allocator for Thrust's temporaries (the executor's ScratchPool
// in miniature).
struct Cache {
  using value_type = char;
  std::multimap<size_t, char*> free_blocks;
  std::map<char*, size_t> used;
  char* allocate(std::ptrdiff_t n) {
    auto it = free_blocks.lower_bound(static_cast<size_t>(n));
    char* p;
    size_t size;
    if (it != free_blocks.end()) {
      p = it->second;
      size = it->first;
      free_blocks.erase(it);
    } else {
      size = static_cast<size_t>(n);
      p = thrust::malloc<char>(thrust::device, size).get();
    }
    used[p] = size;
    return p;
  }
  void deallocate(char* p, size_t) {
    auto it = used.find(p);
    free_blocks.emplace(it->second, p);
    used.erase(it);
  }
};

struct Small {
  unsigned* out;
  __host__ __device__ void operator()(unsigned i) const { out[i] = i * 7u; }
};
struct Odd {
  __host__ __device__ bool operator()(unsigned v) const { return v & 1u; }
};

// A functor with a large local array on a branch that never runs (as the
// exact predicates' expansions are): the kernel's stack frame is large even
// though no thread touches it.
struct BigFrame {
  unsigned* out;
  double scale;
  __host__ __device__ void operator()(unsigned i) const {
    if (scale > 1e300) {  // never true here
      volatile double buf[6000];
      for (int k = 0; k < 6000; ++k) buf[k] = scale * k + i;
      out[i] = static_cast<unsigned>(buf[i % 6000]);
      return;
    }
    out[i] = i;
  }
};

void Check(cudaError_t e, const char* what) {
  if (e != cudaSuccess) {
    std::fprintf(stderr, "%s: %s\n", what, cudaGetErrorString(e));
    std::exit(1);
  }
}

}  // namespace

int main(int argc, char** argv) {
  size_t stack = 96 * 1024;
  int reps = 200;
  for (int i = 1; i < argc; ++i) {
    if (std::strncmp(argv[i], "--stack=", 8) == 0) {
      stack = std::strtoull(argv[i] + 8, nullptr, 10);
    } else if (std::strncmp(argv[i], "--reps=", 7) == 0) {
      reps = std::atoi(argv[i] + 7);
    } else {
      std::printf(
          "kinetri-device-probe [--stack=BYTES] [--reps=N]\n"
          "Times single Thrust algorithms on 1000 elements on this GPU, "
          "with and without a caching allocator, and a kernel with a large "
          "stack frame before and after raising the stack limit to BYTES "
          "(default 98304; 0: leave it).\n");
      return std::strcmp(argv[i], "--help") == 0 ? 0 : 2;
    }
  }
  int count = 0;
  if (cudaGetDeviceCount(&count) != cudaSuccess || count == 0) {
    std::printf("kinetri-device-probe: no CUDA device\n");
    return 0;
  }
  cudaDeviceProp prop{};
  Check(cudaGetDeviceProperties(&prop, 0), "cudaGetDeviceProperties");
  const char* loading = std::getenv("CUDA_MODULE_LOADING");
  std::printf("device: %s, %d SMs; CUDA_MODULE_LOADING=%s\n", prop.name,
              prop.multiProcessorCount, loading ? loading : "(default)");

  const unsigned n = 1000;
  thrust::device_vector<unsigned> a(n), b(n);
  Cache cache;
  auto row = [](const char* name, Timing t) {
    std::printf("%-44s first %10.1f us   median %10.1f us\n", name, t.first_us,
                t.median_us);
  };
  auto suite = [&](const char* when) {
    std::printf("-- %s\n", when);
    unsigned* pa = thrust::raw_pointer_cast(a.data());
    row("for_each (small functor)", Time(reps, [&] {
          thrust::for_each(thrust::device,
                           thrust::counting_iterator<unsigned>(0),
                           thrust::counting_iterator<unsigned>(n), Small{pa});
        }));
    row("for_each (large stack frame functor)", Time(reps, [&] {
          thrust::for_each(
              thrust::device, thrust::counting_iterator<unsigned>(0),
              thrust::counting_iterator<unsigned>(n), BigFrame{pa, 1.0});
        }));
    row("copy_if, default temporaries", Time(reps, [&] {
          thrust::copy_if(thrust::device, a.begin(), a.end(), b.begin(), Odd{});
        }));
    row("copy_if, cached temporaries", Time(reps, [&] {
          thrust::copy_if(thrust::device(cache), a.begin(), a.end(), b.begin(),
                          Odd{});
        }));
    row("sort, default temporaries",
        Time(reps, [&] { thrust::sort(thrust::device, a.begin(), a.end()); }));
    row("sort, cached temporaries", Time(reps, [&] {
          thrust::sort(thrust::device(cache), a.begin(), a.end());
        }));
    row("cudaMemcpy 4 bytes device->host", Time(reps, [&] {
          unsigned v;
          Check(cudaMemcpy(&v, pa, 4, cudaMemcpyDeviceToHost), "cudaMemcpy");
        }));
    Check(cudaGetLastError(), "launch");
  };
  size_t limit = 0;
  Check(cudaDeviceGetLimit(&limit, cudaLimitStackSize), "cudaDeviceGetLimit");
  std::printf("stack limit at start: %zu bytes\n", limit);
  suite("default stack limit");
  if (stack != 0) {
    const cudaError_t e = cudaDeviceSetLimit(cudaLimitStackSize, stack);
    Check(cudaDeviceGetLimit(&limit, cudaLimitStackSize), "cudaDeviceGetLimit");
    std::printf("cudaDeviceSetLimit(stack, %zu): %s; limit now %zu bytes\n",
                stack, cudaGetErrorString(e), limit);
    size_t free_b = 0, total_b = 0;
    Check(cudaMemGetInfo(&free_b, &total_b), "cudaMemGetInfo");
    std::printf("device memory free %.1f of %.1f GiB\n", free_b / 1073741824.0,
                total_b / 1073741824.0);
    suite("after raising the stack limit");
  }
  return 0;
}
