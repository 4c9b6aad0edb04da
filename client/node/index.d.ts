// Type declarations of @kinetri/client (index.js). Checked by `tsc` in
// client/node/test_package.sh.
import {status as grpcStatus} from '@grpc/grpc-js';

/** Interleaved x, y coordinates. */
export type Coordinates = Float64Array | ArrayLike<number>;
/**
 * Point ids: sequential ids (numbers in [0, 2^32)) or, on
 * POINT_ID_POLICY_CLIENT sessions, the client's 64-bit ids.
 */
export type PointId = bigint | number | string;

export interface ClientOptions {
  /** Points per message when uploading (default 131072). */
  chunkPoints?: number;
  /** Limit of every call but step streams, in seconds (default 300; 0: none). */
  deadlineSeconds?: number;
  /** Bearer token sent with every call (default: $KINETRI_TOKEN). */
  token?: string;
  /** PEM CA bundle file: TLS on (default: $KINETRI_CA). */
  ca?: string;
  /** PEM client certificate file, mutual TLS (default: $KINETRI_CERT). */
  cert?: string;
  /** Its private key file (default: $KINETRI_KEY). */
  key?: string;
  /** Name expected in the server's certificate (default: $KINETRI_TLS_SERVER_NAME). */
  serverName?: string;
}

export interface Timestamp {
  seconds: string;
  nanos: number;
}

export interface SessionOptions {
  threads: number;
  pointIdPolicy: 'POINT_ID_POLICY_SEQUENTIAL' | 'POINT_ID_POLICY_CLIENT' |
      'POINT_ID_POLICY_UNSPECIFIED';
  [field: string]: unknown;
}

export interface Session {
  /** "sessions/{id}" */
  name: string;
  options: SessionOptions;
  /** "cpu", "cuda" or "emulated". */
  backend: string;
  pointCount: number;
  siteCount: number;
  /** The last applied step; 0 right after creation. */
  step: number;
  createTime: Timestamp | null;
  updateTime: Timestamp | null;
  expireTime: Timestamp | null;
  [field: string]: unknown;
}

export interface StepStats {
  /** "local", "subdivided", "reinserted", "rebuilt" or "noop". */
  path: string;
  movedPoints: number;
  substeps: number;
  reinserted: number;
  interiorFixFlips: number;
  hullAbsorbFlips: number;
  hullReleaseFlips: number;
  delaunayFlips: number;
  fallbackReason: string;
  updateSeconds: number;
  /** Points that left with this step. */
  removedPoints: number;
  /** Points that joined with this step. */
  addedPoints: number;
  /** The session's point count after the step. */
  pointCount: number;
  /**
   * Sequential sessions: id of the first joining point (the others follow
   * in the order sent); 0 when none joined and on client-id sessions.
   */
  firstAddedId: number;
}

export interface StepAck {
  step: number;
  stats: StepStats;
}

/** Query results in CSR form: row i is [offsets[i], offsets[i + 1]). */
export interface Neighbors {
  /** The step that answered. */
  step: number;
  offsets: Float64Array;
  /** Neighbours (sequential ids); empty on client-id sessions. */
  ids: Uint32Array;
  /** Neighbours as client ids (POINT_ID_POLICY_CLIENT sessions). */
  clientIds: BigUint64Array;
  distances: Float64Array;
  /** Rows cut by maxPerRow. */
  truncatedRows: Float64Array;
}

export interface Mesh {
  step: number;
  /** Interleaved positions, by id. */
  xy: Float64Array;
  /** Index triples, counter-clockwise. */
  triangles: Uint32Array;
  /** Client ids of the positions (client-id sessions), else empty. */
  pointIds: BigUint64Array;
}

export interface Targets {
  /** Query positions (interleaved x, y). */
  positions?: Coordinates;
  /** Query the points with these ids. Neither: all points. */
  ids?: Iterable<PointId>;
  /** Leave the queried point out of its own row (default true). */
  excludeSelf?: boolean;
}

/** Points that leave and join with a step (StepStream.change, moveBy, moveTo). */
export interface PointChanges {
  /** Positions of the points that join (interleaved x, y). */
  add?: Coordinates | null;
  /**
   * Client ids of the joining points, one per point: required on
   * POINT_ID_POLICY_CLIENT sessions, refused on sequential ones (which
   * number joining points after the remaining ones).
   */
  addIds?: Iterable<PointId> | null;
  /** Ids of the points that leave (client ids on POINT_ID_POLICY_CLIENT sessions). */
  remove?: Iterable<PointId> | null;
}

export interface StepOptions extends PointChanges {
  /**
   * Names the step: resending a step already applied under it returns the
   * original acknowledgement and applies nothing.
   */
  requestId?: string;
}

/** A failed call: `code` is a gRPC status code (see `status`). */
export class KinetriError extends Error {
  code: number;
}

/** One long-lived stream; each call applies one step. */
export class StepStream {
  readonly session: string;
  nextStep: number;
  /**
   * Moves points by interleaved deltas: all, or those named by `ids` (the
   * numbering before the step). `requestId` names the step: resending a
   * step already applied under it returns the original acknowledgement and
   * applies nothing. `add`, `addIds`, `remove`: points that join and leave
   * with the step (see change).
   */
  moveBy(deltas: Coordinates, ids?: Iterable<PointId> | null,
         options?: StepOptions): Promise<StepAck>;
  /** Moves points to absolute positions: all, or those named by `ids`. */
  moveTo(positions: Coordinates, ids?: Iterable<PointId> | null,
         options?: StepOptions): Promise<StepAck>;
  /**
   * A step in which no point moves; points leave (`remove`) and join
   * (`add`, with `addIds` on client-id sessions). Removals apply before
   * additions. Sequential sessions number the remaining points 0.. again
   * in their old order and the joining ones after them
   * (`stats.firstAddedId`); client ids never change.
   */
  change(changes?: StepOptions): Promise<StepAck>;
  close(): Promise<void>;
}

export class Client {
  constructor(target?: string, options?: ClientOptions);
  close(): void;
  /**
   * Creates a session; an empty `sessionId` gets newSessionId(). `ids`:
   * one distinct 64-bit id per point (a POINT_ID_POLICY_CLIENT session).
   */
  createSession(xy: Coordinates, sessionId?: string,
                options?: {ids?: Iterable<PointId>, threads?: number}):
      Promise<Session>;
  getSession(name: string): Promise<Session>;
  /** Every session of the server (behind a proxy: of one replica). */
  listSessions(): Promise<Session[]>;
  deleteSession(name: string): Promise<void>;
  /** A step stream after the current step, or at `firstStep`. */
  openSteps(name: string, options?: {firstStep?: number}): Promise<StepStream>;
  nearestAll(session: string): Promise<Neighbors>;
  kNearest(session: string, k: number, targets?: Targets): Promise<Neighbors>;
  radius(session: string, r: number, targets?: Targets & {maxPerRow?: number}):
      Promise<Neighbors>;
  exportTriangulation(session: string): Promise<Mesh>;
}

/** The header naming the session of a call (what a proxy hashes). */
export const SESSION_HEADER: 'kinetri-session';
/** "s-" + 128 random bits in hex, as the server names sessions. */
export function newSessionId(): string;
export const status: typeof grpcStatus;
