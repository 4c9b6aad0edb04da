// End-to-end test of the Node.js client against a real kinetri-server.
'use strict';

const test = require('node:test');
const assert = require('node:assert');
const {spawn} = require('node:child_process');
const readline = require('node:readline');
const {Client, status} = require('..');

// KINETRI_SERVER, else the build tree's server.
const SERVER = process.env.KINETRI_SERVER ||
    require('node:path').join(__dirname, '..', '..', '..', 'build', 'server',
                              'kinetri-server');

function startServer(flags = []) {
  return new Promise((resolve, reject) => {
    const proc = spawn(SERVER,
                       ['--listen=127.0.0.1:0', '--metrics_listen=', ...flags]);
    const rl = readline.createInterface({input: proc.stdout});
    rl.on('line', (line) => {
      const m = /listening on port (\d+)/.exec(line);
      if (m) resolve({proc, target: `127.0.0.1:${m[1]}`});
    });
    proc.on('exit', () => reject(new Error('server exited')));
  });
}

function rng(seed) {
  let s = seed >>> 0;
  return () => ((s = (s * 1664525 + 1013904223) >>> 0) / 2 ** 32);
}

test('create, step, query against brute force, export, errors', async () => {
  const {proc, target} = await startServer();
  const client = new Client(target, {chunkPoints: 400});  // force chunking
  try {
    const rand = rng(7);
    const n = 1500;
    const xy = new Float64Array(2 * n).map(() => rand());
    const s = await client.createSession(xy, 'node-life');
    assert.strictEqual(s.name, 'sessions/node-life');
    assert.strictEqual(s.pointCount, n);

    const steps = await client.openSteps(s.name);
    for (let k = 1; k <= 100; k++) {
      const d = new Float64Array(2 * n).map(() => (rand() - 0.5) * 0.002);
      const ack = await steps.moveBy(d);
      assert.strictEqual(ack.step, k);
      for (let i = 0; i < xy.length; i++) xy[i] += d[i];
    }
    await steps.close();

    const nn = await client.nearestAll(s.name);
    assert.strictEqual(nn.step, 100);
    for (let i = 0; i < n; i += 13) {
      let best = -1, bd = Infinity;
      for (let j = 0; j < n; j++) {
        if (j === i) continue;
        const dx = xy[2 * i] - xy[2 * j], dy = xy[2 * i + 1] - xy[2 * j + 1];
        const dd = dx * dx + dy * dy;
        if (dd < bd) { bd = dd; best = j; }
      }
      assert.strictEqual(nn.ids[nn.offsets[i]], best);
    }
    const r = 0.04;
    const near = await client.radius(s.name, r, {positions: [0.5, 0.5]});
    const want = [];
    for (let j = 0; j < n; j++) {
      const dx = xy[2 * j] - 0.5, dy = xy[2 * j + 1] - 0.5;
      if (dx * dx + dy * dy <= r * r) want.push(j);
    }
    assert.deepStrictEqual([...near.ids].sort((a, b) => a - b), want);

    const knn = await client.kNearest(s.name, 4, {ids: [0, 500, 1000]});
    [0, 500, 1000].forEach((i, row) => {
      const order = [...Array(n).keys()].filter((j) => j !== i).sort((a, b) => {
        const da = (xy[2 * a] - xy[2 * i]) ** 2 + (xy[2 * a + 1] - xy[2 * i + 1]) ** 2;
        const db = (xy[2 * b] - xy[2 * i]) ** 2 + (xy[2 * b + 1] - xy[2 * i + 1]) ** 2;
        return da - db;
      });
      assert.deepStrictEqual([...knn.ids.slice(knn.offsets[row], knn.offsets[row + 1])],
                             order.slice(0, 4));
    });

    // Rows longer than a chunk are split by the server, merged here.
    {
      const req = {session: s.name, kind: 'QUERY_KIND_K_NEAREST', k: 60,
                   includeDistances: true, excludeSelf: true,
                   pointIds: {ids: [3, 4, 5]}};
      const whole = await client.query(req);
      const split = await client.query({...req, resultsPerChunk: 7,
                                        rowsPerChunk: 2});
      assert.deepStrictEqual(split.offsets, whole.offsets);
      assert.deepStrictEqual(split.ids, whole.ids);
      assert.deepStrictEqual(split.distances, whole.distances);
      assert.strictEqual(split.offsets[3], 180);
      // The same rows in fixed-width fields.
      const fixed = await client.query({...req, rowsPerChunk: 2,
                                        encoding: 'ANSWER_ENCODING_FIXED'});
      assert.deepStrictEqual(fixed.offsets, whole.offsets);
      assert.deepStrictEqual(fixed.ids, whole.ids);
      assert.deepStrictEqual(fixed.distances, whole.distances);
    }

    // A resent step (same requestId, its acknowledgement "lost") is not
    // applied twice; another requestId is refused.
    {
      const steps1 = await client.openSteps(s.name);
      const d = new Float64Array(2 * n).fill(1e-4);
      const ack = await steps1.moveBy(d, null, {requestId: 'node-step'});
      await steps1.close();
      const steps2 = await client.openSteps(s.name, {firstStep: ack.step});
      const again = await steps2.moveBy(d, null, {requestId: 'node-step'});
      assert.strictEqual(again.step, ack.step);
      assert.strictEqual(again.stats.delaunayFlips, ack.stats.delaunayFlips);
      await steps2.close();
      assert.strictEqual((await client.getSession(s.name)).step, ack.step);
      const steps3 = await client.openSteps(s.name, {firstStep: ack.step});
      await assert.rejects(steps3.moveBy(d, null, {requestId: 'other'}),
                           (e) => e.code === status.FAILED_PRECONDITION);
      await steps3.close();
    }

    const mesh = await client.exportTriangulation(s.name);
    assert.ok(mesh.xy instanceof Float64Array);
    assert.ok(mesh.triangles instanceof Uint32Array);
    assert.ok(nn.ids instanceof Uint32Array && nn.distances instanceof Float64Array);
    assert.strictEqual(mesh.xy.length, 2 * n);
    assert.ok(mesh.triangles.length > 3 * n);

    await assert.rejects(client.kNearest(s.name, 0, {ids: [1]}),
                         (e) => e.code === status.INVALID_ARGUMENT);
    await assert.rejects(client.getSession('sessions/missing'),
                         (e) => e.code === status.NOT_FOUND);
    const bad = await client.openSteps(s.name);
    const d = new Float64Array(2 * n);
    d[5] = NaN;
    await assert.rejects(bad.moveBy(d),
                         (e) => e.code === status.INVALID_ARGUMENT &&
                                /deltas\[2\]\.y/.test(e.message));
    // 100 steps and the idempotent one: the bad step changed nothing.
    assert.strictEqual((await client.getSession(s.name)).step, 101);
    await client.deleteSession(s.name);
  } finally {
    client.close();
    proc.kill('SIGTERM');
  }
});

