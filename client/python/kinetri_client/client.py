"""Idiomatic wrapper over the generated gRPC stubs."""

import collections
import os
import re
import secrets
from dataclasses import dataclass
from typing import Iterator, List, Optional, Sequence

import grpc
import numpy as np

from kinetri.v1 import kinetri_pb2 as pb
from kinetri.v1 import kinetri_pb2_grpc as pb_grpc

_CHUNK_POINTS = 131072  # 2 MiB of coordinates per message


class KinetriError(Exception):
    """A failed call: `code` is the grpc.StatusCode, str() the message."""

    def __init__(self, code: grpc.StatusCode, message: str):
        super().__init__(f"{code.name}: {message}")
        self.code = code
        self.message = message


def _raise(err: grpc.RpcError):
    raise KinetriError(err.code(), err.details()) from None


def _point_ids(ids, client: bool, field: str = "ids") -> np.ndarray:
    """Point ids as sent: uint64 client ids, or sequential ids checked to
    exist in uint32 range (a larger id never wraps onto another point)."""
    a = np.asarray(ids)
    if a.ndim != 1:
        raise ValueError(f"{field} must be one-dimensional")
    if a.size and not np.issubdtype(a.dtype, np.integer):
        raise ValueError(f"{field} must be integers")
    if client:
        if a.size and np.issubdtype(a.dtype, np.signedinteger) and a.min() < 0:
            i = int(np.argmax(a < 0))
            raise KinetriError(grpc.StatusCode.NOT_FOUND,
                               f"{field}[{i}] = {a[i]}: no such point")
        return a.astype(np.uint64)
    if a.size:
        bad = (a < 0) | (a > np.iinfo(np.uint32).max) if \
            np.issubdtype(a.dtype, np.signedinteger) else \
            (a > np.iinfo(np.uint32).max)
        if bad.any():
            i = int(np.argmax(bad))
            raise KinetriError(grpc.StatusCode.NOT_FOUND,
                               f"{field}[{i}] = {a[i]}: no such point")
    return a.astype(np.uint32)


