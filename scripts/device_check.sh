#!/usr/bin/env bash
# Runs the CUDA build's checks on a machine with a GPU, in one go: the device
# executor's typed suites on the CUDA backend, compute-sanitizer (memcheck,
# racecheck) over a few of them, and kinetri-bench with the device engines.
#
# The build is made elsewhere (a Debian machine with our packages and nvcc):
#   cmake -S . -B build-cuda -G Ninja -DCMAKE_BUILD_TYPE=Release \
#     -DCMAKE_CUDA_ARCHITECTURES=90 -DCMAKE_CUDA_FLAGS=-lineinfo \
#     -DKINETRI_CUDA=ON -DKINETRI_BUILD_SERVICE=OFF
#   ninja -C build-cuda device_predicates_cuda_test kinetic_cuda_test \
#     randomized_cuda_test queries_cuda_test join_leave_cuda_test \
#     device_executor_cuda_test \
#     kinetri-bench kinetri-device-probe
#   scripts/device_check.sh --collect-libs build-cuda
# --collect-libs copies the shared libraries the binaries need beyond the C
# library into build-cuda/devlibs, so the folder runs on a machine without
# our Debian packages. Then, on the GPU machine:
#   scripts/device_check.sh build-cuda OUT_DIR [BENCH_SIZES]
# Every stage has its own time limit (seconds: TEST_S for the suites, BENCH_S
# for each benchmark size, SAN_S for each sanitizer run); STAGES picks the
# stages (default "0 1 2 3"; 4 is Nsight Compute over the query kernels),
# SUITES the typed suites of stage 1, BENCH_STEPS the benchmark's steps (3),
# BENCH_ENGINES and BENCH_WORKLOADS its engines and workloads, BENCH_ARGS
# more of its flags (e.g. --device_loop_capacity=0: the host drives every
# legalizing round, to compare with the device loops); the logs and
# gtest XML go to OUT_DIR and a short table is printed last.
set -uo pipefail