test('client ids: 64-bit, exact, end to end; sequential ids never wrap',
     async () => {
  const {proc, target} = await startServer();
  const client = new Client(target);
  try {
    const rand = rng(11);
    const n = 300;
    const xy = new Float64Array(2 * n).map(() => rand());
    const ids = Array.from({length: n}, (_, i) => (1n << 40n) + BigInt(i) * 7919n);
    const s = await client.createSession(xy, 'node-cids', {ids});
    assert.strictEqual(s.options.pointIdPolicy, 'POINT_ID_POLICY_CLIENT');
    const all = await client.listSessions();
    assert.ok(all.some((x) => x.name === s.name));
    // k-NN of points named by client id, answered in client ids.
    const knn = await client.kNearest(s.name, 2, {ids: [ids[10], ids[20]]});
    assert.strictEqual(knn.ids.length, 0);
    for (const [row, i] of [[0, 10], [1, 20]]) {
      const d = [];
      for (let j = 0; j < n; j++) {
        if (j !== i) {
          d.push([(xy[2 * j] - xy[2 * i]) ** 2 + (xy[2 * j + 1] - xy[2 * i + 1]) ** 2, j]);
        }
      }
      d.sort((a, b) => a[0] - b[0]);
      assert.deepStrictEqual([...knn.clientIds.slice(knn.offsets[row], knn.offsets[row + 1])],
                             [ids[d[0][1]], ids[d[1][1]]]);
    }
    // The same answer in fixed-width fields (client ids as fixed64).
    const fixedKnn = await client.query({
      session: s.name, kind: 'QUERY_KIND_K_NEAREST', k: 2, excludeSelf: true,
      includeDistances: true, encoding: 'ANSWER_ENCODING_FIXED',
      pointIds: {clientIds: [ids[10].toString(), ids[20].toString()]}});
    assert.deepStrictEqual(fixedKnn.clientIds, knn.clientIds);
    assert.deepStrictEqual(fixedKnn.offsets, knn.offsets);
    const steps = await client.openSteps(s.name);
    const ack = await steps.moveTo([0.5, 0.5], [ids[5]]);
    assert.strictEqual(ack.step, 1);
    await steps.close();
    const mesh = await client.exportTriangulation(s.name);
    assert.deepStrictEqual([...mesh.pointIds], ids);
    assert.deepStrictEqual([mesh.xy[10], mesh.xy[11]], [0.5, 0.5]);
    await assert.rejects(client.kNearest(s.name, 1, {ids: [12345n]}),
                         (e) => e.code === status.NOT_FOUND);
    // Sequential sessions: 2^32 + 1 is not point 1.
    const q = await client.createSession(xy.slice(0, 100), 'node-seq');
    await assert.rejects(client.kNearest(q.name, 1, {ids: [2 ** 32 + 1]}),
                         (e) => e.code === status.NOT_FOUND);
    const st = await client.openSteps(q.name);
    await assert.rejects(st.moveBy([0.1, 0.1], [2 ** 32 + 1]),
                         (e) => e.code === status.NOT_FOUND);
    await st.close();
  } finally {
    client.close();
    proc.kill();
  }
});

test('TLS with client certificates and a bearer token', async () => {
  const fs = require('node:fs');
  const os = require('node:os');
  const path = require('node:path');
  const dir = fs.mkdtempSync(path.join(os.tmpdir(), 'kinetri-node-tls-'));
  const {execFileSync} = require('node:child_process');
  execFileSync('bash', [path.join(__dirname, '..', '..', '..', 'tests', 'e2e',
                                  'make_test_certs.sh'), dir]);
  const f = (name) => path.join(dir, name);
  const token = 'node-tenant-token-0123456789';
  fs.writeFileSync(f('tokens'), `${token} node\n`);
  const {proc, target} = await startServer([
    `--tls_cert=${f('server.pem')}`, `--tls_key=${f('server.key')}`,
    `--tls_client_ca=${f('ca.pem')}`, `--auth_tokens_file=${f('tokens')}`]);
  const secure = (extra) => new Client(target, {
    ca: f('ca.pem'), cert: f('client.pem'), key: f('client.key'), token,
    ...extra});
  try {
    const c = secure({});
    const xy = new Float64Array(600);
    const r = rng(3);
    for (let i = 0; i < xy.length; ++i) xy[i] = r();
    const s = await c.createSession(xy, 'node-secure');
    assert.strictEqual(s.name, 'sessions/node-secure');
    assert.strictEqual((await c.listSessions()).length, 1);
    await c.deleteSession(s.name);
    c.close();
    for (const [extra, code] of [
      [{token: ''}, status.UNAUTHENTICATED],
      [{token: 'wrong-token-0123456789'}, status.UNAUTHENTICATED],
      [{cert: '', key: ''}, status.UNAVAILABLE],
    ]) {
      const bad = secure(extra);
      await assert.rejects(bad.listSessions(), (e) => e.code === code);
      bad.close();
    }
    const plain = new Client(target, {token, ca: '', cert: ''});
    await assert.rejects(plain.listSessions(),
                         (e) => e.code === status.UNAVAILABLE);
    plain.close();
  } finally {
    proc.kill('SIGTERM');
    fs.rmSync(dir, {recursive: true, force: true});
  }
});

