// Node.js client for the Kinetri proximity service (kinetri.v1).
//
// Positions go in as interleaved x, y (a Float64Array or any array of
// numbers); results come back as typed arrays: queries in CSR form ({step,
// offsets: Float64Array, ids: Uint32Array, distances: Float64Array,
// clientIds: BigUint64Array, truncatedRows}), exports as {step, xy:
// Float64Array, triangles: Uint32Array, pointIds: BigUint64Array}. Chunking
// is hidden. Point ids are exact: sequential ids are checked to lie in
// uint32 range (never wrapped), client ids (POINT_ID_POLICY_CLIENT
// sessions) are 64-bit (BigInt, Number or decimal string in; BigInt out).
// Types: index.d.ts.
'use strict';

const crypto = require('crypto');
const fs = require('fs');
const path = require('path');
const grpc = require('@grpc/grpc-js');
const protoLoader = require('@grpc/proto-loader');

// The package ships the proto (copied by `npm pack`, see package.json); in
// the source tree it is read from proto/ at the top.
const PROTO_DIR = fs.existsSync(path.join(__dirname, 'proto')) ?
  path.join(__dirname, 'proto') : path.join(__dirname, '..', '..', 'proto');
const PROTO = path.join(PROTO_DIR, 'kinetri', 'v1', 'kinetri.proto');
const CHUNK_VALUES = 2 * 131072;

function loadService() {
  const def = protoLoader.loadSync(PROTO, {
    // 64-bit fields as strings (exact), converted below: counters and
    // offsets to Number, client ids to BigInt.
    keepCase: false, longs: String, enums: String, defaults: true,
    oneofs: true, includeDirs: [PROTO_DIR],
  });
  return grpc.loadPackageDefinition(def).kinetri.v1.KinetriService;
}

// Every call about one session carries its id in this header, so that a
// proxy in front of several servers (HAProxy hashing the header,
// deploy/proxy/haproxy.cfg) sends all of a session's calls to its owner.
const SESSION_HEADER = 'kinetri-session';

// Call metadata routing a call to the owner of `session` (a name
// "sessions/{id}" or an id).
function route(session) {
  const md = new grpc.Metadata();
  const key = session.startsWith('sessions/') ?
    session.slice('sessions/'.length) : session;
  // Only what can be a session id: the server refuses anything else, and a
  // huge name must not become a huge header.
  if (/^[a-z0-9-]{1,63}$/.test(key)) md.set(SESSION_HEADER, key);
  return md;
}

// A new session id as the server would make one: "s-" + 128 random bits.
function newSessionId() {
  return 's-' + crypto.randomBytes(16).toString('hex');
}

class KinetriError extends Error {
  constructor(err) {
    super(err.details || err.message);
    this.code = err.code;  // grpc.status value
  }
}

// A session as returned by the server, with its 64-bit counters as Numbers.
function toSession(s) {
  return {...s, pointCount: Number(s.pointCount), siteCount: Number(s.siteCount),
          step: Number(s.step)};
}

// Every 64-bit counter of a message (strings from the loader) as a Number
// (StepStats: pointCount, firstAddedId, interiorFixFlips, ...).
function numbers(obj) {
  const out = {};
  for (const [k, v] of Object.entries(obj)) {
    out[k] = typeof v === 'string' && /^[0-9]+$/.test(v) ? Number(v) : v;
  }
  return out;
}

// One id as a BigInt: a BigInt, an integral Number or a decimal string
// (null otherwise; an empty string is not 0).
function toBigInt(id) {
  if (typeof id === 'bigint') return id;
  if (typeof id === 'number') return Number.isInteger(id) ? BigInt(id) : null;
  if (typeof id === 'string' && /^-?[0-9]+$/.test(id.trim())) {
    return BigInt(id.trim());
  }
  return null;
}

