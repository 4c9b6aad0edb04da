"""What the synchronous and the asyncio clients share: arguments checked and
turned into requests, streamed answers put back together, channel set-up.
No calls are made here."""

import json
import os
import re
import secrets
from dataclasses import dataclass
from typing import Callable, Dict, Iterator, List, Optional, Sequence, Tuple

import grpc
import numpy as np

try:  # installed package: stubs generated into kinetri_client/_pb
    from kinetri_client._pb import kinetri_pb2 as pb
    from kinetri_client._pb import kinetri_pb2_grpc as pb_grpc
except ImportError:  # source tree: stubs from CMake (build/client/python/gen)
    from kinetri.v1 import kinetri_pb2 as pb  # type: ignore[no-redef]
    from kinetri.v1 import kinetri_pb2_grpc as pb_grpc  # type: ignore

CHUNK_POINTS = 131072  # 2 MiB of coordinates per message
#: Default limit of every call but step streams, in seconds.
DEFAULT_DEADLINE = 300.0

#: Every call about one session carries its id in this header, so that a
#: proxy in front of several servers (HAProxy hashing the header,
#: deploy/proxy/haproxy.cfg) sends all of a session's calls to its owner.
SESSION_HEADER = "kinetri-session"
_SESSION_ID = re.compile(r"[a-z0-9-]{1,63}")

Metadata = Tuple[Tuple[str, str], ...]


class KinetriError(Exception):
    """A failed call: `code` is the grpc.StatusCode, str() the message."""

    def __init__(self, code: grpc.StatusCode, message: str):
        super().__init__(f"{code.name}: {message}")
        self.code = code
        self.message = message


def raise_from(err: grpc.RpcError):
    raise KinetriError(err.code(), err.details()) from None


def new_session_id() -> str:
    """A new session id as the server would make one: "s-" + 128 random
    bits in hex."""
    return "s-" + secrets.token_hex(16)


def route(session: str) -> Metadata:
    """Call metadata routing a call to the owner of `session` (a name
    "sessions/{id}" or an id)."""
    key = session[len("sessions/"):] if session.startswith("sessions/") \
        else session
    # Only what can be a session id: the server refuses anything else, and
    # a huge name must not become a huge header.
    if not _SESSION_ID.fullmatch(key):
        return ()
    return ((SESSION_HEADER, key),)


def point_ids(ids, client: bool, field: str = "ids") -> np.ndarray:
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