// Every call about a session names it in the `kinetri-session` header (what
// a proxy in front of several servers hashes): checked against a stand-in
// server that records the metadata of every call and fails it.
test('routing header on every call about a session', async () => {
  const grpc = require('@grpc/grpc-js');
  const protoLoader = require('@grpc/proto-loader');
  const path = require('node:path');
  const proto = path.join(__dirname, '..', '..', '..', 'proto');
  const def = protoLoader.loadSync(
      path.join(proto, 'kinetri', 'v1', 'kinetri.proto'),
      {includeDirs: [proto]});
  const Service = grpc.loadPackageDefinition(def).kinetri.v1.KinetriService;
  const seen = [];
  const fail = {code: grpc.status.UNIMPLEMENTED, details: 'stand-in'};
  const handlers = {};
  for (const [name, m] of Object.entries(Service.service)) {
    handlers[name] = (call, cb) => {
      seen.push({name, key: call.metadata.get('kinetri-session')});
      if (call.request && call.request.name === 'sessions/hang') return;
      if (!m.responseStream) {
        cb(fail);
      } else {
        call.emit('error', fail);
      }
    };
  }
  const server = new grpc.Server();
  server.addService(Service.service, handlers);
  const port = await new Promise((resolve, reject) =>
    server.bindAsync('127.0.0.1:0', grpc.ServerCredentials.createInsecure(),
                     (err, p) => (err ? reject(err) : resolve(p))));
  const client = new Client(`127.0.0.1:${port}`);
  const xy = new Float64Array(6);
  try {
    const calls = [
      () => client.getSession('sessions/run-7'),
      () => client.deleteSession('sessions/run-7'),
      () => client.nearestAll('sessions/run-7'),
      () => client.kNearest('sessions/run-7', 2, {positions: xy}),
      () => client.exportTriangulation('sessions/run-7'),
      () => client.createSession(xy, 'run-7'),
    ];
    for (const call of calls) {
      seen.length = 0;
      await assert.rejects(call());
      assert.strictEqual(seen.length, 1);
      assert.deepStrictEqual(seen[0].key, ['run-7'], seen[0].name);
    }
    // A session the caller does not name is named by the client, and the
    // creation is routed by that name.
    seen.length = 0;
    await assert.rejects(client.createSession(xy));
    assert.match(seen[0].key[0], /^s-[0-9a-f]{32}$/);
    // Calls about no session carry no key.
    seen.length = 0;
    await assert.rejects(client.listSessions());
    assert.deepStrictEqual(seen[0].key, []);
    // Nor do names that cannot be a session id (huge or odd).
    seen.length = 0;
    await assert.rejects(client.getSession('sessions/' + 'x'.repeat(100000)));
    assert.deepStrictEqual(seen[0].key, []);
    // Every call but step streams has a deadline.
    const impatient = new Client(`127.0.0.1:${port}`, {deadlineSeconds: 0.3});
    const t0 = Date.now();
    await assert.rejects(impatient.getSession('sessions/hang'),
                         (e) => e.code === status.DEADLINE_EXCEEDED);
    assert.ok(Date.now() - t0 < 5000);
    impatient.close();
  } finally {
    client.close();
    server.forceShutdown();
  }
});

// ---------------------------------------------------------------------------
// Points that join and leave with a step (StepRequest remove/add fields).

// Indices of the model's points in the order queries answer from q:
// squared distance, ties between distinct positions to the larger x, then
// the larger y, ties between coincident points to the smaller index (the
// server's documented total order, core/queries.h); `skip`: left out
// (excludeSelf). Returns [order, d2].
function rank(xy, q, skip = -1) {
  const d2 = xy.map(([x, y]) => (x - q[0]) ** 2 + (y - q[1]) ** 2);
  const order = [...xy.keys()].filter((i) => i !== skip);
  order.sort((a, b) => d2[a] - d2[b] || xy[b][0] - xy[a][0] ||
                       xy[b][1] - xy[a][1] || a - b);
  return [order, d2];
}

const key = ([x, y]) => `${x},${y}`;

// Area of the convex hull of the points (monotone chain).
function hullArea(xy) {
  const pts = [...new Map(xy.map((p) => [key(p), p])).values()]
      .sort((a, b) => a[0] - b[0] || a[1] - b[1]);
  if (pts.length < 3) return 0;
  const cross = (o, a, b) =>
    (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]);
  const chain = (list) => {
    const h = [];
    for (const p of list) {
      while (h.length >= 2 && cross(h[h.length - 2], h[h.length - 1], p) <= 0) {
        h.pop();
      }
      h.push(p);
    }
    h.pop();
    return h;
  };
  const h = [...chain(pts), ...chain([...pts].reverse())];
  let a = 0;
  for (let i = 0; i < h.length; i++) {
    const [x0, y0] = h[i], [x1, y1] = h[(i + 1) % h.length];
    a += x0 * y1 - x1 * y0;
  }
  return Math.abs(a) / 2;
}

// The exported mesh of the model's points: corners are the smallest index
// of each distinct position, every one used; counter-clockwise triangles
// tiling the convex hull with empty circumcircles.
function checkDelaunay(xy, tris, what) {
  const first = new Map();
  xy.forEach((p, i) => { if (!first.has(key(p))) first.set(key(p), i); });
  const area = hullArea(xy);
  if (area === 0) {
    assert.strictEqual(tris.length, 0, what);
    return;
  }
  assert.deepStrictEqual([...new Set(tris)].sort((a, b) => a - b),
                         [...first.values()].sort((a, b) => a - b), what);
  const sites = [...first.values()].map((i) => xy[i]);
  let sum = 0;
  for (let t = 0; t < tris.length; t += 3) {
    const [a, b, d] = [xy[tris[t]], xy[tris[t + 1]], xy[tris[t + 2]]];
    const area2 = (b[0] - a[0]) * (d[1] - a[1]) - (b[1] - a[1]) * (d[0] - a[0]);
    assert.ok(area2 > 0, `${what}: triangle ${t / 3} not counter-clockwise`);
    sum += area2 / 2;
    for (const p of sites) {
      const [ax, ay, bx, by, dx, dy] =
          [a[0] - p[0], a[1] - p[1], b[0] - p[0], b[1] - p[1], d[0] - p[0],
           d[1] - p[1]];
      const la = ax * ax + ay * ay, lb = bx * bx + by * by,
            ld = dx * dx + dy * dy;
      const det = ax * (by * ld - lb * dy) - ay * (bx * ld - lb * dx) +
                  la * (bx * dy - by * dx);
      const A = Math.abs;
      const bound = A(ax) * (A(by) * ld + lb * A(dy)) +
                    A(ay) * (A(bx) * ld + lb * A(dx)) +
                    la * (A(bx) * A(dy) + A(by) * A(dx));
      assert.ok(!(det > 1e-9 * bound),
                `${what}: site ${p} inside the circumcircle of triangle ${t / 3}`);
    }
  }
  assert.ok(Math.abs(sum - area) <= 1e-9 * Math.max(1, area),
            `${what}: triangles cover ${sum}, hull ${area}`);
}

