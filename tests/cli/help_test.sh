#!/bin/bash
# Every binary's --help (and -h style --helpshort) lists its own flags and
# exits 0. Arguments: pairs of "<binary> <a flag it defines>".
set -u
fail=0
while [ $# -ge 2 ]; do
  bin=$1 flag=$2
  shift 2
  for opt in --help --helpshort; do
    out=$("$bin" "$opt" 2>&1)
    rc=$?
    if [ $rc -ne 0 ]; then
      echo "FAIL: $(basename "$bin") $opt exited $rc:"; echo "$out" | head -5
      fail=1
    elif ! grep -q -- "--$flag" <<<"$out"; then
      echo "FAIL: $(basename "$bin") $opt does not list --$flag:"
      echo "$out" | head -5
      fail=1
    elif grep -q "No flags matched" <<<"$out"; then
      echo "FAIL: $(basename "$bin") $opt says 'No flags matched'"; fail=1
    else
      echo "ok: $(basename "$bin") $opt"
    fi
  done
done
exit $fail
