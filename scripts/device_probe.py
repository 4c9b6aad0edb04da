#!/usr/bin/env python3
"""Times the CUDA runtime calls the device executor makes per Thrust
algorithm (allocation, free, synchronisation, a small launch) on the GPU
machine, through CuPy where it is installed (scripts/device_check.sh)."""
import statistics
import time

try:
    import cupy
    from cupy.cuda import runtime
except ImportError:  # no CuPy: nothing to time
    print("device_probe: CuPy not installed")
    raise SystemExit(0)


def median_us(fn, reps=200):
    fn()
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times) * 1e6


def malloc_free(nbytes):
    def run():
        p = runtime.malloc(nbytes)
        runtime.free(p)
    return run


x = cupy.zeros(1024, dtype=cupy.uint32)
stream = cupy.cuda.Stream.null
rows = [
    ("cudaMalloc+cudaFree 4 KiB", median_us(malloc_free(4096))),
    ("cudaMalloc+cudaFree 64 MiB", median_us(malloc_free(64 << 20), 50)),
    ("cudaDeviceSynchronize (idle)", median_us(runtime.deviceSynchronize)),
    ("small kernel + sync", median_us(lambda: (x.fill(1), stream.synchronize()))),
    ("4-byte device->host copy", median_us(lambda: int(x[0]))),
]
for name, us in rows:
    print(f"{name:32s} {us:10.1f} us")