// Point ids for a request: client ids as decimal strings (exact 64-bit),
// sequential ids checked to be integers in [0, 2^32) (NOT_FOUND otherwise,
// as the server says for an id it does not know).
function pointIds(ids, clientIds, field = 'ids') {
  return Array.from(ids, (id, i) => {
    const big = toBigInt(id);
    if (big === null) {
      throw new KinetriError({code: grpc.status.INVALID_ARGUMENT,
                              details: `${field}[${i}] = ${id}: not an integer`});
    }
    const max = clientIds ? (1n << 64n) : (1n << 32n);
    if (big < 0n || big >= max) {
      throw new KinetriError({code: grpc.status.NOT_FOUND,
                              details: `${field}[${i}] = ${id}: no such point`});
    }
    return clientIds ? big.toString() : Number(big);
  });
}

// Client ids of points that join (they name no point yet): integers in
// [0, 2^64) as decimal strings, INVALID_ARGUMENT otherwise.
function newPointIds(ids, field) {
  return Array.from(ids, (id, i) => {
    const big = toBigInt(id);
    if (big === null || big < 0n || big >= (1n << 64n)) {
      throw new KinetriError({
        code: grpc.status.INVALID_ARGUMENT,
        details: `${field}[${i}] = ${id}: not an integer in 0 .. 2^64-1`});
    }
    return big.toString();
  });
}

// Interleaved x, y (null/undefined: none) as an Array of numbers, checked
// to hold numbers in pairs (the server checks that they are finite).
function coordinates(values, field) {
  const out = values == null ? [] : Array.from(values);
  for (let i = 0; i < out.length; i++) {
    if (typeof out[i] !== 'number') {
      throw new KinetriError({
        code: grpc.status.INVALID_ARGUMENT,
        details: `${field}[${i}]: ${typeof out[i]}, expected a number ` +
                 '(interleaved x, y)'});
    }
  }
  if (out.length % 2 !== 0) {
    throw new KinetriError({
      code: grpc.status.INVALID_ARGUMENT,
      details: `${field}: ${out.length} coordinates is odd (expected x, y ` +
               'pairs)'});
  }
  return out;
}

function wrap(promiseFn) {
  return new Promise((resolve, reject) => {
    promiseFn((err, value) => (err ? reject(new KinetriError(err))
                                   : resolve(value)));
  });
}

class StepStream {
  constructor(stub, session, firstStep, chunkValues = CHUNK_VALUES,
              clientIds = false) {
    this.chunkValues = chunkValues;
    this.clientIds = clientIds;
    this.session = session;
    this.nextStep = firstStep;
    this.call = stub.StreamSteps(route(session));
    this.pending = [];
    this.error = null;
    this.ended = false;
    this.call.on('data', (resp) => {
      const p = this.pending.shift();
      if (p) {
        p.resolve({step: Number(resp.step),
                   stats: resp.stats ? numbers(resp.stats) : resp.stats});
      }
    });
    this.call.on('error', (err) => {
      this.error = new KinetriError(err);
      this.ended = true;
      for (const p of this.pending.splice(0)) p.reject(this.error);
    });
    this.call.on('end', () => {
      this.ended = true;
      const err = this.error || new Error('step stream closed');
      for (const p of this.pending.splice(0)) p.reject(err);
    });
  }

  // deltas: Float64Array/Array of interleaved dx, dy; ids optional (sparse:
  // the client's ids on POINT_ID_POLICY_CLIENT sessions).
  // requestId (optional) names the step: resending a step the server
  // already applied under that name (its acknowledgement was lost, e.g. on
  // a new stream from openSteps(name, {firstStep})) returns the original
  // acknowledgement and applies nothing.
  // add, addIds, remove (optional): points that join and leave with the
  // step, see change(); the moves use the numbering before the step.
  moveBy(deltas, ids, options = {}) {
    return this.send('DISPLACEMENT_MODE_DELTA', deltas, ids, options);
  }
  moveTo(positions, ids, options = {}) {
    return this.send('DISPLACEMENT_MODE_ABSOLUTE', positions, ids, options);
  }

