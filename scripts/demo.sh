#!/usr/bin/env bash
# Main job: install what is missing, build, start kinetri-server with its
# embedded defaults, run the kinetri-sim demo client against it (DLA, then a
# Brownian gas), write pictures to out/, and stop the server.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
bash scripts/build.sh
mkdir -p out
# Free ports for gRPC and /metrics: a server already running here (its
# default metrics port is 9464) does not stop the demo.
./build/server/kinetri-server --listen=127.0.0.1:0 \
  --metrics_listen=127.0.0.1:0 >out/server.log 2>&1 &
server_pid=$!
trap 'kill -TERM $server_pid 2>/dev/null; wait $server_pid 2>/dev/null || true' EXIT
port=""
for _ in $(seq 100); do
  port=$(sed -n 's/^kinetri-server: listening on port \([0-9]*\).*/\1/p' out/server.log)
  [[ -n "$port" ]] && break
  sleep 0.1
done
[[ -n "$port" ]] || { cat out/server.log; echo "server did not start" >&2; exit 1; }
metrics=$(sed -n 's/^kinetri-server: metrics on \([^ ]*\) .*/\1/p' out/server.log)
echo "kinetri-server is up on 127.0.0.1:$port, metrics ${metrics:-off} (log: out/server.log)"
./build/client/kinetri-sim --server="127.0.0.1:$port" --mode=dla --n=6000 \
  --steps=400 --sigma=1.0 --svg=out/kinetri-dla.svg
./build/client/kinetri-sim --server="127.0.0.1:$port" --mode=brownian \
  --n="${KINETRI_DEMO_N:-100000}" --steps=20 --sigma=0.1 \
  --svg=out/kinetri-brownian.svg
