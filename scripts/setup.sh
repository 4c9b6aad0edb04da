#!/usr/bin/env bash
# Installs the Debian packages Kinetri needs (idempotent: only missing ones).
set -euo pipefail

PACKAGES=(
  build-essential cmake ninja-build pkg-config
  libcgal-dev libgmp-dev libmpfr-dev libboost-dev
  libabsl-dev libtbb-dev libnanoflann-dev
  libgtest-dev libgmock-dev libbenchmark-dev
  libgrpc++-dev protobuf-compiler-grpc libprotobuf-dev protobuf-compiler
  grpc-proto
  prometheus-cpp-dev
  python3 python3-grpcio python3-protobuf python3-numpy python3-yaml
  python3-venv python3-pip python3-setuptools python3-wheel python3-build
  libssl-dev openssl
  redis-server gnuplot-nox
  haproxy  # tests/e2e/server_replicas_test.cc: deploy/proxy/haproxy.cfg
  clang-14 libclang-rt-14-dev  # scripts/fuzz.sh: libFuzzer
)
# Node.js (for client/node) comes with the machine image; it is not a Debian
# package here, so it is checked, not installed.

missing=()
for p in "${PACKAGES[@]}"; do
  if ! dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "ok installed"; then
    missing+=("$p")
  fi
done

if ((${#missing[@]})); then
  echo "[setup] installing: ${missing[*]}"
  SUDO=""
  if [[ $(id -u) -ne 0 ]]; then SUDO=sudo; fi
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${missing[@]}"
else
  echo "[setup] all Debian packages present"
fi
if ! command -v node >/dev/null 2>&1; then
  echo "[setup] note: node not found; the Node.js client tests will be skipped"
fi
