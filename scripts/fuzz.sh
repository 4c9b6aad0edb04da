#!/usr/bin/env bash
# libFuzzer over every RPC's request decoding and the streams' message
# sequences (tests/fuzz/request_fuzzer.cc: the service in-process), built
# with clang into ./build-fuzz under AddressSanitizer and
# UndefinedBehaviorSanitizer. The corpus grows in build-fuzz/corpus (seeded
# with valid calls of every method); a crash is saved in build-fuzz/crashes
# and fails the script (replay: build-fuzz/tests/request_fuzzer FILE).
#
#   bash scripts/fuzz.sh                                  # 60 s (CI)
#   KINETRI_LIBFUZZER_SECONDS=3600 bash scripts/fuzz.sh   # a longer run
set -euo pipefail
cd "$(dirname "$0")/.."
BUILD_DIR=${KINETRI_FUZZ_BUILD_DIR:-build-fuzz}
SECONDS_TO_RUN=${KINETRI_LIBFUZZER_SECONDS:-60}
FLAGS="-fsanitize=fuzzer-no-link,address,undefined -fno-sanitize-recover=undefined -fno-omit-frame-pointer"
# Line tables only (-g1): reports keep file:line, and compiling and linking
# take less time than with full debug info (CI runs close to its limit).
OPT="-O2 -g1 -DNDEBUG"
cmake -S . -B "$BUILD_DIR" -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo \
  -DCMAKE_CXX_FLAGS_RELWITHDEBINFO="$OPT" -DCMAKE_C_FLAGS_RELWITHDEBINFO="$OPT" \
  -DCMAKE_C_COMPILER=clang-14 -DCMAKE_CXX_COMPILER=clang++-14 \
  -DKINETRI_BUILD_BENCH=OFF -DKINETRI_CUDA=OFF -DKINETRI_LIBFUZZER=ON \
  -DCMAKE_CXX_FLAGS="$FLAGS" \
  -DCMAKE_EXE_LINKER_FLAGS="-fsanitize=address,undefined" >/dev/null
cmake --build "$BUILD_DIR" -j "$(nproc)" --target request_fuzzer
FUZZER="$BUILD_DIR/tests/request_fuzzer"
mkdir -p "$BUILD_DIR/corpus" "$BUILD_DIR/crashes"
if [[ -z "$(ls -A "$BUILD_DIR/corpus")" ]]; then
  KINETRI_FUZZ_SEEDS_OUT="$BUILD_DIR/corpus" "$FUZZER"
fi
# The service lives for the whole run (not freed per input): no leak checks.
export ASAN_OPTIONS=detect_leaks=0
export UBSAN_OPTIONS=print_stacktrace=1
echo "[fuzz] libFuzzer for ${SECONDS_TO_RUN} s"
set +e
"$FUZZER" -max_total_time="$SECONDS_TO_RUN" -timeout=30 -rss_limit_mb=4096 \
  -detect_leaks=0 -print_final_stats=1 \
  -artifact_prefix="$BUILD_DIR/crashes/" "$BUILD_DIR/corpus" 2>&1 |
  grep -v "^#[0-9]*[[:space:]]*\(NEW\|REDUCE\|pulse\)"
status=${PIPESTATUS[0]}
set -e
if [[ $status -ne 0 ]] || [[ -n "$(ls -A "$BUILD_DIR/crashes")" ]]; then
  echo "[fuzz] failed (status $status); inputs in $BUILD_DIR/crashes:"
  ls -l "$BUILD_DIR/crashes"
  exit 1
fi
echo "[fuzz] no crash"