// Checks the session against the model: positions `xy` ([x, y] in id
// order) and, on client-id sessions, `ids` (BigInt, same order; null:
// sequential). Session, export, k nearest and radius against brute force.
async function checkModel(client, name, step, xy, ids, seed) {
  const n = xy.length;
  const what = `step ${step}`;
  const s = await client.getSession(name);
  assert.strictEqual(s.step, step, what);
  assert.strictEqual(s.pointCount, n, what);
  assert.strictEqual(s.siteCount, new Set(xy.map(key)).size, what);

  const mesh = await client.exportTriangulation(name);
  assert.strictEqual(mesh.step, step, what);
  assert.deepStrictEqual(mesh.xy, Float64Array.from(xy.flat()), what);
  assert.deepStrictEqual([...mesh.pointIds], ids || [], what);
  checkDelaunay(xy, mesh.triangles, what);
  if (n === 0) return;

  // How the server names model point i in requests and answers.
  const named = (i) => (ids ? ids[i] : i);
  const row = (res, r) => (ids ?
    [...res.clientIds.slice(res.offsets[r], res.offsets[r + 1])] :
    [...res.ids.slice(res.offsets[r], res.offsets[r + 1])]);
  const dist = (res, r) => [...res.distances.slice(res.offsets[r],
                                                   res.offsets[r + 1])];
  const close = (got, want, msg) => {
    assert.strictEqual(got.length, want.length, msg);
    got.forEach((g, j) => assert.ok(
        Math.abs(g - want[j]) <= 1e-12 * Math.max(1, want[j]),
        `${msg}: distance ${g}, want ${want[j]}`));
  };

  // k nearest of points named by id (excludeSelf).
  const sel = [...xy.keys()].filter((i) => i % 7 === step % 7);
  const knn = await client.kNearest(name, 5, {ids: sel.map(named)});
  assert.strictEqual(knn.step, step, what);
  assert.strictEqual(knn.offsets.length, sel.length + 1, what);
  sel.forEach((i, r) => {
    const [order, d2] = rank(xy, xy[i], i);
    const want = order.slice(0, 5);
    assert.deepStrictEqual(row(knn, r), want.map(named), `${what}: knn of ${i}`);
    close(dist(knn, r), want.map((j) => Math.sqrt(d2[j])), `${what}: knn of ${i}`);
  });

  // k nearest of positions: random ones, the most crowded site, a point
  // outside the hull.
  const counts = new Map();
  for (const p of xy) counts.set(key(p), (counts.get(key(p)) || 0) + 1);
  const crowded = xy.find((p) => counts.get(key(p)) ===
                                 Math.max(...counts.values()));
  const r = rng(seed);
  const qs = [...Array(12)].map(() => [r(), r()]);
  qs.push(crowded, [-3, 0.5]);
  const knq = await client.kNearest(name, 4, {positions: qs.flat()});
  qs.forEach((q, k) => {
    const [order, d2] = rank(xy, q);
    const want = order.slice(0, 4);
    assert.deepStrictEqual(row(knq, k), want.map(named), `${what}: knn of ${q}`);
    close(dist(knq, k), want.map((j) => Math.sqrt(d2[j])), `${what}: knn of ${q}`);
  });

  // Radius (inclusive, closest first) of points named by id and of the
  // crowded site.
  const rad = 0.07;
  const rsel = [...xy.keys()].filter((i) => i % 11 === step % 11);
  const near = await client.radius(name, rad, {ids: rsel.map(named)});
  rsel.forEach((i, k) => {
    const [order, d2] = rank(xy, xy[i], i);
    const want = order.filter((j) => d2[j] <= rad * rad);
    assert.deepStrictEqual(row(near, k), want.map(named), `${what}: radius of ${i}`);
    close(dist(near, k), want.map((j) => Math.sqrt(d2[j])), `${what}: radius of ${i}`);
  });
  const nearq = await client.radius(name, rad, {positions: crowded});
  {
    const [order, d2] = rank(xy, crowded);
    assert.deepStrictEqual(row(nearq, 0),
                           order.filter((j) => d2[j] <= rad * rad).map(named),
                           `${what}: radius of ${crowded}`);
  }

  // Nearest other point of every point.
  const nn = await client.nearestAll(name);
  assert.strictEqual(nn.offsets.length, n + 1, what);
  for (let i = 0; i < n; i++) {
    const want = n > 1 ? [named(rank(xy, xy[i], i)[0][0])] : [];
    assert.deepStrictEqual(row(nn, i), want, `${what}: nearest of ${i}`);
  }
}

// One step sent as the raw messages `reqs` on a new stream: resolves with
// its acknowledgement, rejects with the server's status.
function rawStep(client, reqs) {
  return new Promise((resolve, reject) => {
    const call = client.stub.StreamSteps();
    call.on('data', (resp) => { resolve(resp); call.end(); });
    call.on('error', (err) => reject(err));
    call.on('end', () => reject(new Error('stream ended without an answer')));
    for (const r of reqs) call.write(r);
  });
}

