#!/usr/bin/env bash
# The Node package as a user gets it: `npm pack`, installed into a fresh
# project (with TypeScript), then a JavaScript program run against the real
# server and a TypeScript program type-checked by `tsc --strict` against
# index.d.ts. Exits 77 (skipped) when Node.js is not installed.
#   KINETRI_SERVER=build/server/kinetri-server bash client/node/test_package.sh
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
command -v node >/dev/null 2>&1 || { echo "node not found: skipping"; exit 77; }
server=$(realpath "${KINETRI_SERVER:-$here/../../build/server/kinetri-server}")
tmp=$(mktemp -d /tmp/kinetri-npm-XXXXXX)
trap 'rm -rf "$tmp"' EXIT
quiet=(--no-audit --no-fund --loglevel=error)

(cd "$here" && npm pack --pack-destination "$tmp" --loglevel=error >/dev/null)
tarball=$(ls "$tmp"/kinetri-client-*.tgz)
tar -tzf "$tarball" | sort >"$tmp/contents"
for f in package/index.js package/index.d.ts package/README.md \
         package/proto/kinetri/v1/kinetri.proto; do
  grep -qx "$f" "$tmp/contents" || { echo "missing from the package: $f"; exit 1; }
done
test ! -e "$here/proto" || { echo "postpack left client/node/proto"; exit 1; }

mkdir "$tmp/app"
cd "$tmp/app"
npm init -y >/dev/null
npm install "${quiet[@]}" "$tarball" typescript@5 @types/node@20 >/dev/null

cat >smoke.js <<'JS'
// The installed package against a real server (no source tree involved).
'use strict';
const assert = require('node:assert');
const {spawn} = require('node:child_process');
const {Client, status} = require('@kinetri/client');

const proc = spawn(process.argv[2], ['--listen=127.0.0.1:0', '--metrics_listen=']);
proc.stdout.on('data', async (data) => {
  const m = /listening on port (\d+)/.exec(data.toString());
  if (!m) return;
  const client = new Client(`127.0.0.1:${m[1]}`, {deadlineSeconds: 30});
  try {
    const n = 500;
    const xy = new Float64Array(2 * n).map(() => Math.random());
    const s = await client.createSession(xy);
    assert.match(s.name, /^sessions\/s-[0-9a-f]{32}$/);
    const steps = await client.openSteps(s.name);
    const ack = await steps.moveBy(new Float64Array(2 * n).fill(0.001));
    assert.strictEqual(ack.step, 1);
    // Points that leave and join: survivors renumbered, joiners after them.
    const change = await steps.change({add: [2, 2], remove: [0]});
    assert.deepStrictEqual([change.step, change.stats.removedPoints,
                            change.stats.addedPoints, change.stats.pointCount,
                            change.stats.firstAddedId], [2, 1, 1, n, n - 1]);
    await steps.close();
    const knn = await client.kNearest(s.name, 3, {ids: [0, 1]});
    assert.ok(knn.ids instanceof Uint32Array);
    assert.strictEqual(knn.ids.length, 6);
    const mesh = await client.exportTriangulation(s.name);
    assert.ok(mesh.xy instanceof Float64Array && mesh.xy.length === 2 * n);
    await client.deleteSession(s.name);
    await assert.rejects(client.getSession(s.name),
                         (e) => e.code === status.NOT_FOUND);
    console.log('npm package: create, step, change, query, export, delete: ok');
  } catch (e) {
    console.error(e);
    process.exitCode = 1;
  } finally {
    client.close();
    proc.kill();
  }
});
JS
node smoke.js "$server"

cat >check.ts <<'TS'
// Uses the declarations the way a TypeScript simulation would.
import {Client, KinetriError, Neighbors, SESSION_HEADER, StepAck,
        newSessionId, status} from '@kinetri/client';

async function run(target: string): Promise<number> {
  const client = new Client(target, {deadlineSeconds: 10, token: 'x'.repeat(16)});
  const xy = new Float64Array(200);
  const s = await client.createSession(xy, newSessionId(), {ids: [1n, 2n]});
  const steps = await client.openSteps(s.name);
  const ack: StepAck = await steps.moveBy(xy, [1n]);
  const joined: StepAck = await steps.change({add: [0.1, 0.2], addIds: [3n],
                                              remove: ['1'], requestId: 'r'});
  await steps.moveTo(xy, null, {add: new Float64Array(2), addIds: [4], remove: []});
  const nn: Neighbors = await client.kNearest(s.name, 4, {positions: [0.5, 0.5]});
  const first: number = nn.ids[nn.offsets[0]];
  const far: bigint = nn.clientIds[0];
  const mesh = await client.exportTriangulation(s.name);
  const triangle: number = mesh.triangles[0];
  await steps.close();
  client.close();
  try {
    await client.getSession('sessions/none');
  } catch (e) {
    if (e instanceof KinetriError && e.code === status.NOT_FOUND) return 0;
  }
  return ack.step + first + Number(far) + triangle + SESSION_HEADER.length +
      s.pointCount + ack.stats.delaunayFlips + joined.stats.pointCount +
      joined.stats.firstAddedId + joined.stats.removedPoints +
      joined.stats.addedPoints;
}
void run;
TS
npx tsc --noEmit --strict --target es2020 --module commonjs \
  --moduleResolution node check.ts
echo "npm package: index.d.ts checked by tsc --strict: ok"