if [[ ${1:-} == --collect-libs ]]; then
  B=${2:?build folder}
  mkdir -p "$B/devlibs"
  for bin in "$B"/tests/*_cuda_test "$B"/bench/kinetri-bench \
    "$B"/bench/kinetri-device-probe; do
    ldd "$bin" | awk '/=> \// {print $3}'
  done | sort -u | while read -r lib; do
    case $(basename "$lib") in
      libc.so*|libm.so*|libpthread.so*|libdl.so*|librt.so*|ld-linux*|\
      libcuda.so*) ;;
      *) cp -L "$lib" "$B/devlibs/" ;;
    esac
  done
  du -sh "$B/devlibs"
  exit 0
fi

B=${1:?build folder}
OUT_DIR=${2:?output folder}
SIZES=${3:-100000,1000000}
TEST_S=${TEST_S:-150}
BENCH_S=${BENCH_S:-180}
SAN_S=${SAN_S:-60}
# STAGES picks which of the stages below run (0: what one call costs;
# 1: the typed suites; 2: the benchmark; 3: compute-sanitizer; 4: the
# query kernels under Nsight Compute).
STAGES=${STAGES:-0 1 2 3}
want() { [[ " $STAGES " == *" $1 "* ]]; }
# Logs are written to $O and packed into OUT_DIR/logs.tgz after every stage
# (so a machine that returns only a few files still returns them all).
mkdir -p "$OUT_DIR"
O=$(mktemp -d)
pack() { tar czf "$OUT_DIR/logs.tgz" -C "$O" .; }
if [[ -d $B/devlibs ]]; then
  export LD_LIBRARY_PATH="$(cd "$B/devlibs" && pwd):${LD_LIBRARY_PATH:-}"
fi
summary=()
note() {
  summary+=("$*")
  echo "== $*"
  pack
}

nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.sm,clocks.mem \
  --format=csv | tee "$O/gpu.txt"
# Who else is on this GPU (processes of other tenants time-slice with ours).
nvidia-smi --query-compute-apps=pid,process_name,used_memory --format=csv \
  >> "$O/gpu.txt" 2>&1
nvidia-smi -q -d COMPUTE >> "$O/gpu.txt" 2>&1
# What each runtime call costs on this machine (CuPy, where installed).
timeout 30 python3 "$(dirname "$0")/device_probe.py" | tee "$O/probe.txt"

if want 0; then
# 0. Are the exact predicates right in device code (docs/DEVICE.md: NVVM
#    -O3 got them wrong; the fallbacks are compiled at -O1 since), and do
#    three small query tests pass? Then what one device algorithm costs:
#    the probe alone, three small kinetic tests with the executor's profile
#    by call site, and the kernels' own times under Nsight Compute.
qsmall='Queries.TinySets:Queries.LatticeWithManyTies:Queries.Collinear'
timeout 60 "$B/tests/device_predicates_cuda_test" > "$O/predicates.log" 2>&1
note "device_predicates_cuda_test rc=$?"
grep -E 'OK \]|FAILED \]|disagree|stack limit|what\(\)' "$O/predicates.log" | head -20
timeout 30 "$B/tests/queries_cuda_test" --gtest_filter="$qsmall" \
  > "$O/queries_small.log" 2>&1
note "small query tests rc=$?"
grep -E 'OK \]|FAILED \]|what\(\)' "$O/queries_small.log"
if [[ -x $B/bench/kinetri-device-probe ]]; then
  timeout 60 "$B/bench/kinetri-device-probe" > "$O/call_probe.txt" 2>&1
  note "kinetri-device-probe rc=$?"
  cat "$O/call_probe.txt"
fi
small='Kinetic.ShearFlow:Kinetic.ClusteringAggregationAndDispersal'
small+=':Kinetic.HullExpandsAndContracts'
KINETRI_DEVICE_PROFILE=2 timeout 60 "$B/tests/kinetic_cuda_test" \
  --gtest_filter="$small" > "$O/profile.log" 2>&1
note "kinetic profile rc=$?"
grep -E 'OK \]|FAILED|profile\] (cuda|emulated|queries|stack|time by)|\.inl:' \
  "$O/profile.log" | head -60
# How long the kernels themselves run: 60 launches of one small test,
# after its first 300 (Nsight Compute, clocks left as they are).
if command -v ncu > /dev/null; then
  timeout 90 ncu --clock-control none --launch-skip 300 --launch-count 60 \
    --metrics gpu__time_duration.sum --csv "$B/tests/kinetic_cuda_test" \
    --gtest_filter=Kinetic.ShearFlow > "$O/ncu.csv" 2>&1
  note "ncu ShearFlow rc=$?"
  grep gpu__time_duration "$O/ncu.csv" | awk -F'","' \
    '{n=$5; sub(/\(.*/, "", n); print substr(n, 1, 60), $NF}' | head -60
fi
fi

if want 1; then
# 1. The typed suites on the CUDA backend, one after the other (processes
#    sharing a GPU are time-sliced, which would blur the timings), each
#    with the executor's profile at its end and the caller's promises
#    checked, as ctest runs them (core/device/checks.h).
for s in ${SUITES:-device_predicates device_executor kinetic queries join_leave randomized}; do
  KINETRI_DEVICE_CHECK=1 KINETRI_DEVICE_PROFILE=2 timeout "$TEST_S" "$B/tests/${s}_cuda_test" \
    --gtest_output="xml:$O/${s}.xml" > "$O/${s}.log" 2>&1
  rc=$?
  passed=$(grep -c '^\[       OK \]' "$O/${s}.log")
  failed=$(grep -c '^\[  FAILED  \]' "$O/${s}.log")
  skipped=$(grep -c '^\[  SKIPPED \]' "$O/${s}.log")
  took=$(grep -o 'tests\? from [0-9]* test suites\? ran. ([0-9]* ms total)' \
    "$O/${s}.log" | grep -o '([0-9]* ms')
  note "${s}_cuda_test rc=$rc ok=$passed failed_lines=$failed" \
    "skipped=$skipped ${took:-}"
  grep -E '^\[  FAILED  \]|Failure|error' "$O/${s}.log" | head -20