def _xy(points) -> np.ndarray:
    a = np.ascontiguousarray(points, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 2:
        raise ValueError(f"points must have shape (n, 2), got {a.shape}")
    return a.reshape(-1)


@dataclass
class Neighbors:
    """CSR rows: neighbours of row i are ids[offsets[i]:offsets[i+1]]."""

    step: int
    offsets: np.ndarray
    ids: np.ndarray
    distances: np.ndarray
    truncated_rows: np.ndarray
    # Sessions with client ids (POINT_ID_POLICY_CLIENT): neighbours as the
    # client's uint64 ids; `ids` is then empty.
    client_ids: np.ndarray

    def row(self, i: int) -> np.ndarray:
        ids = self.client_ids if len(self.client_ids) else self.ids
        return ids[self.offsets[i]:self.offsets[i + 1]]

    def __len__(self) -> int:
        return len(self.offsets) - 1


class Export(tuple):
    """(step, positions, triangles), unpackable as before, with .ids."""

    def __new__(cls, step, positions, triangles, ids):
        obj = super().__new__(cls, (step, positions, triangles))
        obj.step, obj.positions, obj.triangles, obj.ids = (
            step, positions, triangles, ids)
        return obj


class StepStream:
    """One long-lived stream; each call applies one step and returns its stats."""

    def __init__(self, stub, session: str, first_step: int,
                 chunk_points: int = _CHUNK_POINTS, client_ids: bool = False):
        self._chunk_points = chunk_points
        self._client_ids = client_ids
        self._session = session
        self._next = first_step
        self._requests: List[pb.StepRequest] = []
        self._queue = _RequestQueue()
        self._responses = stub.StreamSteps(iter(self._queue),
                                           metadata=_route(session))

    @property
    def next_step(self) -> int:
        return self._next

    def move_by(self, deltas, ids: Optional[Sequence[int]] = None):
        """Moves points by (n, 2) deltas: all points in id order, or the
        points named by `ids` (the client's ids on POINT_ID_POLICY_CLIENT
        sessions)."""
        return self._send(pb.DISPLACEMENT_MODE_DELTA, deltas, ids)

    def move_to(self, positions, ids: Optional[Sequence[int]] = None):
        return self._send(pb.DISPLACEMENT_MODE_ABSOLUTE, positions, ids)

    def _send(self, mode, values, ids):
        flat = _xy(values)
        id_arr = None if ids is None else _point_ids(ids, self._client_ids)
        if id_arr is not None and 2 * len(id_arr) != len(flat):
            raise ValueError("one (x, y) pair per id")
        step = 2 * self._chunk_points
        start = 0
        while True:
            end = min(len(flat), start + step)
            req = pb.StepRequest(session=self._session, step=self._next,
                                 mode=mode, end_of_step=end == len(flat))
            req.xy.extend(flat[start:end].tolist())
            if id_arr is not None:
                part = id_arr[start // 2:end // 2].tolist()
                if self._client_ids:
                    req.client_ids.extend(part)
                else:
                    req.ids.extend(part)
            self._queue.put(req)
            start = end
            if start >= len(flat):
                break
        try:
            resp = next(self._responses)
        except grpc.RpcError as e:
            _raise(e)
        self._next += 1
        return resp

    def close(self):
        self._queue.close()
        try:
            for _ in self._responses:
                pass
        except grpc.RpcError as e:
            if e.code() != grpc.StatusCode.CANCELLED:
                _raise(e)


class _RequestQueue:
    """Blocking iterator feeding a request stream."""

    def __init__(self):
        import queue
        self._q = queue.Queue()

    def put(self, item):
        self._q.put(item)

    def close(self):
        self._q.put(None)

    def __iter__(self) -> Iterator:
        while True:
            item = self._q.get()
            if item is None:
                return
            yield item


class _BearerToken(grpc.UnaryUnaryClientInterceptor,
                   grpc.UnaryStreamClientInterceptor,
                   grpc.StreamUnaryClientInterceptor,
                   grpc.StreamStreamClientInterceptor):
    """Adds `authorization: Bearer TOKEN` to every call."""

    def __init__(self, token: str):
        self._md = ("authorization", "Bearer " + token)

    def _details(self, d):
        md = list(d.metadata or []) + [self._md]
        return _CallDetails(d.method, d.timeout, md, d.credentials,
                            getattr(d, "wait_for_ready", None),
                            getattr(d, "compression", None))

    def intercept_unary_unary(self, cont, d, req):
        return cont(self._details(d), req)

    def intercept_unary_stream(self, cont, d, req):
        return cont(self._details(d), req)

    def intercept_stream_unary(self, cont, d, it):
        return cont(self._details(d), it)

    def intercept_stream_stream(self, cont, d, it):
        return cont(self._details(d), it)


class _CallDetails(
        collections.namedtuple(
            "_CallDetails", ("method", "timeout", "metadata", "credentials",
                             "wait_for_ready", "compression")),
        grpc.ClientCallDetails):
    pass


#: Every call about one session carries its id in this header, so that a
#: proxy in front of several servers (HAProxy hashing the header,
#: deploy/proxy/haproxy.cfg) sends all of a session's calls to its owner.
SESSION_HEADER = "kinetri-session"
_SESSION_ID = re.compile(r"[a-z0-9-]{1,63}")


def _route(session: str):
    """Call metadata routing a call to the owner of `session` (a name
    "sessions/{id}" or an id)."""
    key = session[len("sessions/"):] if session.startswith("sessions/") \
        else session
    # Only what can be a session id: the server refuses anything else, and
    # a huge name must not become a huge header.
    if not _SESSION_ID.fullmatch(key):
        return ()
    return ((SESSION_HEADER, key),)


def new_session_id() -> str:
    """A new session id as the server would make one: "s-" + 128 random
    bits in hex."""
    return "s-" + secrets.token_hex(16)


def _read(path: str, what: str) -> bytes:
    try:
        with open(path, "rb") as f:
            return f.read()
    except OSError as e:
        raise KinetriError(grpc.StatusCode.FAILED_PRECONDITION,
                           f"{what}: cannot read {path}: {e.strerror}")


class Client:
    """Connects to a kinetri-server at `target` ("host:port").

    Security (docs/SECURITY.md): `token` is sent as a bearer token with every
    call; `ca` (a PEM CA bundle) turns TLS on; `cert` and `key` add a client
    certificate (mutual TLS); `server_name` overrides the name expected in
    the server's certificate. Each defaults to its environment variable
    (KINETRI_TOKEN, KINETRI_CA, KINETRI_CERT, KINETRI_KEY,
    KINETRI_TLS_SERVER_NAME); unset means plaintext without a token.
    """

    def __init__(self, target: str = "127.0.0.1:50051",
                 chunk_points: int = _CHUNK_POINTS, *,
                 token: Optional[str] = None, ca: Optional[str] = None,
                 cert: Optional[str] = None, key: Optional[str] = None,
                 server_name: Optional[str] = None):
        env = os.environ.get
        token = token if token is not None else env("KINETRI_TOKEN", "")
        ca = ca if ca is not None else env("KINETRI_CA", "")
        cert = cert if cert is not None else env("KINETRI_CERT", "")
        key = key if key is not None else env("KINETRI_KEY", "")
        server_name = (server_name if server_name is not None
                       else env("KINETRI_TLS_SERVER_NAME", ""))
        self._chunk_points = chunk_points
        options = [("grpc.max_receive_message_length", 64 << 20)]
        if ca or cert:
            creds = grpc.ssl_channel_credentials(
                root_certificates=_read(ca, "ca") if ca else None,
                private_key=_read(key, "key") if cert else None,
                certificate_chain=_read(cert, "cert") if cert else None)
            if server_name:
                options.append(("grpc.ssl_target_name_override", server_name))
            self._channel = grpc.secure_channel(target, creds, options=options)
        else:
            self._channel = grpc.insecure_channel(target, options=options)
        channel = self._channel
        if token:
            channel = grpc.intercept_channel(channel, _BearerToken(token))
        self._stub = pb_grpc.KinetriServiceStub(channel)
        self._policy = {}  # session name -> uses client ids

    def close(self):
        self._channel.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # Sessions -------------------------------------------------------------
    def create_session(self, points, session_id: str = "",
                       threads: int = 0, ids=None) -> pb.Session:
        """ids: optional distinct uint64 per point (POINT_ID_POLICY_CLIENT)."""
        flat = _xy(points)
        id_arr = None if ids is None else np.asarray(ids, dtype=np.uint64)
        if id_arr is not None and 2 * len(id_arr) != len(flat):
            raise ValueError("one id per point")
        policy = (pb.POINT_ID_POLICY_CLIENT if id_arr is not None
                  else pb.POINT_ID_POLICY_SEQUENTIAL)

        # Named here when the caller does not, so that a proxy routes the
        # creation by the same key as every later call (deploy/README.md).
        session_id = session_id or new_session_id()

        def requests():
            yield pb.CreateSessionRequest(header=pb.CreateSessionHeader(
                session_id=session_id, point_count=len(flat) // 2,
                options=pb.SessionOptions(threads=threads,
                                          point_id_policy=policy)))
            step = 2 * self._chunk_points
            for i in range(0, len(flat), step):
                chunk = pb.PointChunk(xy=flat[i:i + step].tolist())
                if id_arr is not None:
                    chunk.ids.extend(id_arr[i // 2:(i + step) // 2].tolist())
                yield pb.CreateSessionRequest(points=chunk)

        try:
            return self._stub.CreateSession(requests(),
                                            metadata=_route(session_id))
        except grpc.RpcError as e:
            _raise(e)

    def get_session(self, name: str) -> pb.Session:
        try:
            return self._stub.GetSession(pb.GetSessionRequest(name=name),
                                         metadata=_route(name))
        except grpc.RpcError as e:
            _raise(e)

    def list_sessions(self) -> List[pb.Session]:
        out, token = [], ""
        while True:
            try:
                resp = self._stub.ListSessions(
                    pb.ListSessionsRequest(page_size=100, page_token=token))
            except grpc.RpcError as e:
                _raise(e)
            out.extend(resp.sessions)
            token = resp.next_page_token
            if not token:
                return out

    def delete_session(self, name: str) -> None:
        self._policy.pop(name, None)
        try:
            self._stub.DeleteSession(pb.DeleteSessionRequest(name=name),
                                     metadata=_route(name))
        except grpc.RpcError as e:
            _raise(e)

    def open_steps(self, name: str) -> StepStream:
        s = self.get_session(name)
        return StepStream(self._stub, name, s.step + 1, self._chunk_points,
                          s.options.point_id_policy ==
                          pb.POINT_ID_POLICY_CLIENT)

    def _uses_client_ids(self, name: str) -> bool:
        """The session's id policy (asked once per session name)."""
        if name not in self._policy:
            self._policy[name] = (self.get_session(name).options.point_id_policy
                                  == pb.POINT_ID_POLICY_CLIENT)
        return self._policy[name]

    # Queries ----------------------------------------------------------------
    def query(self, request: pb.QueryRequest) -> Neighbors:
        offsets, ids, dists, trunc = [np.zeros(1, np.uint64)], [], [], []
        cids = []
        step, base, rows = 0, 0, 0
        try:
            for chunk in self._stub.Query(request,
                                          metadata=_route(request.session)):
                step = chunk.step
                off = np.asarray(chunk.offsets, dtype=np.uint64)
                offsets.append(off[1:] + base)
                ids.append(np.asarray(chunk.ids, dtype=np.uint32))
                cids.append(np.asarray(chunk.client_ids, dtype=np.uint64))
                dists.append(np.asarray(chunk.distances, dtype=np.float64))
                trunc.append(np.asarray(chunk.truncated_rows, np.uint64) + rows)
                base += len(chunk.ids) + len(chunk.client_ids)
                rows += len(off) - 1
        except grpc.RpcError as e:
            _raise(e)
        cat = np.concatenate
        return Neighbors(step, cat(offsets), cat(ids) if ids else
                         np.zeros(0, np.uint32),
                         cat(dists) if dists else np.zeros(0),
                         cat(trunc) if trunc else np.zeros(0, np.uint64),
                         cat(cids) if cids else np.zeros(0, np.uint64))

    def nearest_all(self, name: str) -> Neighbors:
        return self.query(pb.QueryRequest(
            session=name, kind=pb.QUERY_KIND_NEAREST, exclude_self=True,
            include_distances=True, all_points=pb.AllPoints()))

    def knn(self, name: str, k: int, points=None, ids=None,
            exclude_self: bool = True) -> Neighbors:
        req = pb.QueryRequest(session=name, kind=pb.QUERY_KIND_K_NEAREST, k=k,
                              include_distances=True,
                              exclude_self=exclude_self)
        self._targets(req, name, points, ids)
        return self.query(req)

    def radius(self, name: str, r: float, points=None, ids=None,
               exclude_self: bool = True, max_per_row: int = 0) -> Neighbors:
        req = pb.QueryRequest(session=name, kind=pb.QUERY_KIND_RADIUS,
                              radius=r, include_distances=True,
                              exclude_self=exclude_self,
                              max_results_per_row=max_per_row)
        self._targets(req, name, points, ids)
        return self.query(req)

    def _targets(self, req, name, points, ids):
        """Query targets: positions, point ids (the client's ids on
        POINT_ID_POLICY_CLIENT sessions) or all points."""
        if points is not None:
            req.positions.xy.extend(_xy(points).tolist())
        elif ids is not None:
            client = self._uses_client_ids(name)
            arr = _point_ids(ids, client).tolist()
            if client:
                req.point_ids.client_ids.extend(arr)
            else:
                req.point_ids.ids.extend(arr)
        else:
            req.all_points.SetInParent()

    def export(self, name: str) -> "Export":
        """Returns (step, positions (n, 2), triangles (m, 3)); the result
        also has .ids: each position's id (the client's uint64 ids on
        POINT_ID_POLICY_CLIENT sessions, else 0..n-1)."""
        xy, tris, pids, step = [], [], [], 0
        try:
            for chunk in self._stub.ExportTriangulation(
                    pb.ExportTriangulationRequest(session=name),
                    metadata=_route(name)):
                step = chunk.step
                xy.append(np.asarray(chunk.xy, dtype=np.float64))
                tris.append(np.asarray(chunk.triangles, dtype=np.uint32))
                pids.append(np.asarray(chunk.point_ids, dtype=np.uint64))
        except grpc.RpcError as e:
            _raise(e)
        positions = np.concatenate(xy).reshape(-1, 2)
        ids = np.concatenate(pids) if pids else np.zeros(0, np.uint64)
        if len(ids) != len(positions):
            ids = np.arange(len(positions), dtype=np.uint64)
        return Export(step, positions, np.concatenate(tris).reshape(-1, 3),
                      ids)
