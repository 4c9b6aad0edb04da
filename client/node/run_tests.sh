#!/usr/bin/env bash
# Installs the npm dependencies (from package-lock.json) and runs the tests.
# Exits 77 (skipped) when Node.js is not installed.
set -euo pipefail
cd "$(dirname "$0")"
command -v node >/dev/null 2>&1 || { echo "node not found: skipping"; exit 77; }
if [[ ! -d node_modules/@grpc/grpc-js ]]; then
  npm ci --no-audit --no-fund --loglevel=error
fi
exec node --test test/
