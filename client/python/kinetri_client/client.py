"""The synchronous client over the generated gRPC stubs."""

import queue
from typing import Iterator, List, Optional, Sequence

import grpc

from kinetri_client._common import (CHUNK_POINTS, DEFAULT_DEADLINE,
                                    ClientBase, Export, ExportBuilder,
                                    KinetriError, Metadata, Neighbors,
                                    NeighborsBuilder, create_requests,
                                    new_session_id, pb, query_messages,
                                    query_request,
                                    raise_from, route, step_requests)

__all__ = ["Client", "StepStream"]


class StepStream:
    """One long-lived stream; each call applies one step and returns its
    acknowledgement (step number and statistics). A context manager."""

    def __init__(self, stub, session: str, first_step: int,
                 chunk_points: int = CHUNK_POINTS, client_ids: bool = False,
                 metadata: Metadata = ()):
        self._chunk_points = chunk_points
        self._client_ids = client_ids
        self._session = session
        self._next = first_step
        self._failed = False
        self._queue = _RequestQueue()
        self._responses = stub.StreamSteps(
            iter(self._queue), metadata=tuple(metadata) + route(session))

    @property
    def next_step(self) -> int:
        return self._next

    def move_by(self, deltas, ids: Optional[Sequence[int]] = None,
                request_id: str = "", *, add=None,
                add_ids: Optional[Sequence[int]] = None,
                remove: Optional[Sequence[int]] = None) -> "pb.StepResponse":
        """Moves points by (n, 2) deltas: all points in id order, or the
        points named by `ids` (the client's ids on POINT_ID_POLICY_CLIENT
        sessions). `request_id` names the step: resending a step the server
        already applied under that name (its acknowledgement was lost, e.g.
        on a new stream from open_steps(name, first_step=...)) returns the
        original acknowledgement and applies nothing.

        Points may leave and join with the same step (see `change`):
        `remove` names the points that leave, `add` gives (m, 2) positions
        of the points that join, `add_ids` their client ids. The moves use
        the numbering before the step and apply first."""
        return self._send(pb.DISPLACEMENT_MODE_DELTA, deltas, ids, request_id,
                          add, add_ids, remove)

    def move_to(self, positions, ids: Optional[Sequence[int]] = None,
                request_id: str = "", *, add=None,
                add_ids: Optional[Sequence[int]] = None,
                remove: Optional[Sequence[int]] = None) -> "pb.StepResponse":
        """Moves points to (n, 2) absolute positions; `add`, `add_ids`
        and `remove` as for move_by."""
        return self._send(pb.DISPLACEMENT_MODE_ABSOLUTE, positions, ids,
                          request_id, add, add_ids, remove)

    def change(self, add=None, add_ids: Optional[Sequence[int]] = None,
               remove: Optional[Sequence[int]] = None,
               request_id: str = "") -> "pb.StepResponse":
        """A step in which no point moves, only points leave and join.

        `remove`: ids of the points that leave (sequential ids, or the
        client's ids on POINT_ID_POLICY_CLIENT sessions). `add`: (m, 2)
        positions of the points that join; `add_ids`: their client ids, one
        per point (required on POINT_ID_POLICY_CLIENT sessions, refused on
        sequential ones). Removals apply before additions, so a client id
        may leave and join again in one step. On sequential sessions the
        remaining points are numbered 0.. again in their old order and the
        joining ones follow in the order given: the acknowledgement's
        stats.first_added_id is the first one's id. stats.point_count is
        the session's point count after the step."""
        return self._send(pb.DISPLACEMENT_MODE_DELTA, None, None, request_id,
                          add, add_ids, remove)

    def _send(self, mode, values, ids, request_id: str, add=None,
              add_ids=None, remove=None) -> "pb.StepResponse":
        for req in step_requests(self._session, self._next, mode, values, ids,
                                 self._client_ids, self._chunk_points,
                                 request_id, add=add, add_ids=add_ids,
                                 remove=remove):
            self._queue.put(req)
        try:
            resp = next(self._responses)
        except grpc.RpcError as e:
            self._failed = True
            raise_from(e)
        self._next += 1
        return resp

    def close(self) -> None:
        """Ends the stream; raises its final error unless a step already
        raised it."""
        self._queue.close()
        try:
            for _ in self._responses:
                pass
        except grpc.RpcError as e:
            if e.code() != grpc.StatusCode.CANCELLED and not self._failed:
                raise_from(e)

    def __enter__(self) -> "StepStream":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class _RequestQueue:
    """Blocking iterator feeding a request stream."""

    def __init__(self):
        self._q: "queue.Queue" = queue.Queue()

    def put(self, item) -> None:
        self._q.put(item)

    def close(self) -> None:
        self._q.put(None)

    def __iter__(self) -> Iterator:
        while True:
            item = self._q.get()
            if item is None:
                return
            yield item