async function runJoinLeave(clientIds) {
  const {proc, target} = await startServer();
  // Few points per message: moves, removals and additions of a step span
  // several messages.
  const client = new Client(target, {chunkPoints: 37});
  try {
    const rand = rng(clientIds ? 31 : 30);
    const n = 500;
    let xy = [...Array(n)].map(() => [rand(), rand()]);
    let ids = clientIds ?
      [...Array(n).keys()].map((i) => (1n << 40n) + BigInt(i) * 7919n) : null;
    let nextCid = 1n << 50n;
    const leftEarlier = [];  // client ids that left in an earlier step
    const s = await client.createSession(Float64Array.from(xy.flat()), '',
                                         clientIds ? {ids} : {});
    const name = s.name;
    const steps = await client.openSteps(name);
    const named = (list) => (clientIds ? list.map((i) => ids[i]) : list);
    for (let step = 1; step <= 8; step++) {
      const count = xy.length;
      // Distinct leaving points.
      const gone = [];
      const size = 5 + Math.floor(rand() * 35);
      while (gone.length < size) {
        const i = Math.floor(rand() * count);
        if (!gone.includes(i)) gone.push(i);
      }
      const keep = xy.map((_, i) => !gone.includes(i));
      const moved = xy.map((p) => [...p]);
      const kind = step % 4;
      let values = null, mids = null;
      if (kind === 0) {  // dense deltas (the leaving points' are ignored)
        values = xy.map(() => [(rand() - 0.5) * 4e-3, (rand() - 0.5) * 4e-3]);
        moved.forEach((p, i) => { p[0] += values[i][0]; p[1] += values[i][1]; });
      } else if (kind === 1 || kind === 2) {  // sparse deltas / positions
        mids = [...xy.keys()].filter((i) => keep[i] && i % 11 === step % 11);
        values = mids.map(() => (kind === 1 ?
          [(rand() - 0.5) * 1e-2, (rand() - 0.5) * 1e-2] : [rand(), rand()]));
        mids.forEach((i, k) => {
          moved[i] = kind === 1 ?
            [moved[i][0] + values[k][0], moved[i][1] + values[k][1]] :
            [...values[k]];
        });
      }
      const stay = moved.filter((_, i) => keep[i]);
      // Joining points: inside, outside the hull, on a remaining point
      // (twice), where a leaving point was, and on each other.
      const m = 10 + Math.floor(rand() * 50);
      const add = [...Array(m)].map(() => [rand(), rand()]);
      add[0] = [-0.5 - 0.25 * step, 1.0 + 0.3 * step];
      add[1] = [2.0 + 0.1 * step, -0.1 * step];
      add[2] = [...stay[Math.floor(rand() * stay.length)]];
      add[3] = [...add[2]];
      add[4] = [...xy[gone[0]]];
      add[5] = [...add[6]];
      let addIds;
      if (clientIds) {
        addIds = [...Array(m).keys()].map((k) => nextCid + BigInt(k));
        nextCid += BigInt(m);
        // A leaving id joins again at once, one that left earlier now.
        addIds[m - 1] = ids[gone[0]];
        if (leftEarlier.length) addIds[m - 2] = leftEarlier.shift();
        leftEarlier.push(ids[gone[1]], ids[gone[2]]);
      }
      const changes = {add: Float64Array.from(add.flat()), addIds,
                       remove: named(gone)};
      let ack;
      if (kind === 0) {
        ack = await steps.moveBy(values.flat(), null, changes);
      } else if (kind === 1) {
        ack = await steps.moveBy(values.flat(), named(mids), changes);
      } else if (kind === 2) {
        ack = await steps.moveTo(values.flat(), named(mids), changes);
      } else {
        ack = await steps.change(changes);
        assert.strictEqual(ack.stats.movedPoints, 0);
      }
      xy = [...stay, ...add];
      if (clientIds) ids = [...ids.filter((_, i) => keep[i]), ...addIds];
      assert.strictEqual(ack.step, step);
      assert.strictEqual(ack.stats.removedPoints, gone.length);
      assert.strictEqual(ack.stats.addedPoints, m);
      assert.strictEqual(ack.stats.pointCount, xy.length);
      assert.strictEqual(ack.stats.firstAddedId, clientIds ? 0 : stay.length);
      await checkModel(client, name, step, xy, ids, step);
    }
    await steps.close();
    await checkRefusals(client, name, clientIds, xy, ids);
    await client.deleteSession(name);
  } finally {
    client.close();
    proc.kill();
  }
}

