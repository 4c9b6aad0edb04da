#!/usr/bin/env bash
# The Python package as users install it, offline from Debian's packages:
# a wheel built with `python3 -m build --no-isolation` and `pip install` of
# the source directory, each into a fresh venv made with
# --system-site-packages; then, from outside the source tree, the installed
# package (stubs inside, py.typed, sync and asyncio clients) against the
# real server.
#   KINETRI_SERVER=build/server/kinetri-server bash client/python/test_package.sh
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
server=$(realpath "${KINETRI_SERVER:-$here/../../build/server/kinetri-server}")
py=/usr/bin/python3
tmp=$(mktemp -d /tmp/kinetri-pip-XXXXXX)
trap 'rm -rf "$tmp"' EXIT
export KINETRI_PROTO_DIR=$here/../../proto PIP_NO_INDEX=1 \
  PIP_DISABLE_PIP_VERSION_CHECK=1 PYTHONDONTWRITEBYTECODE=1
# Build from copies: the source tree stays clean.
cp -r "$here" "$tmp/src"
rm -rf "$tmp/src/tests" "$tmp/src/build" "$tmp/src"/*.egg-info

"$py" -m build --wheel --no-isolation --outdir "$tmp/dist" "$tmp/src" \
  >"$tmp/build.log" 2>&1 || { cat "$tmp/build.log"; exit 1; }
wheel=$(ls "$tmp"/dist/kinetri_client-*.whl)
"$py" -m zipfile -l "$wheel" | awk '{print $1}' >"$tmp/contents"
for f in kinetri_client/__init__.py kinetri_client/aio.py \
         kinetri_client/py.typed kinetri_client/_pb/kinetri_pb2.py \
         kinetri_client/_pb/kinetri_pb2.pyi \
         kinetri_client/_pb/kinetri_pb2_grpc.py; do
  grep -qx "$f" "$tmp/contents" || { echo "missing from the wheel: $f"; exit 1; }
done

cat >"$tmp/smoke.py" <<'PY'
"""The installed package against a real server (no source tree)."""
import asyncio
import os
import re
import subprocess
import sys

import numpy as np

import kinetri_client
from kinetri_client import Client, KinetriError
from kinetri_client.aio import AsyncClient

assert "site-packages" in kinetri_client.__file__, kinetri_client.__file__
assert os.path.exists(os.path.join(os.path.dirname(kinetri_client.__file__),
                                   "py.typed"))
proc = subprocess.Popen([sys.argv[1], "--listen=127.0.0.1:0",
                         "--metrics_listen="], stdout=subprocess.PIPE,
                        text=True)
try:
    for line in proc.stdout:
        m = re.search(r"listening on port (\d+)", line)
        if m:
            break
    target = f"127.0.0.1:{m.group(1)}"
    rng = np.random.default_rng(1)
    pts = rng.random((400, 2))
    with Client(target, deadline=30) as c:
        s = c.create_session(pts)
        with c.open_steps(s.name) as steps:
            assert steps.move_by(np.full((400, 2), 1e-3)).step == 1
        nn = c.nearest_all(s.name)
        assert len(nn) == 400 and nn.ids.dtype == np.uint32
        step, positions, triangles = c.export(s.name)
        assert step == 1 and np.allclose(positions, pts + 1e-3)

    async def run():
        async with AsyncClient(target, deadline=30) as a:
            got = await a.get_session(s.name)
            assert got.step == 1
            async with await a.open_steps(s.name) as steps:
                assert (await steps.move_by(np.zeros((400, 2)))).step == 2
            knn = await a.knn(s.name, 3, ids=[0, 1])
            assert len(knn) == 2 and len(knn.row(0)) == 3
            async with await a.open_steps(s.name) as steps:  # join, leave
                ack = await steps.change(add=[[2.0, 2.0]], remove=[0])
                assert (ack.step, ack.stats.point_count,
                        ack.stats.first_added_id) == (3, 400, 399), ack
            await a.delete_session(s.name)
            try:
                await a.get_session(s.name)
            except KinetriError as e:
                assert e.code.name == "NOT_FOUND", e
            else:
                raise AssertionError("deleted session still there")
    asyncio.run(run())
    print("pip package: sync and asyncio clients: ok")
finally:
    proc.terminate()
    proc.wait(timeout=30)
PY

for how in wheel source; do
  "$py" -m venv --system-site-packages "$tmp/venv-$how"
  if [[ $how == wheel ]]; then
    "$tmp/venv-$how/bin/pip" install -q "$wheel"
  else
    "$tmp/venv-$how/bin/pip" install -q --no-build-isolation "$tmp/src"
  fi
  (cd "$tmp" && "$tmp/venv-$how/bin/python" smoke.py "$server")
  echo "pip package ($how): ok"
done
