#!/usr/bin/env bash
# find_package(Kinetri) after `cmake --install`: installs the build tree
# into a temporary prefix, builds tests/package/consumer against it (only
# the installed files: the source tree is not on its include path) and
# runs it.
#   bash tests/package/find_package_test.sh BUILD_DIR
set -euo pipefail
build=${1:?usage: find_package_test.sh BUILD_DIR}
here=$(cd "$(dirname "$0")" && pwd)
tmp=$(mktemp -d /tmp/kinetri-package-XXXXXX)
trap 'rm -rf "$tmp"' EXIT
cmake --install "$build" --prefix "$tmp/prefix" >/dev/null
test -f "$tmp/prefix/lib/cmake/Kinetri/KinetriConfig.cmake" || test -f "$tmp/prefix/lib/x86_64-linux-gnu/cmake/Kinetri/KinetriConfig.cmake"
test -x "$tmp/prefix/bin/kinetri-server"
cp -r "$here/consumer" "$tmp/consumer"
generator=()
command -v ninja >/dev/null 2>&1 && generator=(-G Ninja)
build() {  # output shown only when a step fails
  "$@" >"$tmp/log" 2>&1 || { cat "$tmp/log"; echo "failed: $*"; exit 1; }
}
build cmake -S "$tmp/consumer" -B "$tmp/build" "${generator[@]}" \
  -DCMAKE_BUILD_TYPE=Release -DCMAKE_PREFIX_PATH="$tmp/prefix"
build cmake --build "$tmp/build"
"$tmp/build/consumer"