def flat_xy(points, field: str = "points") -> np.ndarray:
    """(n, 2) positions or deltas as one float64 array x0, y0, x1, ..."""
    a = np.ascontiguousarray(points, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 2:
        raise ValueError(f"{field} must have shape (n, 2), got {a.shape}")
    return a.reshape(-1)


def optional_xy(points, field: str) -> np.ndarray:
    """flat_xy, with None or an empty array-like (such as []) meaning no
    points."""
    if points is None:
        return np.zeros(0, np.float64)
    a = np.asarray(points, dtype=np.float64)
    return np.zeros(0, np.float64) if a.size == 0 else flat_xy(a, field)


def new_point_ids(ids, field: str) -> np.ndarray:
    """Client ids of points that join, as sent: integers in uint64 range
    (ValueError otherwise; they name no existing point)."""
    a = np.asarray(ids)
    if a.ndim != 1:
        raise ValueError(f"{field} must be one-dimensional")
    if not a.size:
        return np.zeros(0, np.uint64)
    if not np.issubdtype(a.dtype, np.integer):
        raise ValueError(f"{field} must be integers in 0 .. 2**64-1")
    if np.issubdtype(a.dtype, np.signedinteger) and a.min() < 0:
        i = int(np.argmax(a < 0))
        raise ValueError(f"{field}[{i}] = {a[i]}: not in 0 .. 2**64-1")
    return a.astype(np.uint64)


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
    """(step, positions, triangles), unpackable, with .ids: each position's
    id (the client's uint64 ids on POINT_ID_POLICY_CLIENT sessions, else
    0..n-1)."""

    step: int
    positions: np.ndarray
    triangles: np.ndarray
    ids: np.ndarray

    def __new__(cls, step, positions, triangles, ids):
        obj = super().__new__(cls, (step, positions, triangles))
        obj.step, obj.positions, obj.triangles, obj.ids = (
            step, positions, triangles, ids)
        return obj


class NeighborsBuilder:
    """Puts the chunks of one query answer back together."""

    def __init__(self):
        self._offsets: List[np.ndarray] = [np.zeros(1, np.uint64)]
        self._ids: List[np.ndarray] = []
        self._cids: List[np.ndarray] = []
        self._dists: List[np.ndarray] = []
        self._trunc: List[np.ndarray] = []
        self._step = self._base = self._rows = 0
        self._continues = False

    def add(self, chunk: "pb.QueryResponse") -> None:
        # A field in both encodings is no answer a server writes; it is
        # refused, as the C++ client refuses it, before anything is kept.
        if ((chunk.fixed_offsets and chunk.offsets) or
                (chunk.fixed_ids and chunk.ids) or
                (chunk.fixed_client_ids and chunk.client_ids)):
            raise KinetriError(
                grpc.StatusCode.INTERNAL,
                "query answer: not a valid QueryResponse (offsets, ids or "
                "client ids both as varints and fixed-width)")
        self._step = chunk.step
        if self._continues:
            # The row split across chunks goes on: its end offset is
            # replaced, not followed.
            self._offsets[-1] = self._offsets[-1][:-1]
            self._rows -= 1
        self._continues = chunk.last_row_continues
        # Offsets and ids come in their varint fields or, for requests
        # with encoding ANSWER_ENCODING_FIXED, in the fixed-width ones.
        off = np.asarray(chunk.fixed_offsets or chunk.offsets,
                         dtype=np.uint64)
        ids = np.asarray(chunk.fixed_ids or chunk.ids, dtype=np.uint32)
        cids = np.asarray(chunk.fixed_client_ids or chunk.client_ids,
                          dtype=np.uint64)
        self._offsets.append(off[1:] + np.uint64(self._base))
        self._ids.append(ids)
        self._cids.append(cids)
        self._dists.append(np.asarray(chunk.distances, dtype=np.float64))
        self._trunc.append(np.asarray(chunk.truncated_rows, np.uint64) +
                           np.uint64(self._rows))
        self._base += len(ids) + len(cids)
        self._rows += len(off) - 1

    def result(self) -> Neighbors:
        def cat(parts, dtype):
            return np.concatenate(parts) if parts else np.zeros(0, dtype)
        return Neighbors(self._step, cat(self._offsets, np.uint64),
                         cat(self._ids, np.uint32),
                         cat(self._dists, np.float64),
                         cat(self._trunc, np.uint64),
                         cat(self._cids, np.uint64))


class ExportBuilder:
    """Puts the chunks of one export back together."""

    def __init__(self):
        self._xy: List[np.ndarray] = []
        self._tris: List[np.ndarray] = []
        self._pids: List[np.ndarray] = []
        self._step = 0

    def add(self, chunk: "pb.ExportTriangulationResponse") -> None:
        self._step = chunk.step
        self._xy.append(np.asarray(chunk.xy, dtype=np.float64))
        self._tris.append(np.asarray(chunk.triangles, dtype=np.uint32))
        self._pids.append(np.asarray(chunk.point_ids, dtype=np.uint64))

    def result(self) -> Export:
        positions = (np.concatenate(self._xy) if self._xy
                     else np.zeros(0)).reshape(-1, 2)
        tris = (np.concatenate(self._tris) if self._tris
                else np.zeros(0, np.uint32)).reshape(-1, 3)
        ids = np.concatenate(self._pids) if self._pids else \
            np.zeros(0, np.uint64)
        if len(ids) != len(positions):
            ids = np.arange(len(positions), dtype=np.uint64)
        return Export(self._step, positions, tris, ids)


def create_requests(points, session_id: str, threads: int, ids,
                    chunk_points: int) -> Iterator["pb.CreateSessionRequest"]:
    """The request stream of CreateSession (checked before anything is
    sent)."""
    flat = flat_xy(points)
    id_arr = None if ids is None else np.asarray(ids, dtype=np.uint64)
    if id_arr is not None and 2 * len(id_arr) != len(flat):
        raise ValueError("one id per point")
    policy = (pb.POINT_ID_POLICY_CLIENT if id_arr is not None
              else pb.POINT_ID_POLICY_SEQUENTIAL)

    def requests():
        yield pb.CreateSessionRequest(header=pb.CreateSessionHeader(
            session_id=session_id, point_count=len(flat) // 2,
            options=pb.SessionOptions(threads=threads,
                                      point_id_policy=policy)))
        step = 2 * chunk_points
        for i in range(0, len(flat), step):
            chunk = pb.PointChunk(xy=flat[i:i + step].tolist())
            if id_arr is not None:
                chunk.ids.extend(id_arr[i // 2:(i + step) // 2].tolist())
            yield pb.CreateSessionRequest(points=chunk)
    return requests()


def step_requests(session: str, step: int, mode, values,
                  ids: Optional[Sequence[int]], client_ids: bool,
                  chunk_points: int, request_id: str = "", *,
                  add=None, add_ids: Optional[Sequence[int]] = None,
                  remove: Optional[Sequence[int]] = None
                  ) -> List["pb.StepRequest"]:
    """The messages of one step (checked before anything is sent);
    `request_id` names the step (resending it is then safe).

    `values`: (n, 2) deltas or positions of all points (ids None) or of the
    points named by `ids`; None or empty: no moves. `remove`: ids of points
    that leave (sequential ids, or client ids when `client_ids`); `add`:
    (m, 2) positions of points that join, `add_ids` their client ids (one
    per point; POINT_ID_POLICY_CLIENT sessions need them, sequential ones
    refuse them). Each message carries at most `chunk_points` moves,
    leaving and joining points together (moves first, then removals, then
    additions); the request_id goes on the first, end_of_step on the last.
    """
    flat = optional_xy(values, "values")
    id_arr = None if ids is None else point_ids(ids, client_ids)
    if id_arr is not None and 2 * len(id_arr) != len(flat):
        raise ValueError("one (x, y) pair per id")
    add_flat = optional_xy(add, "add")
    add_arr = None if add_ids is None else new_point_ids(add_ids, "add_ids")
    if add_arr is not None and 2 * len(add_arr) != len(add_flat):
        raise ValueError(f"add_ids: {len(add_arr)} ids for "
                         f"{len(add_flat) // 2} added points (one per point)")
    remove_arr = None if remove is None else point_ids(remove, client_ids,
                                                       "remove")

    def moves(req, lo, hi):
        req.xy.extend(flat[2 * lo:2 * hi].tolist())
        if id_arr is not None:
            (req.client_ids if client_ids else req.ids).extend(
                id_arr[lo:hi].tolist())

    def removals(req, lo, hi):
        (req.remove_client_ids if client_ids else req.remove_ids).extend(
            remove_arr[lo:hi].tolist())

    def additions(req, lo, hi):
        req.add_xy.extend(add_flat[2 * lo:2 * hi].tolist())
        if add_arr is not None:
            req.add_client_ids.extend(add_arr[lo:hi].tolist())

    sections = [(len(flat) // 2, moves),
                (0 if remove_arr is None else len(remove_arr), removals),
                (len(add_flat) // 2, additions)]
    chunk_points = max(1, chunk_points)
    out = [pb.StepRequest(session=session, step=step, mode=mode,
                          request_id=request_id)]
    room = chunk_points
    for count, put in sections:
        pos = 0
        while pos < count:
            if room == 0:
                out.append(pb.StepRequest(session=session, step=step,
                                          mode=mode))
                room = chunk_points
            take = min(room, count - pos)
            put(out[-1], pos, pos + take)
            pos += take
            room -= take
    out[-1].end_of_step = True
    return out


def query_request(session: str, kind, *, k: int = 0, radius: float = 0.0,
                  exclude_self: bool = True, max_per_row: int = 0,
                  points=None, ids=None,
                  client_ids: bool = False) -> "pb.QueryRequest":
    """A query of positions, of points named by id (the client's ids on
    POINT_ID_POLICY_CLIENT sessions) or, when neither, of all points."""
    req = pb.QueryRequest(session=session, kind=kind, k=k, radius=radius,
                          include_distances=True, exclude_self=exclude_self,
                          max_results_per_row=max_per_row)
    if points is not None:
        req.positions.xy.extend(flat_xy(points).tolist())
    elif ids is not None:
        arr = point_ids(ids, client_ids).tolist()
        if client_ids:
            req.point_ids.client_ids.extend(arr)
        else:
            req.point_ids.ids.extend(arr)
    else:
        req.all_points.SetInParent()
    return req


def query_messages(request: "pb.QueryRequest",
                   per: int) -> Optional[List["pb.QueryRequest"]]:
    """None when the request's targets fit in one message of `per` values
    (coordinates or ids); else the messages of a StreamQuery: the query with
    its first targets, then the others `per` values at a time."""
    which = request.WhichOneof("targets")
    if which == "positions":
        values = list(request.positions.xy)
    elif which == "point_ids":
        ids = request.point_ids
        values = list(ids.ids) if len(ids.ids) else list(ids.client_ids)
        client = len(ids.ids) == 0
    else:
        return None
    per = max(2, per - per % 2)
    if len(values) <= per:
        return None
    out = []
    for start in range(0, len(values), per):
        part = values[start:start + per]
        if start == 0:
            msg = pb.QueryRequest()
            msg.CopyFrom(request)
            msg.ClearField(which)
        else:
            msg = pb.QueryRequest()
        if which == "positions":
            msg.positions.xy.extend(part)
        elif client:
            msg.point_ids.client_ids.extend(part)
        else:
            msg.point_ids.ids.extend(part)
        out.append(msg)
    return out


#: Calls that change nothing are retried on UNAVAILABLE (a server
#: restarting, a replica behind the proxy coming back), with backoff; a
#: streamed answer is retried only before its first chunk arrives.
_RETRY_CONFIG = json.dumps({"methodConfig": [{
    "name": [{"service": "kinetri.v1.KinetriService", "method": m}
             for m in ("GetSession", "ListSessions", "Query",
                       "ExportTriangulation")],
    "retryPolicy": {"maxAttempts": 4, "initialBackoff": "0.2s",
                    "maxBackoff": "2s", "backoffMultiplier": 2,
                    "retryableStatusCodes": ["UNAVAILABLE"]},
}]})


def _read(path: str, what: str) -> bytes:
    try:
        with open(path, "rb") as f:
            return f.read()
    except OSError as e:
        raise KinetriError(grpc.StatusCode.FAILED_PRECONDITION,
                           f"{what}: cannot read {path}: {e.strerror}")


@dataclass
class ChannelSetup:
    """How to reach the server: credentials (None: plaintext), channel
    options and the metadata every call carries."""

    credentials: Optional[grpc.ChannelCredentials]
    options: List[Tuple[str, object]]
    auth: Metadata


def channel_setup(token: Optional[str], ca: Optional[str],
                  cert: Optional[str], key: Optional[str],
                  server_name: Optional[str]) -> ChannelSetup:
    """Security settings, each defaulting to its environment variable
    (KINETRI_TOKEN, KINETRI_CA, KINETRI_CERT, KINETRI_KEY,
    KINETRI_TLS_SERVER_NAME); unset means plaintext without a token."""
    env = os.environ.get
    token = token if token is not None else env("KINETRI_TOKEN", "")
    ca = ca if ca is not None else env("KINETRI_CA", "")
    cert = cert if cert is not None else env("KINETRI_CERT", "")
    key = key if key is not None else env("KINETRI_KEY", "")
    server_name = (server_name if server_name is not None
                   else env("KINETRI_TLS_SERVER_NAME", ""))
    options: List[Tuple[str, object]] = [
        ("grpc.max_receive_message_length", 64 << 20),
        ("grpc.enable_retries", 1),
        ("grpc.service_config", _RETRY_CONFIG),
    ]
    credentials = None
    if ca or cert:
        credentials = grpc.ssl_channel_credentials(
            root_certificates=_read(ca, "ca") if ca else None,
            private_key=_read(key, "key") if cert else None,
            certificate_chain=_read(cert, "cert") if cert else None)
        if server_name:
            options.append(("grpc.ssl_target_name_override", server_name))
    auth: Metadata = (("authorization", "Bearer " + token),) if token else ()
    return ChannelSetup(credentials, options, auth)


class ClientBase:
    """What both clients keep: the channel (made by `secure` or `insecure`,
    grpc's or grpc.aio's), the stub, chunk size, deadline, the metadata
    every call carries, and each session's id policy once asked."""

    def __init__(self, target: str, chunk_points: int,
                 token: Optional[str], ca: Optional[str], cert: Optional[str],
                 key: Optional[str], server_name: Optional[str],
                 deadline: Optional[float], secure: Callable,
                 insecure: Callable):
        setup = channel_setup(token, ca, cert, key, server_name)
        self._chunk_points = chunk_points
        self._deadline = deadline
        self._auth = setup.auth
        if setup.credentials is not None:
            self._channel = secure(target, setup.credentials,
                                   options=setup.options)
        else:
            self._channel = insecure(target, options=setup.options)
        self._stub = pb_grpc.KinetriServiceStub(self._channel)
        self._policy: Dict[str, bool] = {}  # session -> uses client ids

    def _md(self, session: str = "") -> Metadata:
        """The call's metadata: the token, and the routing header of
        `session` (none for calls about no session)."""
        return self._auth + (route(session) if session else ())
