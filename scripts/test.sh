#!/usr/bin/env bash
# Installs what is missing, builds, and runs the whole test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
# Each phase prints how long it took (CI has a 90-minute limit).
phase() {
  local start=$SECONDS
  "$@"
  echo "[test] $* took $((SECONDS - start)) s (total $SECONDS s)"
}
phase bash scripts/build.sh
phase ctest --test-dir build --output-on-failure -j "$(nproc)"
# The suite again under AddressSanitizer + UndefinedBehaviorSanitizer
# (./build-asan, about 28 minutes on 2 cores), then the concurrency tests
# under ThreadSanitizer (./build-tsan, about 11 minutes), then libFuzzer over
# the service's requests for 60 s (./build-fuzz, clang, about 4 minutes);
# KINETRI_SKIP_SANITIZERS=1 skips all three.
if [[ "${KINETRI_SKIP_SANITIZERS:-0}" != 1 ]]; then
  phase bash scripts/test_sanitizers.sh
  phase bash scripts/test_tsan.sh
  phase bash scripts/fuzz.sh
fi
