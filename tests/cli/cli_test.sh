#!/bin/bash
# kinetri-cli and kinetri-sim against a real server: argument errors say what
# is wrong (exit 2), local file errors are not reported as gRPC codes, query
# columns match the usage text, stats are readable, export writes standard
# formats to a file or stdout.
# Arguments: kinetri-server kinetri-cli kinetri-sim
set -u
server_bin=$1 cli=$2 sim=$3
tmp=$(mktemp -d)
trap 'kill $server_pid 2>/dev/null; wait $server_pid 2>/dev/null; rm -rf "$tmp"' EXIT
"$server_bin" --listen=127.0.0.1:0 --metrics_listen= >"$tmp/server.log" 2>&1 &
server_pid=$!
for _ in $(seq 100); do
  port=$(sed -n 's/.*listening on port \([0-9]*\).*/\1/p' "$tmp/server.log")
  [ -n "$port" ] && break
  sleep 0.1
done
[ -n "$port" ] || { echo "server did not start"; cat "$tmp/server.log"; exit 1; }
S="--server=127.0.0.1:$port"
fail=0
# expect <exit status> <text in stderr or stdout> -- command...
expect() {
  local want=$1 text=$2
  shift 3
  out=$("$@" 2>&1)
  rc=$?
  if [ "$rc" != "$want" ] || ! grep -qF -- "$text" <<<"$out"; then
    echo "FAIL: $* -> exit $rc (want $want), output:"; echo "$out" | head -5
    fail=1
  else
    echo "ok: $* -> $rc"
  fi
}
expect 2 "no command given" -- "$cli" $S
expect 2 "unknown command 'frobnicate'" -- "$cli" $S frobnicate
expect 2 "give the points" -- "$cli" $S create
expect 2 "exclude each other" -- "$cli" $S create --random=10 --csv=x.csv
expect 1 "nope.csv: cannot open" -- "$cli" $S create --csv="$tmp/nope.csv"
if "$cli" $S create --csv="$tmp/nope.csv" 2>&1 | grep -q NOT_FOUND; then
  echo "FAIL: a local file error printed as a gRPC code"; fail=1
fi
expect 0 "sessions/t points=50" -- "$cli" $S create --random=50 --id=t
expect 2 "--session=sessions/ID is required" -- "$cli" $S get
expect 2 "--steps=0 must be >= 1" -- "$cli" $S move --session=sessions/t --steps=0
expect 2 "--steps=-3 must be >= 1" -- "$cli" $S move --session=sessions/t --steps=-3
expect 2 "--sigma must be a positive number" -- "$cli" $S move --session=sessions/t --sigma=-1
expect 0 "step 1:" -- "$cli" $S move --session=sessions/t --sigma=0.001 --steps=2
expect 0 "row,query_id,rank,neighbour,distance" -- "$cli" $S query --session=sessions/t --kind=knn --k=2 --ids=7,3
# The query_id column names the queried point; rank 0 is its nearest.
rows=$("$cli" $S query --session=sessions/t --kind=knn --k=2 --ids=7,3 | tail -n +3)
if [ "$(cut -d, -f2 <<<"$rows" | sort -u | tr '\n' ' ')" != "3 7 " ] ||
   [ "$(wc -l <<<"$rows")" != 4 ]; then
  echo "FAIL: query rows: $rows"; fail=1
fi
expect 2 "--k must be >= 1" -- "$cli" $S query --session=sessions/t --kind=knn --k=0
# Points join and leave (a separate session: the stats below expect step 2).
expect 0 "sessions/j points=50" -- "$cli" $S create --random=50 --id=j
printf 'x,y\n0.25,0.25\n0.5,0.75\n' >"$tmp/add.csv"
expect 0 "2 points joined, 52 points now (ids 50..51)" -- "$cli" $S add --session=sessions/j --csv="$tmp/add.csv"
expect 0 "3 points left, 49 points now" -- "$cli" $S remove --session=sessions/j --ids=0,50,7
expect 1 "NOT_FOUND: remove[0] = 49" -- "$cli" $S remove --session=sessions/j --ids=49
expect 2 "remove: --ids=1,2,3 is required" -- "$cli" $S remove --session=sessions/j
expect 2 "add: --csv=points.csv" -- "$cli" $S add --session=sessions/j
expect 2 "this session numbers points itself" -- "$cli" $S add --session=sessions/j --csv="$tmp/add.csv" --ids=4,5
# The point that joined as id 51 (0.5, 0.75) is now id 48, after 0, 7, 50 left.
last=$("$cli" $S export --session=sessions/j --format=csv | awk -F, '$1 == "point" && $2 == 48')
if [ "$last" != "point,48,0.5,0.75" ]; then
  echo "FAIL: joined point not where expected: '$last'"; fail=1
fi
expect 0 "step: 2" -- "$cli" $S stats --session=sessions/t
expect 0 "created: 20" -- "$cli" $S stats --session=sessions/t
if "$cli" $S stats --session=sessions/t | grep -q "seconds:"; then
  echo "FAIL: stats prints protobuf text"; fail=1
fi
expect 0 "v " -- "$cli" $S export --session=sessions/t --format=obj
nv=$("$cli" $S export --session=sessions/t --format=obj | grep -c "^v ")
[ "$nv" = 50 ] || { echo "FAIL: obj export has $nv vertices"; fail=1; }
expect 0 "wrote 50 points" -- "$cli" $S export --session=sessions/t --format=csv --out="$tmp/m.csv"
grep -q "^triangle," "$tmp/m.csv" || { echo "FAIL: csv export"; fail=1; }
expect 1 "cannot write" -- "$cli" $S export --session=sessions/t --out=/nonexistent/dir/m.txt
expect 1 "NOT_FOUND" -- "$cli" $S get --session=sessions/absent
# The server's --device flag: CUDA sessions need a GPU (none here: the
# machine's tests run without one), unknown values named.
if ! command -v nvidia-smi > /dev/null || ! nvidia-smi -L > /dev/null 2>&1; then
  expect 2 "--device=cuda: this build or machine has no such backend" -- "$server_bin" --listen=127.0.0.1:0 --metrics_listen= --device=cuda
fi
expect 2 "--device must be auto, cuda, emulated or none" -- "$server_bin" --listen=127.0.0.1:0 --metrics_listen= --device=gpu
expect 2 "needs >= 3" -- "$sim" $S --n=0
expect 2 "cannot write" -- "$sim" $S --n=100 --steps=1 --svg=/nonexistent/dir/x.svg
exit $fail