class Client(ClientBase):
    """Connects to a kinetri-server at `target` ("host:port").

    Security (docs/SECURITY.md): `token` is sent as a bearer token with every
    call; `ca` (a PEM CA bundle) turns TLS on; `cert` and `key` add a client
    certificate (mutual TLS); `server_name` overrides the name expected in
    the server's certificate. Each defaults to its environment variable
    (KINETRI_TOKEN, KINETRI_CA, KINETRI_CERT, KINETRI_KEY,
    KINETRI_TLS_SERVER_NAME); unset means plaintext without a token.

    `deadline`: seconds every call but a step stream may take (None: no
    limit); past it the call fails with DEADLINE_EXCEEDED and the server
    stops its work. Calls that change nothing (get, list, query, export)
    are retried on UNAVAILABLE with backoff. A context manager.
    """

    def __init__(self, target: str = "127.0.0.1:50051",
                 chunk_points: int = CHUNK_POINTS, *,
                 token: Optional[str] = None, ca: Optional[str] = None,
                 cert: Optional[str] = None, key: Optional[str] = None,
                 server_name: Optional[str] = None,
                 deadline: Optional[float] = DEFAULT_DEADLINE):
        super().__init__(target, chunk_points, token, ca, cert, key,
                         server_name, deadline, grpc.secure_channel,
                         grpc.insecure_channel)

    def close(self) -> None:
        self._channel.close()

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # Sessions -------------------------------------------------------------
    def create_session(self, points, session_id: str = "",
                       threads: int = 0, ids=None) -> "pb.Session":
        """Creates a session of (n, 2) `points`; `ids`: optional distinct
        uint64 per point (POINT_ID_POLICY_CLIENT). Without `session_id` the
        client names it (new_session_id()), so that a proxy routes the
        creation by the same key as every later call."""
        session_id = session_id or new_session_id()
        requests = create_requests(points, session_id, threads, ids,
                                   self._chunk_points)
        try:
            s = self._stub.CreateSession(requests, timeout=self._deadline,
                                         metadata=self._md(session_id))
        except grpc.RpcError as e:
            raise_from(e)
        # The id policy is known (a session made again under an old name
        # may have another one).
        self._policy[s.name] = ids is not None
        return s

    def get_session(self, name: str) -> "pb.Session":
        try:
            return self._stub.GetSession(pb.GetSessionRequest(name=name),
                                         timeout=self._deadline,
                                         metadata=self._md(name))
        except grpc.RpcError as e:
            raise_from(e)

    def list_sessions(self) -> List["pb.Session"]:
        """Every session (behind a proxy: of one replica)."""
        out: List[pb.Session] = []
        token = ""
        while True:
            try:
                resp = self._stub.ListSessions(
                    pb.ListSessionsRequest(page_size=100, page_token=token),
                    timeout=self._deadline, metadata=self._md())
            except grpc.RpcError as e:
                raise_from(e)
            out.extend(resp.sessions)
            token = resp.next_page_token
            if not token:
                return out

    def delete_session(self, name: str) -> None:
        self._policy.pop(name, None)
        try:
            self._stub.DeleteSession(pb.DeleteSessionRequest(name=name),
                                     timeout=self._deadline,
                                     metadata=self._md(name))
        except grpc.RpcError as e:
            raise_from(e)

    def open_steps(self, name: str,
                   first_step: Optional[int] = None) -> StepStream:
        """A step stream continuing after the session's current step, or at
        `first_step` (to resend a step whose acknowledgement was lost)."""
        s = self.get_session(name)
        return StepStream(self._stub, name,
                          s.step + 1 if first_step is None else first_step,
                          self._chunk_points,
                          s.options.point_id_policy ==
                          pb.POINT_ID_POLICY_CLIENT, self._auth)

    def _uses_client_ids(self, name: str) -> bool:
        """The session's id policy (asked once per session name)."""
        if name not in self._policy:
            self._policy[name] = (self.get_session(name).options.point_id_policy
                                  == pb.POINT_ID_POLICY_CLIENT)
        return self._policy[name]

    # Queries ----------------------------------------------------------------
    def query(self, request: "pb.QueryRequest") -> Neighbors:
        out = NeighborsBuilder()
        # Targets beyond one message go by StreamQuery, cut into messages.
        msgs = query_messages(request, 2 * self._chunk_points)
        chunks = None
        try:
            chunks = (self._stub.Query(request, timeout=self._deadline,
                                       metadata=self._md(request.session))
                      if msgs is None else
                      self._stub.StreamQuery(
                          iter(msgs), timeout=self._deadline,
                          metadata=self._md(request.session)))
            for chunk in chunks:
                out.add(chunk)
        except grpc.RpcError as e:
            raise_from(e)
        except KinetriError:
            # A chunk was refused: the rest of the answer is not read.
            if chunks is not None:
                chunks.cancel()
            raise
        return out.result()

    def nearest_all(self, name: str) -> Neighbors:
        return self.query(query_request(name, pb.QUERY_KIND_NEAREST))

    def knn(self, name: str, k: int, points=None, ids=None,
            exclude_self: bool = True) -> Neighbors:
        """k nearest of (n, 2) `points`, of the points named by `ids`, or of
        all points."""
        client = ids is not None and points is None and \
            self._uses_client_ids(name)
        return self.query(query_request(
            name, pb.QUERY_KIND_K_NEAREST, k=k, exclude_self=exclude_self,
            points=points, ids=ids, client_ids=client))

    def radius(self, name: str, r: float, points=None, ids=None,
               exclude_self: bool = True, max_per_row: int = 0) -> Neighbors:
        """Every point within `r` (inclusive), closest first."""
        client = ids is not None and points is None and \
            self._uses_client_ids(name)
        return self.query(query_request(
            name, pb.QUERY_KIND_RADIUS, radius=r, exclude_self=exclude_self,
            max_per_row=max_per_row, points=points, ids=ids,
            client_ids=client))

    def export(self, name: str) -> Export:
        """Returns (step, positions (n, 2), triangles (m, 3)); the result
        also has .ids: each position's id (the client's uint64 ids on
        POINT_ID_POLICY_CLIENT sessions, else 0..n-1)."""
        out = ExportBuilder()
        try:
            for chunk in self._stub.ExportTriangulation(
                    pb.ExportTriangulationRequest(session=name),
                    timeout=self._deadline, metadata=self._md(name)):
                out.add(chunk)
        except grpc.RpcError as e:
            raise_from(e)
        return out.result()


# Kept importable from here as before.
__all__ += ["KinetriError", "Neighbors", "Export"]
