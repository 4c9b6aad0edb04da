#!/usr/bin/env bash
# Runs the exact-predicate checks over several CUDA builds side by side on a
# GPU machine: RUN_DIR holds devlibs/ and one folder per variant with tests/.
#   scripts/device_variants.sh RUN_DIR OUT_DIR VARIANT...
# Per variant and stack limit (the driver's, then 96 KiB): the device
# predicates test, the small query tests, then three motion tests.
set -uo pipefail
R=${1:?run folder}
OUT=${2:?output folder}
shift 2
export LD_LIBRARY_PATH="$(cd "$R/devlibs" && pwd)"
mkdir -p "$OUT"
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader
qsmall='Queries.TinySets:Queries.LatticeWithManyTies:Queries.Collinear'
ksmall='Kinetic.ShearFlow:Kinetic.CollinearBecomesPlanarAndBack'
ksmall+=':Kinetic.DuplicatesMergeAndSeparate'
passing=()
for v in "$@"; do
  T=$R/$v/tests
  for st in 0 98304; do
    tag=$v-$st
    for t in SameSignsAsTheHost SameSignsInAPlainKernel; do
      KINETRI_CUDA_STACK_BYTES=$st timeout 20 "$T/device_predicates_cuda_test" \
        --gtest_filter="*.$t" > "$OUT/pred-$tag-$t.log" 2>&1
      echo "== $tag predicates $t rc=$?"
      grep -E 'FAILED \]|disagree|stack limit|what\(\)|input [0-9]+:' \
        "$OUT/pred-$tag-$t.log" | head -6
    done
    KINETRI_DEVICE_PROFILE=1 KINETRI_CUDA_STACK_BYTES=$st timeout 20 \
      "$T/queries_cuda_test" --gtest_filter="$qsmall" \
      > "$OUT/qsmall-$tag.log" 2>&1
    qrc=$?
    echo "== $tag small queries rc=$qrc ok=$(grep -c 'OK \]' "$OUT/qsmall-$tag.log")"
    [[ $qrc == 0 ]] && passing+=("$v $st")
    grep -E 'FAILED \]|what\(\)|stack limit' "$OUT/qsmall-$tag.log" | head -5
    KINETRI_CUDA_STACK_BYTES=$st timeout 30 "$T/kinetic_cuda_test" \
      --gtest_filter="$ksmall" > "$OUT/ksmall-$tag.log" 2>&1
    echo "== $tag small kinetic rc=$? ok=$(grep -c 'OK \]' "$OUT/ksmall-$tag.log")"
    grep -E 'FAILED \]|what\(\)' "$OUT/ksmall-$tag.log" | head -5
  done
done

# The whole query suite for the first variant whose small query tests passed.
if (( ${#passing[@]} > 0 )); then
  read -r v st <<< "${passing[0]}"
  KINETRI_DEVICE_PROFILE=1 KINETRI_CUDA_STACK_BYTES=$st timeout "${FULL_S:-120}" \
    "$R/$v/tests/queries_cuda_test" > "$OUT/queries-$v-$st.log" 2>&1
  echo "== $v-$st whole query suite rc=$? ok=$(grep -c 'OK \]' "$OUT/queries-$v-$st.log")"
  grep -E 'FAILED \]|what\(\)|tests? from .* ran' "$OUT/queries-$v-$st.log" | head -12
fi
# Where the first variant goes wrong (memcheck, with -lineinfo).
if [[ -n ${MEMCHECK:-} ]] && command -v compute-sanitizer > /dev/null; then
  timeout 60 compute-sanitizer --tool memcheck --print-limit 5 \
    "$R/$1/tests/device_predicates_cuda_test" \
    --gtest_filter='*.SameSignsInAPlainKernel' > "$OUT/memcheck-pred.log" 2>&1
  echo "== memcheck predicates ($1) rc=$?"
  grep -E 'Invalid|at .*\.h:|ERROR SUMMARY|Address' "$OUT/memcheck-pred.log" | head -20
fi