// Refused steps end the stream with their status and change nothing.
async function checkRefusals(client, name, clientIds, xy, ids) {
  const n = xy.length;
  const step = (await client.getSession(name)).step;
  const before = await client.exportTriangulation(name);
  const unchanged = async (what) => {
    const s = await client.getSession(name);
    assert.deepStrictEqual([s.step, s.pointCount], [step, n], what);
    assert.deepStrictEqual(await client.exportTriangulation(name), before, what);
  };
  const refused = async (code, send, what) => {
    const steps = await client.openSteps(name);
    await assert.rejects(send(steps), (e) => {
      assert.strictEqual(e.code, code, `${what}: ${e.code} ${e.message}`);
      return true;
    }, what);
    await steps.close();
    await unchanged(what);
  };
  const raw = async (code, fields, what) => {
    await assert.rejects(
        rawStep(client, [{session: name, step: step + 1, endOfStep: true,
                          ...fields}]),
        (e) => {
          assert.strictEqual(e.code, code, `${what}: ${e.code} ${e.details}`);
          return true;
        }, what);
    await unchanged(what);
  };
  const {INVALID_ARGUMENT, NOT_FOUND, ALREADY_EXISTS} = status;
  if (clientIds) {
    const [a, b, c] = [ids[1], ids[2], ids[3]];
    await refused(NOT_FOUND, (st) => st.change({remove: [123456789n]}),
                  'unknown leaving id');
    await refused(NOT_FOUND, (st) => st.change({remove: [a, 5]}),
                  'known and unknown leaving ids');
    await refused(ALREADY_EXISTS,
                  (st) => st.change({add: [0.25, 0.25], addIds: [a]}),
                  'joining id that stays');
    await refused(ALREADY_EXISTS,
                  (st) => st.change({add: [0.25, 0.25], addIds: [b],
                                     remove: [a]}),
                  'joining id that stays, another leaves');
    await refused(ALREADY_EXISTS,
                  (st) => st.moveBy([0.01, 0], [c],
                                    {add: [0.3, 0.3], addIds: [c]}),
                  'joining id that moves');
    await refused(INVALID_ARGUMENT,
                  (st) => st.change({add: [0.1, 0.1, 0.2, 0.2],
                                     addIds: [77n, 77n]}),
                  'duplicate joining ids');
    await refused(INVALID_ARGUMENT,
                  (st) => st.change({add: [0.1, 0.1, 0.2, 0.2],
                                     addIds: [a, a], remove: [a]}),
                  'duplicate joining ids, leaving too');
    await refused(INVALID_ARGUMENT, (st) => st.change({remove: [a, b, a]}),
                  'duplicate leaving ids');
    await refused(INVALID_ARGUMENT,
                  (st) => st.moveBy([0.01, 0], [b], {remove: [b]}),
                  'moved and leaving');
    await refused(INVALID_ARGUMENT,
                  (st) => st.moveTo([0.5, 0.5], [b], {remove: [a, b]}),
                  'moved to and leaving');
    await refused(INVALID_ARGUMENT,
                  (st) => st.change({add: [0.25, NaN], addIds: [99n]}),
                  'joining at NaN');
    // What the client checks itself, sent raw.
    await raw(INVALID_ARGUMENT, {addXy: [0.25, 0.25]},
              'joining point without its id');
    await raw(INVALID_ARGUMENT, {addXy: [0.25, 0.25],
                                 addClientIds: ['5', '6']},
              'two ids for one joining point');
    await raw(INVALID_ARGUMENT, {removeIds: [1]},
              'sequential leaving id on a client-id session');
    await raw(INVALID_ARGUMENT, {addXy: [0.25, 0.25, 0.5],
                                 addClientIds: ['5']},
              'odd add_xy');
  } else {
    await refused(NOT_FOUND, (st) => st.change({remove: [n]}),
                  'leaving id past the end');
    await refused(NOT_FOUND, (st) => st.change({remove: [3, n + 10]}),
                  'known and unknown leaving ids');
    await refused(NOT_FOUND,
                  (st) => st.moveBy(new Float64Array(2 * n), null,
                                    {remove: [n], add: [0.5, 0.5]}),
                  'unknown leaving id with dense moves');
    await refused(INVALID_ARGUMENT, (st) => st.change({remove: [4, 9, 4]}),
                  'duplicate leaving ids');
    await refused(INVALID_ARGUMENT,
                  (st) => st.moveBy([0.01, 0], [6], {remove: [6]}),
                  'moved and leaving');
    await refused(INVALID_ARGUMENT,
                  (st) => st.moveTo([0.5, 0.5, 0.6, 0.6], [7, 6],
                                    {remove: [2, 6], add: [0.1, 0.1]}),
                  'moved to and leaving');
    await refused(INVALID_ARGUMENT, (st) => st.change({add: [0.25, NaN]}),
                  'joining at NaN');
    await refused(INVALID_ARGUMENT,
                  (st) => st.change({add: [Infinity, 0.25]}),
                  'joining at infinity');
    await raw(INVALID_ARGUMENT, {addXy: [0.25, 0.25], addClientIds: ['7']},
              'joining id on a sequential session');
    await raw(INVALID_ARGUMENT, {removeClientIds: ['1']},
              'client leaving id on a sequential session');
    await raw(INVALID_ARGUMENT, {addXy: [0.25]}, 'odd add_xy');
  }
  // Checked before anything is sent: the stream goes on.
  const steps = await client.openSteps(name);
  const bad = [
    {add: [0.5]},
    {add: [[0.5, 0.5]]},
    {add: [0.5, 0.5], addIds: [1n, 2n]},
    {addIds: [5n]},
    {add: [0.5, 0.5], addIds: [-1]},
    {add: [0.5, 0.5], addIds: [1n << 64n]},
    {add: [0.5, 0.5], addIds: [1.5]},
    {add: [0.5, 0.5], addIds: ['']},
    {add: [0.5, 0.5], addIds: ['x']},
    {remove: [1.5]},
  ];
  if (!clientIds) bad.push({add: [0.5, 0.5], addIds: [3]});
  else bad.push({add: [0.5, 0.5]});
  for (const changes of bad) {
    await assert.rejects(steps.change(changes),
                         (e) => e.code === INVALID_ARGUMENT,
                         JSON.stringify(changes, (k, v) =>
                           (typeof v === 'bigint' ? `${v}n` : v)));
  }
  for (const remove of [[-1], clientIds ? [1n << 64n] : [2 ** 32]]) {
    await assert.rejects(steps.change({remove}),
                         (e) => e.code === NOT_FOUND, `remove ${remove}`);
  }
  assert.strictEqual(steps.nextStep, step + 1);
  await unchanged('refused before sending');
  // The same stream applies the next valid step.
  const ack = await steps.change(clientIds ?
    {remove: [ids[0]], add: [0.5, 0.5], addIds: [ids[0]]} :
    {remove: [0], add: [...xy[0]]});
  assert.deepStrictEqual([ack.step, ack.stats.pointCount], [step + 1, n]);
  await steps.close();
}

test('points join and leave with steps: sequential ids', () =>
  runJoinLeave(false));

test('points join and leave with steps: client ids', () =>
  runJoinLeave(true));