  // A step in which no point moves; points leave and join:
  //   remove: ids of the points that leave (sequential ids, or the client's
  //     ids on POINT_ID_POLICY_CLIENT sessions);
  //   add: interleaved x, y of the points that join;
  //   addIds: their client ids, one per point (POINT_ID_POLICY_CLIENT
  //     sessions need them, sequential sessions refuse them).
  // Moves apply first, then removals, then additions (a client id may leave
  // and join again in one step). Sequential sessions number the remaining
  // points 0.. again in their old order and the joining ones after them,
  // in the order given: stats.firstAddedId is the first one's id;
  // stats.pointCount is the session's point count after the step.
  change({add, addIds, remove, requestId = ''} = {}) {
    return this.send('DISPLACEMENT_MODE_DELTA', null, null,
                     {add, addIds, remove, requestId});
  }

  // The messages of one step, checked before anything is sent. Each
  // carries at most chunkValues / 2 entries: moves first, then the points
  // that leave, then those that join (each list split across messages as
  // needed); requestId on the first, endOfStep on the last.
  requests(mode, values, ids, {requestId = '', add, addIds, remove} = {}) {
    const xy = coordinates(
        values, mode === 'DISPLACEMENT_MODE_DELTA' ? 'deltas' : 'positions');
    const idList = ids == null ? null : pointIds(ids, this.clientIds);
    if (idList && 2 * idList.length !== xy.length) {
      throw new Error('one (x, y) pair per id');
    }
    const addXy = coordinates(add, 'add');
    const addIdList = addIds == null ? [] : newPointIds(addIds, 'addIds');
    if (this.clientIds) {
      if (2 * addIdList.length !== addXy.length) {
        throw new KinetriError({
          code: grpc.status.INVALID_ARGUMENT,
          details: `addIds: ${addIdList.length} ids for ${addXy.length / 2} ` +
                   'added points (POINT_ID_POLICY_CLIENT sessions name each ' +
                   'point)'});
      }
    } else if (addIdList.length > 0) {
      throw new KinetriError({
        code: grpc.status.INVALID_ARGUMENT,
        details: 'addIds: this session numbers points sequentially (joining ' +
                 'points are numbered after the others)'});
    }
    const removeList = remove == null ? [] :
      pointIds(remove, this.clientIds, 'remove');

    const head = () => ({session: this.session, step: this.nextStep, mode});
    const out = [{...head(), requestId}];
    const perMessage = Math.max(1, Math.floor(this.chunkValues / 2));
    let room = perMessage;
    const sections = [
      [xy.length / 2, (req, lo, hi) => {
        req.xy = xy.slice(2 * lo, 2 * hi);
        if (idList) {
          req[this.clientIds ? 'clientIds' : 'ids'] = idList.slice(lo, hi);
        }
      }],
      [removeList.length, (req, lo, hi) => {
        req[this.clientIds ? 'removeClientIds' : 'removeIds'] =
          removeList.slice(lo, hi);
      }],
      [addXy.length / 2, (req, lo, hi) => {
        req.addXy = addXy.slice(2 * lo, 2 * hi);
        if (this.clientIds) req.addClientIds = addIdList.slice(lo, hi);
      }],
    ];
    for (const [count, put] of sections) {
      for (let pos = 0; pos < count;) {
        if (room === 0) {
          out.push(head());
          room = perMessage;
        }
        const take = Math.min(room, count - pos);
        put(out[out.length - 1], pos, pos + take);
        pos += take;
        room -= take;
      }
    }
    out[out.length - 1].endOfStep = true;
    return out;
  }

  send(mode, values, ids, options = {}) {
    if (this.error) return Promise.reject(this.error);
    if (typeof options === 'string') options = {requestId: options};
    let reqs;
    try {
      reqs = this.requests(mode, values, ids, options);
    } catch (e) {
      return Promise.reject(e);
    }
    const result = new Promise((resolve, reject) => {
      this.pending.push({resolve, reject});
    });
    for (const req of reqs) this.call.write(req);
    this.nextStep += 1;
    return result;
  }

