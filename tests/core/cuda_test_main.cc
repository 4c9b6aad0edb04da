// main() of the suites built for the device executor's CUDA backend
// (KINETRI_TEST_CUDA): registers the backend and runs the tests where a GPU
// exists. Elsewhere every test reports "[  SKIPPED ]" (ctest then lists it
// as skipped, never as passed); listing the tests works everywhere.
#include <gtest/gtest.h>

#include <cstdio>

#include "core/device/cuda_backend.h"
#include "core/device/device_executor.h"

int main(int argc, char** argv) {
  ::testing::InitGoogleTest(&argc, argv);
  namespace dev = kinetri::core::device;
  dev::RegisterCudaBackend();
  if (!::testing::GTEST_FLAG(list_tests) &&
      !dev::DeviceBackendAvailable(dev::DeviceBackend::kCuda)) {
    std::printf("[  SKIPPED ] %s: no CUDA device present\n",
                ::testing::GTEST_FLAG(filter).c_str());
    return 0;
  }
  return RUN_ALL_TESTS();
}