test('join and leave: emptied and refilled, resent changes', async () => {
  const {proc, target} = await startServer();
  const client = new Client(target);
  try {
    // Sequential: down to no points, a line, a triangle again.
    const rand = rng(5);
    const pts = [...Array(6)].map(() => [rand(), rand()]);
    const s = await client.createSession(Float64Array.from(pts.flat()));
    const steps = await client.openSteps(s.name);
    let ack = await steps.change({remove: [5, 4, 3, 2, 1, 0]});
    assert.deepStrictEqual([ack.stats.removedPoints, ack.stats.pointCount,
                            ack.stats.firstAddedId], [6, 0, 0]);
    await checkModel(client, s.name, 1, [], null, 1);
    const line = [[0, 0], [1, 1], [2, 2]];
    ack = await steps.change({add: line.flat()});
    assert.deepStrictEqual([ack.stats.addedPoints, ack.stats.pointCount,
                            ack.stats.firstAddedId], [3, 3, 0]);
    await checkModel(client, s.name, 2, line, null, 2);
    ack = await steps.moveBy([0, 1], [2], {add: [2, 0], remove: [1]});
    assert.deepStrictEqual([ack.stats.pointCount, ack.stats.firstAddedId],
                           [3, 2]);
    await checkModel(client, s.name, 3, [[0, 0], [2, 3], [2, 0]], null, 3);
    await steps.close();
    await client.deleteSession(s.name);

    // Client ids: all leave, then some join again.
    const cids = [10n, 20n, 30n, 40n, 50n];
    const c = await client.createSession(Float64Array.from(pts.slice(0, 5).flat()),
                                         '', {ids: cids});
    const csteps = await client.openSteps(c.name);
    ack = await csteps.change({remove: [...cids].reverse()});
    assert.strictEqual(ack.stats.pointCount, 0);
    await checkModel(client, c.name, 1, [], [], 1);
    ack = await csteps.change({add: line.flat(), addIds: [30n, 31n, 32n]});
    assert.strictEqual(ack.stats.pointCount, 3);
    await checkModel(client, c.name, 2, line, [30n, 31n, 32n], 2);
    ack = await csteps.moveBy([0, 1], [32n],
                              {add: [2, 0], addIds: ['10'], remove: [31]});
    await checkModel(client, c.name, 3, [[0, 0], [2, 3], [2, 0]],
                     [30n, 32n, 10n], 3);
    await csteps.close();
    await client.deleteSession(c.name);

    // A step of joins and leaves resent under its requestId (its
    // acknowledgement lost) gets the original acknowledgement and applies
    // nothing, also after a later step.
    const many = [...Array(200)].map(() => [rand(), rand()]);
    const add = [...Array(5)].map(() => [rand(), rand()]);
    const r = await client.createSession(Float64Array.from(many.flat()),
                                         'node-change-idem');
    let st = await client.openSteps(r.name);
    const first = await st.change({add: add.flat(), remove: [0, 1],
                                   requestId: 'j-1'});
    await st.close();
    st = await client.openSteps(r.name, {firstStep: 1});
    assert.deepStrictEqual(await st.change({add: add.flat(), remove: [0, 1],
                                            requestId: 'j-1'}), first);
    await st.close();
    assert.strictEqual((await client.getSession(r.name)).pointCount, 203);
    st = await client.openSteps(r.name);
    const second = await st.moveBy([0.001, 0], [5],
                                   {add: add.slice(0, 3).flat(),
                                    requestId: 'j-2'});
    assert.deepStrictEqual([second.stats.pointCount, second.stats.firstAddedId],
                           [206, 203]);
    await st.close();
    st = await client.openSteps(r.name, {firstStep: 1});
    const again = await st.change({add: add.flat(), remove: [0, 1],
                                   requestId: 'j-1'});
    assert.deepStrictEqual(again, first);
    assert.deepStrictEqual([again.stats.pointCount, again.stats.firstAddedId],
                           [203, 198]);
    await st.close();
    const model = [...many.slice(2), ...add, ...add.slice(0, 3)];
    model[5] = [model[5][0] + 0.001, model[5][1]];
    await checkModel(client, r.name, 2, model, null, 4);
    await client.deleteSession(r.name);
  } finally {
    client.close();
    proc.kill();
  }
});