  // Ends the stream (resolves at once if the server already ended it).
  close() {
    return new Promise((resolve) => {
      if (this.ended) {
        resolve();
        return;
      }
      this.call.on('end', resolve);
      this.call.on('error', () => resolve());
      this.call.end();
    });
  }
}

function readPem(file, what) {
  try {
    return fs.readFileSync(file);
  } catch (e) {
    throw new Error(`${what}: cannot read ${file}: ${e.message}`);
  }
}

class Client {
  // chunkPoints: points per message when uploading (default 131072).
  // Security (docs/SECURITY.md): token (sent as a bearer token with every
  // call), ca (PEM CA bundle: TLS on), cert + key (client certificate,
  // mutual TLS), serverName (name expected in the server's certificate);
  // each defaults to KINETRI_TOKEN, KINETRI_CA, KINETRI_CERT, KINETRI_KEY,
  // KINETRI_TLS_SERVER_NAME. Unset: plaintext without a token.
  // deadlineSeconds: limit of every call but step streams (which live as
  // long as the simulation); 0: none. A call past it fails with
  // DEADLINE_EXCEEDED and the server stops its work.
  constructor(target = '127.0.0.1:50051', {
    chunkPoints = CHUNK_VALUES / 2,
    deadlineSeconds = 300,
    token = process.env.KINETRI_TOKEN || '',
    ca = process.env.KINETRI_CA || '',
    cert = process.env.KINETRI_CERT || '',
    key = process.env.KINETRI_KEY || '',
    serverName = process.env.KINETRI_TLS_SERVER_NAME || '',
  } = {}) {
    this.chunkValues = 2 * chunkPoints;
    this.deadlineSeconds = deadlineSeconds;
    const Service = loadService();
    const options = {'grpc.max_receive_message_length': 64 << 20};
    let credentials = grpc.credentials.createInsecure();
    if (ca || cert) {
      credentials = grpc.credentials.createSsl(
          ca ? readPem(ca, 'ca') : null, cert ? readPem(key, 'key') : null,
          cert ? readPem(cert, 'cert') : null);
      if (serverName) options['grpc.ssl_target_name_override'] = serverName;
    }
    if (token) {
      // On every call, streams included (an interceptor works on plaintext
      // channels too, unlike call credentials).
      options.interceptors = [(opts, nextCall) =>
        new grpc.InterceptingCall(nextCall(opts), {
          start(metadata, listener, next) {
            metadata.add('authorization', `Bearer ${token}`);
            next(metadata, listener);
          },
        })];
    }
    this.stub = new Service(target, credentials, options);
  }

  close() { this.stub.close(); }

  // Call options with the client's deadline.
  callOptions() {
    return this.deadlineSeconds > 0 ?
      {deadline: new Date(Date.now() + 1000 * this.deadlineSeconds)} : {};
  }

  // ids (optional): one distinct 64-bit id per point (BigInt, Number or
  // decimal string): a POINT_ID_POLICY_CLIENT session.
  async createSession(xy, sessionId = '', {ids, threads = 0} = {}) {
    const idList = ids ? pointIds(ids, true) : null;
    if (idList && 2 * idList.length !== xy.length) {
      throw new Error('one id per point');
    }
    const options = {threads, pointIdPolicy: idList ? 'POINT_ID_POLICY_CLIENT'
                                                     : 'POINT_ID_POLICY_SEQUENTIAL'};
    // Named here when the caller does not, so that a proxy routes the
    // creation by the same key as every later call (deploy/README.md).
    sessionId = sessionId || newSessionId();
    const s = await wrap((cb) => {
      const call = this.stub.CreateSession(route(sessionId), this.callOptions(),
                                           cb);
      call.write({header: {sessionId, pointCount: xy.length / 2, options}});
      for (let i = 0; i < xy.length; i += this.chunkValues) {
        const points = {xy: Array.from(xy.slice(i, i + this.chunkValues))};
        if (idList) points.ids = idList.slice(i / 2, (i + this.chunkValues) / 2);
        call.write({points});
      }
      call.end();
    });
    return toSession(s);
  }

