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
