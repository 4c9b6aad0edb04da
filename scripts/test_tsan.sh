#!/usr/bin/env bash
# ThreadSanitizer run of the concurrency tests: the server (sessions,
# snapshots, query pool, memory budget, watchdog, durability threads) under
# load, and the core's parallel loops (1 vs N threads, cancellation).
#
# TSan sees only synchronisation that is compiled with it. Debian's Abseil
# (absl::Mutex, which our locks and gRPC's gpr_mu use) and oneTBB (the task
# hand-off of every parallel loop) are not, so this script first builds the
# same Debian source packages with -fsanitize=thread (`apt-get source`, the
# Debian patches applied; about a minute on 2 cores) into
# $BUILD_DIR/deps, and the tests run with those libraries first on
# LD_LIBRARY_PATH. gRPC itself stays uninstrumented: its own accesses are
# not recorded, and its locks go through the instrumented Abseil.
#
# Any report fails the run (reports also land in $BUILD_DIR/reports).
# Usage: scripts/test_tsan.sh [extra ctest args]
set -euo pipefail
cd "$(dirname "$0")/.."
BUILD_DIR=${BUILD_DIR:-build-tsan}
ROOT=$PWD
DEPS="$ROOT/$BUILD_DIR/deps"
SRC="$ROOT/$BUILD_DIR/src"
FLAGS="-fsanitize=thread -fno-omit-frame-pointer"
# Line tables only (-g1): reports keep file:line, and compiling and linking
# take less time than with full debug info (CI runs close to its limit).
OPT="-O2 -g1 -DNDEBUG"
SUDO=""
if [[ $(id -u) -ne 0 ]]; then SUDO=sudo; fi

# Source packages: the deb-src twin of the machine's Debian sources.
if ! apt-get source --print-uris abseil >/dev/null 2>&1; then
  echo "[tsan] enabling Debian source packages (deb-src)"
  for f in /etc/apt/sources.list.d/debian.sources /etc/apt/sources.list; do
    [[ -f $f ]] || continue
    if [[ $f == *.sources ]]; then
      sed 's/^Types: deb$/Types: deb-src/' "$f" |
        $SUDO tee /etc/apt/sources.list.d/kinetri-deb-src.sources >/dev/null
    else
      sed -n 's/^deb /deb-src /p' "$f" |
        $SUDO tee /etc/apt/sources.list.d/kinetri-deb-src.list >/dev/null
    fi
    break
  done
  $SUDO apt-get update -qq
fi

# package name in Debian, cmake arguments
build_dep() {
  local pkg=$1
  shift
  if [[ -f "$DEPS/.$pkg.done" ]]; then return; fi
  local work="$SRC/$pkg"
  rm -rf "$work" && mkdir -p "$work" "$DEPS"
  (cd "$work" && apt-get source -qq "$pkg" >/dev/null 2>&1)
  local dir
  dir=$(find "$work" -mindepth 1 -maxdepth 1 -type d | head -1)
  echo "[tsan] building $(basename "$dir") with -fsanitize=thread"
  cmake -S "$dir" -B "$work/build" -G Ninja \
    -DCMAKE_BUILD_TYPE=RelWithDebInfo -DCMAKE_INSTALL_PREFIX="$DEPS" \
    -DCMAKE_CXX_FLAGS_RELWITHDEBINFO="$OPT" \
    -DCMAKE_C_FLAGS_RELWITHDEBINFO="$OPT" \
    -DCMAKE_INSTALL_LIBDIR=lib "$@" >"$work/build.log"
  cmake --build "$work/build" -j "$(nproc)" --target install \
    >>"$work/build.log"
  touch "$DEPS/.$pkg.done"
}
build_dep abseil -DCMAKE_CXX_STANDARD=17 -DBUILD_SHARED_LIBS=ON \
  -DBUILD_TESTING=OFF -DCMAKE_CXX_FLAGS="$FLAGS" \
  -DCMAKE_SHARED_LINKER_FLAGS="-fsanitize=thread"
build_dep onetbb -DTBB_TEST=OFF -DTBB_EXAMPLES=OFF -DTBB_STRICT=OFF \
  -DTBBMALLOC_BUILD=OFF -DTBB_SANITIZE=thread

# The project: library, server, client and the tests below (no CUDA, no
# benchmarks), compiled against Debian's headers of the same versions.
TESTS=(memory_budget_test query_pool_test queries_test kinetic_test
  strip_builder_test join_leave_test request_fuzz_test server_hardening_test
  server_e2e_test server_soak_test server_durability_test)
# The device executor's queries on its emulated backend (the stop word a
# watcher thread raises while the kernels run), where the CCCL headers are.
if [[ -d /usr/local/cuda/include/cccl || -d /usr/include/thrust ]]; then
  TESTS+=(queries_device_test)
fi
cmake -S . -B "$BUILD_DIR" -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo \
  -DCMAKE_CXX_FLAGS_RELWITHDEBINFO="$OPT" -DCMAKE_C_FLAGS_RELWITHDEBINFO="$OPT" \
  -DKINETRI_BUILD_BENCH=OFF -DKINETRI_CUDA=OFF \
  -DCMAKE_CXX_FLAGS="$FLAGS" -DCMAKE_EXE_LINKER_FLAGS="$FLAGS" \
  -DCMAKE_SHARED_LINKER_FLAGS="$FLAGS"
cmake --build "$BUILD_DIR" -j "$(nproc)" --target kinetri-server "${TESTS[@]}"

REPORTS="$ROOT/$BUILD_DIR/reports"
rm -rf "$REPORTS" && mkdir -p "$REPORTS"
export LD_LIBRARY_PATH="$DEPS/lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
export TSAN_OPTIONS="log_path=$REPORTS/tsan second_deadlock_stack=1 history_size=4 suppressions=$ROOT/scripts/tsan.supp"
export KINETRI_SOAK_SECONDS=${KINETRI_SOAK_SECONDS:-15}
export KINETRI_FUZZ_SECONDS=${KINETRI_FUZZ_SECONDS:-10}
# The tests of the targets above: the thread-count, cancellation and
# concurrency suites of the core (the strip build among them), and every
# server test but those that assert latencies, orderings in time or the
# server's RSS (TSan slows the server 5-15x and adds shadow memory; they
# run in the normal build and under ASan; abandoned and cancelled calls
# still run here in the soak and fuzz tests), nor the admission of a
# session on the emulated device (a budget test; the device's steps are
# not among the concurrency tests here). Found by a CI run: a 2.5M-point upload that must finish
# well inside its deadline took 1449 of 1500 ms under TSan.
status=0
ctest --test-dir "$BUILD_DIR" --output-on-failure -j "$(nproc)" \
  -R "MemoryBudget|QueryPool|Queries\.(ThreadCount|Cancellation|Admit|Blocks)|Kinetic\.(Cancelled|StopAnywhere|ResultIndependentOfThreadCount|HeldVerticesCollide|RebuildInStrips)|StripBuilder|JoinLeave|RequestFuzz|Hardening|E2e|Soak|Durability" \
  -E "ConvexCurveIsNotQuadratic|DeleteReturnsMemory|DeviceSessionsAreAdmitted|QueryAnswersAreAdmitted|StepWithoutRoomForACopy|StepsAreNotStarved|SigtermDuringALongQuery|DeadlineStops|QueriesSeeOneStepWhileStepsApply" \
  "$@" || status=$?
if compgen -G "$REPORTS/tsan*" >/dev/null; then
  echo "[tsan] ThreadSanitizer reports:"
  cat "$REPORTS"/tsan*
  exit 1
fi
exit $status