done
fi

if want 2; then
# 2. kinetri-bench at N points with the device engines beside the host ones
#    (cross-checked between engines inside the benchmark).
for n in ${SIZES//,/ }; do
  KINETRI_DEVICE_PROFILE=2 timeout "$BENCH_S" stdbuf -oL \
    "$B/bench/kinetri-bench" --sizes="$n" \
    --steps="${BENCH_STEPS:-3}" --workloads="${BENCH_WORKLOADS:-brownian,paper}" \
    --engines="${BENCH_ENGINES:-kinetri,kinetri-device,grid,grid-device}" \
    --query_points=100000 ${BENCH_ARGS:-} --json="$O/bench-$n.json" \
    > "$O/bench-$n.log" 2>&1
  note "kinetri-bench n=$n rc=$?"
  grep -E 'kinetri-device|grid-device|\] ' "$O/bench-$n.log" | tail -40
done
fi

# 3. compute-sanitizer over small tests (it slows kernels many times).
if ! want 3; then
  :
elif command -v compute-sanitizer > /dev/null; then
  kfilter='Kinetic.ShearFlow:Kinetic.DuplicatesMergeAndSeparate'
  kfilter+=':Kinetic.CollinearBecomesPlanarAndBack:Kinetic.HeldVerticesCollide'
  qfilter='Queries.TinySets:Queries.Duplicates:Queries.Collinear'
  qfilter+=':Queries.LatticeWithManyTies'
  timeout "$SAN_S" compute-sanitizer --tool memcheck --print-limit 20 \
    "$B/tests/kinetic_cuda_test" --gtest_filter="$kfilter" \
    > "$O/memcheck.log" 2>&1
  note "memcheck kinetic rc=$? $(grep -E 'ERROR SUMMARY' "$O/memcheck.log" | tail -1)"
  timeout "$SAN_S" compute-sanitizer --tool memcheck --print-limit 20 \
    "$B/tests/queries_cuda_test" --gtest_filter="$qfilter" \
    > "$O/memcheck_queries.log" 2>&1
  note "memcheck queries rc=$? $(grep -E 'ERROR SUMMARY' "$O/memcheck_queries.log" | tail -1)"
  timeout "$SAN_S" compute-sanitizer --tool racecheck --print-limit 20 \
    "$B/tests/kinetic_cuda_test" --gtest_filter="$kfilter" \
    > "$O/racecheck.log" 2>&1
  note "racecheck kinetic rc=$? $(grep -E 'ERROR SUMMARY|RACECHECK SUMMARY' "$O/racecheck.log" | tail -1)"
else
  note "compute-sanitizer: not on PATH"
fi

# 4. The query kernels of one 100K-point benchmark step under Nsight
#    Compute: duration, occupancy, registers and local memory per thread.
if want 4 && command -v ncu > /dev/null; then
  timeout "${NCU_S:-90}" ncu --clock-control none --kernel-name-base demangled \
    --kernel-name regex:'KnnRows|RadiusCounts|RadiusFill|PreparePositions' \
    --launch-count "${NCU_LAUNCHES:-8}" --section SpeedOfLight \
    --section LaunchStats --section Occupancy --section WarpStateStats \
    "$B/bench/kinetri-bench" --sizes=100000 --steps=1 \
    --workloads=brownian --engines=kinetri-device --query_points=100000 \
    > "$O/ncu_queries.txt" 2>&1
  note "ncu query kernels rc=$?"
  grep -E '^  [A-Za-z].*\(|Duration|Registers Per|Local Memory|Achieved Occ|Theoretical Occ|Block Size|Grid Size|Stall|Memory Throughput|Compute \(SM\) Th' \
    "$O/ncu_queries.txt" | head -80
fi

echo
printf '%s\n' "${summary[@]}" | tee "$OUT_DIR/summary.txt"
pack
