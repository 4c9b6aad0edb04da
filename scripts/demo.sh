#!/usr/bin/env bash
# Main job: install what is missing, build, and run the kinetic demo
# (moves points, prints per-step figures, writes out/kinetri.svg).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
bash scripts/build.sh
mkdir -p out
./build/client/kinetri-sim --n="${KINETRI_DEMO_N:-50000}" --steps=10 \
  --svg=out/kinetri.svg "$@"