// The messages of one step (no server): every list split over messages of
// at most chunkPoints entries (moves, then removals, then additions),
// requestId on the first, endOfStep on the last; at the default chunk size
// no message reaches 4 MiB.
test('join and leave: step messages', () => {
  const {StepStream} = require('..');
  const grpc = require('@grpc/grpc-js');
  const protoLoader = require('@grpc/proto-loader');
  const path = require('node:path');
  const proto = path.join(__dirname, '..', '..', '..', 'proto');
  const def = protoLoader.loadSync(
      path.join(proto, 'kinetri', 'v1', 'kinetri.proto'),
      {includeDirs: [proto], longs: String, enums: String, defaults: true});
  const method = grpc.loadPackageDefinition(def).kinetri.v1.KinetriService
      .service.StreamSteps;
  const sent = [];
  const stub = {StreamSteps: () => ({on() {}, write: (r) => sent.push(r)})};
  const rand = rng(2);
  for (const clientIds of [false, true]) {
    const perMessage = 7;
    const stream = new StepStream(stub, 'sessions/x', 4, 2 * perMessage,
                                  clientIds);
    const id = (k) => (clientIds ? (1n << 60n) + BigInt(k) : k);
    for (const [nv, nr, na] of [[0, 0, 0], [25, 0, 0], [0, 7, 0], [0, 0, 9],
                                [10, 3, 4], [7, 7, 7], [31, 12, 50]]) {
      sent.length = 0;
      const values = [...Array(2 * nv)].map(rand);
      const ids = nv % 2 ? [...Array(nv).keys()].map((k) => id(3 * k)) : null;
      const remove = [...Array(nr).keys()].map((k) => id(1000 + k));
      const add = [...Array(2 * na)].map(rand);
      const addIds = clientIds ?
        [...Array(na).keys()].map((k) => (1n << 62n) + BigInt(k)) : undefined;
      const step = stream.nextStep;
      stream.moveTo(values, ids, {requestId: 'rid', add, addIds, remove});
      const total = nv + nr + na;
      assert.strictEqual(sent.length, Math.max(1, Math.ceil(total / perMessage)));
      // As the server decodes them.
      const msgs = sent.map((r) => method.requestDeserialize(
          method.requestSerialize(r)));
      assert.deepStrictEqual(msgs.map((r) => r.requestId),
                             ['rid', ...Array(msgs.length - 1).fill('')]);
      assert.deepStrictEqual(msgs.map((r) => r.endOfStep),
                             [...Array(msgs.length - 1).fill(false), true]);
      for (const r of msgs) {
        assert.deepStrictEqual([r.step, r.session, r.mode],
                               [String(step), 'sessions/x',
                                'DISPLACEMENT_MODE_ABSOLUTE']);
        assert.ok(r.xy.length / 2 + r.removeIds.length +
                  r.removeClientIds.length + r.addXy.length / 2 <= perMessage);
        // A message with moves names them (sparse steps).
        assert.strictEqual((clientIds ? r.clientIds : r.ids).length,
                           ids ? r.xy.length / 2 : 0);
      }
      const cat = (field) => msgs.flatMap((r) => r[field]);
      const str = (list) => list.map(String);
      assert.deepStrictEqual(cat('xy'), values);
      assert.deepStrictEqual(str(cat(clientIds ? 'clientIds' : 'ids')),
                             ids ? str(ids) : []);
      assert.deepStrictEqual(str(cat(clientIds ? 'removeClientIds' : 'removeIds')),
                             str(remove));
      assert.deepStrictEqual(cat(clientIds ? 'removeIds' : 'removeClientIds'), []);
      assert.deepStrictEqual(cat('addXy'), add);
      assert.deepStrictEqual(str(cat('addClientIds')), addIds ? str(addIds) : []);
    }
  }
  // Default chunk size: the largest ids, every list longer than a message.
  sent.length = 0;
  const big = 131072 + 1000;
  const stream = new StepStream(stub, 'sessions/x', 1, undefined, true);
  const huge = (k) => (1n << 64n) - 1n - BigInt(k);
  stream.moveBy(new Float64Array(2 * big).fill(Math.PI),
                [...Array(big).keys()].map(huge),
                {add: new Float64Array(2 * big).fill(Math.E),
                 addIds: [...Array(big).keys()].map((k) => huge(big + k)),
                 remove: [...Array(big).keys()].map((k) => huge(2 * big + k))});
  assert.strictEqual(sent.length, 4);
  const sizes = sent.map((r) => method.requestSerialize(r).length);
  assert.ok(Math.max(...sizes) < 4 << 20, `message sizes ${sizes}`);
});

test('query targets beyond one message go by StreamQuery', async () => {
  const {proc, target} = await startServer();
  const client = new Client(target, {chunkPoints: 100});
  try {
    const rand = rng(21);
    const n = 800;
    const xy = new Float64Array(2 * n).map(() => rand());
    const s = await client.createSession(xy);
    const q = new Float64Array(2 * 700).map(() => rand());  // 7 messages
    const knn = await client.kNearest(s.name, 3, {positions: q});
    assert.strictEqual(knn.offsets.length, 701);
    const d2 = (a, x, y) => (xy[2 * a] - x) ** 2 + (xy[2 * a + 1] - y) ** 2;
    for (let r = 0; r < 700; r += 23) {
      const x = q[2 * r], y = q[2 * r + 1];
      const order = [...Array(n).keys()].sort(
          (a, b) => d2(a, x, y) - d2(b, x, y));
      assert.deepStrictEqual([...knn.ids.slice(knn.offsets[r],
                                               knn.offsets[r + 1])],
                             order.slice(0, 3), `query ${r}`);
    }
    const ids = [...Array(n).keys()];  // 800 ids: 4 messages
    const byId = await client.kNearest(s.name, 1, {ids});
    assert.strictEqual(byId.offsets.length, n + 1);
    const nn = await client.nearestAll(s.name);
    assert.deepStrictEqual([...byId.ids], [...nn.ids]);
    await client.deleteSession(s.name);
  } finally {
    client.close();
    proc.kill();
  }
});

// A chunk that carries offsets, ids or client ids in both encodings is no
// answer a server writes: the query is refused with INTERNAL, as the C++
// client refuses it. A fake server (the same proto) writes them.
test('a query answer with a field in both encodings is refused', async () => {
  const grpc = require('@grpc/grpc-js');
  const protoLoader = require('@grpc/proto-loader');
  const path = require('node:path');
  const protoDir = path.join(__dirname, '..', '..', '..', 'proto');
  const def = protoLoader.loadSync(
      path.join(protoDir, 'kinetri', 'v1', 'kinetri.proto'),
      {keepCase: false, longs: String, enums: String, defaults: true,
       oneofs: true, includeDirs: [protoDir]});
  const Service = grpc.loadPackageDefinition(def).kinetri.v1.KinetriService;
  const good = {offsets: [0, 1], ids: [4]};
  const bad = [
    {offsets: [0, 1], fixedOffsets: [0, 1], ids: [4]},
    {offsets: [0, 1], ids: [4], fixedIds: [4]},
    {fixedOffsets: [0, 1], clientIds: ['4'], fixedClientIds: ['4']},
  ];
  let chunk = good;
  const server = new grpc.Server();
  server.addService(Service.service, {
    query: (call) => {
      call.write({step: 3, ...chunk});
      call.write({step: 3, offsets: [0, 1], ids: [5]});
      call.end();
    },
  });
  const port = await new Promise((resolve, reject) => server.bindAsync(
      '127.0.0.1:0', grpc.ServerCredentials.createInsecure(),
      (err, p) => (err ? reject(err) : resolve(p))));
  const client = new Client(`127.0.0.1:${port}`);
  try {
    const req = {session: 's', kind: 'QUERY_KIND_K_NEAREST', k: 1,
                 pointIds: {ids: [0]}};
    const ok = await client.query(req);
    assert.deepStrictEqual(Array.from(ok.ids), [4, 5]);
    for (chunk of bad) {
      await assert.rejects(client.query(req), (err) => {
        assert.strictEqual(err.code, status.INTERNAL, JSON.stringify(chunk));
        assert.match(err.message, /both as varints and fixed-width/);
        return true;
      });
    }
  } finally {
    client.close();
    server.forceShutdown();
  }
});