  async getSession(name) {
    return toSession(await wrap((cb) => this.stub.GetSession({name}, route(name),
                                                    this.callOptions(), cb)));
  }

  // Every session, following the pages.
  async listSessions() {
    const out = [];
    let pageToken = '';
    do {
      const r = await wrap((cb) =>
        this.stub.ListSessions({pageSize: 100, pageToken},
                               this.callOptions(), cb));
      for (const s of r.sessions) out.push(toSession(s));
      pageToken = r.nextPageToken;
    } while (pageToken);
    return out;
  }

  async deleteSession(name) {
    if (this.policies) this.policies.delete(name);
    await wrap((cb) => this.stub.DeleteSession({name}, route(name),
                                               this.callOptions(), cb));
  }

  // firstStep (optional): the step number the stream starts at (default:
  // after the session's current step).
  async openSteps(name, {firstStep} = {}) {
    const s = await this.getSession(name);
    return new StepStream(this.stub, name,
                          firstStep === undefined ? s.step + 1 : firstStep,
                          this.chunkValues,
                          s.options.pointIdPolicy === 'POINT_ID_POLICY_CLIENT');
  }

  // Whether a session names its points with client ids (asked once).
  async usesClientIds(name) {
    if (!this.policies) this.policies = new Map();
    if (!this.policies.has(name)) {
      const s = await this.getSession(name);
      this.policies.set(name,
                        s.options.pointIdPolicy === 'POINT_ID_POLICY_CLIENT');
    }
    return this.policies.get(name);
  }

  async targets(req, session, positions, ids) {
    if (positions) {
      req.positions = {xy: Array.from(positions)};
    } else if (ids) {
      const client = await this.usesClientIds(session);
      req.pointIds = {[client ? 'clientIds' : 'ids']: pointIds(ids, client)};
    } else {
      req.allPoints = {};
    }
  }

  // Query, or StreamQuery when the targets (positions or ids) are more
  // than one message carries: the query with its first targets, then the
  // others chunkValues at a time.
  openQuery(request) {
    const per = this.chunkValues;
    const pos = request.positions && request.positions.xy;
    const pid = request.pointIds;
    const list = pos ? Array.from(pos)
                     : pid ? Array.from((pid.ids && pid.ids.length)
                                            ? pid.ids : (pid.clientIds || []))
                           : [];
    if (list.length <= per) {
      return this.stub.Query(request, route(request.session),
                             this.callOptions());
    }
    const field = pos ? 'xy' : ((pid.ids && pid.ids.length) ? 'ids'
                                                            : 'clientIds');
    const call = this.stub.StreamQuery(route(request.session),
                                       this.callOptions());
    for (let i = 0; i < list.length; i += per) {
      const part = list.slice(i, i + per);
      const msg = i === 0 ? {...request} : {};
      if (pos) {
        msg.positions = {xy: part};
      } else {
        msg.pointIds = {[field]: part};
      }
      call.write(msg);
    }
    call.end();
    return call;
  }

