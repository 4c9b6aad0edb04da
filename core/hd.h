// Host/device annotation so per-element steps compile for CPU and CUDA.
#ifndef KINETRI_CORE_HD_H_
#define KINETRI_CORE_HD_H_

#if defined(__CUDACC__)
#define KINETRI_HD __host__ __device__
#else
#define KINETRI_HD
#endif

#endif  // KINETRI_CORE_HD_H_
