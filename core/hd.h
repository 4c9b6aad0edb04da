// Host/device annotation so per-element steps compile for CPU and CUDA.
#ifndef KINETRI_CORE_HD_H_
#define KINETRI_CORE_HD_H_

#if defined(__CUDACC__)
#define KINETRI_HD __host__ __device__
#else
#define KINETRI_HD
#endif

// Rarely taken slow paths (exact predicate fallbacks): kept out of line so
// the fast filters inline into hot loops without their large stack frames.
#if defined(__CUDA_ARCH__)
#define KINETRI_COLD __noinline__
#elif defined(__GNUC__)
#define KINETRI_COLD __attribute__((noinline, cold))
#else
#define KINETRI_COLD
#endif

#endif  // KINETRI_CORE_HD_H_