  query(request) {
    return new Promise((resolve, reject) => {
      const out = {step: 0, offsets: [0], ids: [], distances: [],
                   truncatedRows: [], clientIds: []};
      const call = this.openQuery(request);
      let continues = false;  // the last row goes on in this chunk
      let refused = false;
      const both = (fixed, varint) =>
        fixed && fixed.length > 0 && varint && varint.length > 0;
      call.on('data', (chunk) => {
        if (refused) return;
        // A field in both encodings is no answer a server writes: refused
        // (as the C++ client refuses it), the rest of the call cancelled.
        if (both(chunk.fixedOffsets, chunk.offsets) ||
            both(chunk.fixedIds, chunk.ids) ||
            both(chunk.fixedClientIds, chunk.clientIds)) {
          refused = true;
          reject(new KinetriError({
            code: grpc.status.INTERNAL,
            details: 'query answer: not a valid QueryResponse (offsets, ids ' +
                'or client ids both as varints and fixed-width)',
          }));
          call.cancel();
          return;
        }
        out.step = Number(chunk.step);
        // A row split across chunks: its end offset is replaced.
        if (continues) out.offsets.pop();
        continues = chunk.lastRowContinues;
        const base = out.ids.length + out.clientIds.length;
        const row0 = out.offsets.length - 1;
        // Offsets and ids in their varint fields or, for requests with
        // encoding ANSWER_ENCODING_FIXED, in the fixed-width ones.
        const pick = (fixed, varint) =>
          (fixed && fixed.length) ? fixed : (varint || []);
        const offsets = pick(chunk.fixedOffsets, chunk.offsets);
        for (let i = 1; i < offsets.length; i++) {
          out.offsets.push(base + Number(offsets[i]));
        }
        for (const id of pick(chunk.fixedIds, chunk.ids)) out.ids.push(id);
        for (const id of pick(chunk.fixedClientIds, chunk.clientIds)) {
          out.clientIds.push(BigInt(id));
        }
        for (const d of chunk.distances) out.distances.push(d);
        for (const r of chunk.truncatedRows) {
          out.truncatedRows.push(row0 + Number(r));
        }
      });
      call.on('error', (err) => reject(new KinetriError(err)));
      call.on('end', () => resolve({
        step: out.step,
        offsets: Float64Array.from(out.offsets),
        ids: Uint32Array.from(out.ids),
        distances: Float64Array.from(out.distances),
        truncatedRows: Float64Array.from(out.truncatedRows),
        clientIds: BigUint64Array.from(out.clientIds),
      }));
    });
  }

  nearestAll(session) {
    return this.query({session, kind: 'QUERY_KIND_NEAREST', excludeSelf: true,
                       includeDistances: true, allPoints: {}});
  }

  // Targets: positions (interleaved x, y), ids (client ids on
  // POINT_ID_POLICY_CLIENT sessions) or, when neither, all points.
  async kNearest(session, k, {positions, ids, excludeSelf = true} = {}) {
    const req = {session, kind: 'QUERY_KIND_K_NEAREST', k, excludeSelf,
                 includeDistances: true};
    await this.targets(req, session, positions, ids);
    return this.query(req);
  }

  async radius(session, r,
               {positions, ids, excludeSelf = true, maxPerRow = 0} = {}) {
    const req = {session, kind: 'QUERY_KIND_RADIUS', radius: r, excludeSelf,
                 includeDistances: true, maxResultsPerRow: maxPerRow};
    await this.targets(req, session, positions, ids);
    return this.query(req);
  }

  exportTriangulation(session) {
    return new Promise((resolve, reject) => {
      // pointIds: the client ids of the positions (client-id sessions).
      const out = {step: 0, xy: [], triangles: [], pointIds: []};
      const call = this.stub.ExportTriangulation({session}, route(session),
                                                 this.callOptions());
      call.on('data', (c) => {
        out.step = Number(c.step);
        for (const v of c.xy) out.xy.push(v);
        for (const v of c.triangles) out.triangles.push(v);
        for (const v of c.pointIds) out.pointIds.push(BigInt(v));
      });
      call.on('error', (err) => reject(new KinetriError(err)));
      call.on('end', () => resolve({
        step: out.step,
        xy: Float64Array.from(out.xy),
        triangles: Uint32Array.from(out.triangles),
        pointIds: BigUint64Array.from(out.pointIds),
      }));
    });
  }
}

module.exports = {Client, StepStream, KinetriError, SESSION_HEADER,
                  newSessionId, status: grpc.status};
