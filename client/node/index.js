// Node.js client for the Kinetri proximity service (kinetri.v1).
//
// Positions are Float64Arrays of interleaved x, y; query results come back in
// CSR form ({step, offsets, ids, distances}). Chunking is hidden.
'use strict';

const path = require('path');
const grpc = require('@grpc/grpc-js');
const protoLoader = require('@grpc/proto-loader');

const PROTO = path.join(__dirname, '..', '..', 'proto', 'kinetri', 'v1',
                        'kinetri.proto');
const CHUNK_VALUES = 2 * 131072;

function loadService() {
  const def = protoLoader.loadSync(PROTO, {
    keepCase: false, longs: Number, enums: String, defaults: true,
    oneofs: true, includeDirs: [path.join(__dirname, '..', '..', 'proto')],
  });
  return grpc.loadPackageDefinition(def).kinetri.v1.KinetriService;
}

class KinetriError extends Error {
  constructor(err) {
    super(err.details || err.message);
    this.code = err.code;  // grpc.status value
  }
}

function wrap(promiseFn) {
  return new Promise((resolve, reject) => {
    promiseFn((err, value) => (err ? reject(new KinetriError(err))
                                   : resolve(value)));
  });
}

class StepStream {
  constructor(stub, session, firstStep, chunkValues = CHUNK_VALUES) {
    this.chunkValues = chunkValues;
    this.session = session;
    this.nextStep = firstStep;
    this.call = stub.StreamSteps();
    this.pending = [];
    this.error = null;
    this.call.on('data', (resp) => {
      const p = this.pending.shift();
      if (p) p.resolve(resp);
    });
    this.call.on('error', (err) => {
      this.error = new KinetriError(err);
      for (const p of this.pending.splice(0)) p.reject(this.error);
    });
    this.call.on('end', () => {
      const err = this.error || new Error('step stream closed');
      for (const p of this.pending.splice(0)) p.reject(err);
    });
  }

  // deltas: Float64Array/Array of interleaved dx, dy; ids optional (sparse).
  moveBy(deltas, ids) { return this.send('DISPLACEMENT_MODE_DELTA', deltas, ids); }
  moveTo(positions, ids) {
    return this.send('DISPLACEMENT_MODE_ABSOLUTE', positions, ids);
  }

  send(mode, values, ids) {
    if (this.error) return Promise.reject(this.error);
    const xy = Array.from(values);
    const result = new Promise((resolve, reject) => {
      this.pending.push({resolve, reject});
    });
    for (let i = 0; ; i += this.chunkValues) {
      const end = Math.min(xy.length, i + this.chunkValues);
      const req = {session: this.session, step: this.nextStep, mode,
                   xy: xy.slice(i, end), endOfStep: end === xy.length};
      if (ids) req.ids = Array.from(ids).slice(i / 2, end / 2);
      this.call.write(req);
      if (end >= xy.length) break;
    }
    this.nextStep += 1;
    return result;
  }

  close() {
    return new Promise((resolve) => {
      this.call.on('end', resolve);
      this.call.on('error', () => resolve());
      this.call.end();
    });
  }
}

class Client {
  // chunkPoints: points per message when uploading (default 131072).
  constructor(target = '127.0.0.1:50051', {chunkPoints = CHUNK_VALUES / 2} = {}) {
    this.chunkValues = 2 * chunkPoints;
    const Service = loadService();
    this.stub = new Service(target, grpc.credentials.createInsecure(), {
      'grpc.max_receive_message_length': 64 << 20,
    });
  }

  close() { this.stub.close(); }

  createSession(xy, sessionId = '') {
    return wrap((cb) => {
      const call = this.stub.CreateSession(cb);
      call.write({header: {sessionId, pointCount: xy.length / 2, options: {}}});
      for (let i = 0; i < xy.length; i += this.chunkValues) {
        call.write({points: {xy: Array.from(xy.slice(i, i + this.chunkValues))}});
      }
      call.end();
    });
  }

  getSession(name) { return wrap((cb) => this.stub.GetSession({name}, cb)); }
  deleteSession(name) {
    return wrap((cb) => this.stub.DeleteSession({name}, cb));
  }

  async openSteps(name) {
    const s = await this.getSession(name);
    return new StepStream(this.stub, name, s.step + 1, this.chunkValues);
  }

  query(request) {
    return new Promise((resolve, reject) => {
      const out = {step: 0, offsets: [0], ids: [], distances: [],
                   truncatedRows: []};
      const call = this.stub.Query(request);
      call.on('data', (chunk) => {
        out.step = chunk.step;
        const base = out.ids.length;
        const row0 = out.offsets.length - 1;
        for (let i = 1; i < chunk.offsets.length; i++) {
          out.offsets.push(base + chunk.offsets[i]);
        }
        for (const id of chunk.ids) out.ids.push(id);
        for (const d of chunk.distances) out.distances.push(d);
        for (const r of chunk.truncatedRows) out.truncatedRows.push(row0 + r);
      });
      call.on('error', (err) => reject(new KinetriError(err)));
      call.on('end', () => resolve(out));
    });
  }

  nearestAll(session) {
    return this.query({session, kind: 'QUERY_KIND_NEAREST', excludeSelf: true,
                       includeDistances: true, allPoints: {}});
  }

  kNearest(session, k, {positions, ids, excludeSelf = true} = {}) {
    const req = {session, kind: 'QUERY_KIND_K_NEAREST', k, excludeSelf,
                 includeDistances: true};
    if (positions) req.positions = {xy: Array.from(positions)};
    else if (ids) req.pointIds = {ids: Array.from(ids)};
    else req.allPoints = {};
    return this.query(req);
  }

  radius(session, r, {positions, ids, excludeSelf = true, maxPerRow = 0} = {}) {
    const req = {session, kind: 'QUERY_KIND_RADIUS', radius: r, excludeSelf,
                 includeDistances: true, maxResultsPerRow: maxPerRow};
    if (positions) req.positions = {xy: Array.from(positions)};
    else if (ids) req.pointIds = {ids: Array.from(ids)};
    else req.allPoints = {};
    return this.query(req);
  }

  exportTriangulation(session) {
    return new Promise((resolve, reject) => {
      const out = {step: 0, xy: [], triangles: []};
      const call = this.stub.ExportTriangulation({session});
      call.on('data', (c) => {
        out.step = c.step;
        for (const v of c.xy) out.xy.push(v);
        for (const v of c.triangles) out.triangles.push(v);
      });
      call.on('error', (err) => reject(new KinetriError(err)));
      call.on('end', () => resolve(out));
    });
  }
}

module.exports = {Client, StepStream, KinetriError, status: grpc.status};
