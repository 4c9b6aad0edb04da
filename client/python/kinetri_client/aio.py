"""The asyncio client (grpc.aio): the same calls as kinetri_client.Client,
as coroutines.

    async with AsyncClient("127.0.0.1:50051") as client:
        s = await client.create_session(points)
        async with await client.open_steps(s.name) as steps:
            await steps.move_by(deltas)
        nn = await client.nearest_all(s.name)
"""

from typing import List, Optional, Sequence

import grpc
import grpc.aio

from kinetri_client._common import (CHUNK_POINTS, DEFAULT_DEADLINE,
                                    ClientBase, Export, ExportBuilder,
                                    KinetriError, Metadata, Neighbors,
                                    NeighborsBuilder,
                                    create_requests, new_session_id, pb,
                                    query_messages, query_request,
                                    raise_from, route,
                                    step_requests)

__all__ = ["AsyncClient", "AsyncStepStream"]


class AsyncStepStream:
    """One long-lived stream; each awaited call applies one step and returns
    its acknowledgement. An async context manager."""

    def __init__(self, stub, session: str, first_step: int,
                 chunk_points: int, client_ids: bool, metadata: Metadata):
        self._chunk_points = chunk_points
        self._client_ids = client_ids
        self._session = session
        self._next = first_step
        self._failed = False
        self._call = stub.StreamSteps(metadata=tuple(metadata) +
                                      route(session))

    @property
    def next_step(self) -> int:
        return self._next

    async def move_by(self, deltas, ids: Optional[Sequence[int]] = None,
                      request_id: str = "", *, add=None,
                      add_ids: Optional[Sequence[int]] = None,
                      remove: Optional[Sequence[int]] = None
                      ) -> "pb.StepResponse":
        """Moves points by (n, 2) deltas: all points in id order, or the
        points named by `ids`. `request_id` names the step (see
        StepStream.move_by); `add`, `add_ids` and `remove`: points that
        join and leave with the step (see change)."""
        return await self._send(pb.DISPLACEMENT_MODE_DELTA, deltas, ids,
                                request_id, add, add_ids, remove)

    async def move_to(self, positions, ids: Optional[Sequence[int]] = None,
                      request_id: str = "", *, add=None,
                      add_ids: Optional[Sequence[int]] = None,
                      remove: Optional[Sequence[int]] = None
                      ) -> "pb.StepResponse":
        """Moves points to (n, 2) absolute positions; `add`, `add_ids`
        and `remove` as for move_by."""
        return await self._send(pb.DISPLACEMENT_MODE_ABSOLUTE, positions, ids,
                                request_id, add, add_ids, remove)

    async def change(self, add=None, add_ids: Optional[Sequence[int]] = None,
                     remove: Optional[Sequence[int]] = None,
                     request_id: str = "") -> "pb.StepResponse":
        """A step in which no point moves, only points leave (`remove`)
        and join (`add` positions, `add_ids` their client ids); see
        StepStream.change."""
        return await self._send(pb.DISPLACEMENT_MODE_DELTA, None, None,
                                request_id, add, add_ids, remove)

    async def _send(self, mode, values, ids, request_id: str, add=None,
                    add_ids=None, remove=None) -> "pb.StepResponse":
        requests = step_requests(self._session, self._next, mode, values, ids,
                                 self._client_ids, self._chunk_points,
                                 request_id, add=add, add_ids=add_ids,
                                 remove=remove)
        try:
            for req in requests:
                await self._call.write(req)
            resp = await self._call.read()
        except grpc.RpcError as e:
            self._failed = True
            raise_from(e)
        if resp is grpc.aio.EOF:
            self._failed = True
            code = await self._call.code()
            raise_from(_Ended(code, await self._call.details()))
        self._next += 1
        return resp

    async def close(self) -> None:
        """Ends the stream; raises its final error unless a step already
        raised it."""
        try:
            await self._call.done_writing()
            code = await self._call.code()
        except grpc.RpcError as e:
            if e.code() != grpc.StatusCode.CANCELLED and not self._failed:
                raise_from(e)
            return
        if code not in (grpc.StatusCode.OK, grpc.StatusCode.CANCELLED) and \
                not self._failed:
            raise_from(_Ended(code, await self._call.details()))

    async def __aenter__(self) -> "AsyncStepStream":
        return self

    async def __aexit__(self, *exc) -> None:
        await self.close()


class _Ended(grpc.RpcError):
    """A stream's final status, shaped like the errors calls raise."""

    def __init__(self, code, details):
        super().__init__()
        self._code, self._details = code, details

    def code(self):
        return self._code

    def details(self):
        return self._details


class AsyncClient(ClientBase):
    """kinetri_client.Client for asyncio: the same arguments (security
    settings default to the KINETRI_* environment variables), deadlines and
    retries; every method is a coroutine. An async context manager."""

    def __init__(self, target: str = "127.0.0.1:50051",
                 chunk_points: int = CHUNK_POINTS, *,
                 token: Optional[str] = None, ca: Optional[str] = None,
                 cert: Optional[str] = None, key: Optional[str] = None,
                 server_name: Optional[str] = None,
                 deadline: Optional[float] = DEFAULT_DEADLINE):
        super().__init__(target, chunk_points, token, ca, cert, key,
                         server_name, deadline, grpc.aio.secure_channel,
                         grpc.aio.insecure_channel)

    async def close(self) -> None:
        await self._channel.close()

    async def __aenter__(self) -> "AsyncClient":
        return self

    async def __aexit__(self, *exc) -> None:
        await self.close()

    async def create_session(self, points, session_id: str = "",
                             threads: int = 0, ids=None) -> "pb.Session":
        session_id = session_id or new_session_id()
        requests = create_requests(points, session_id, threads, ids,
                                   self._chunk_points)
        try:
            s = await self._stub.CreateSession(
                requests, timeout=self._deadline,
                metadata=self._md(session_id))
        except grpc.RpcError as e:
            raise_from(e)
        self._policy[s.name] = ids is not None
        return s

    async def get_session(self, name: str) -> "pb.Session":
        try:
            return await self._stub.GetSession(
                pb.GetSessionRequest(name=name), timeout=self._deadline,
                metadata=self._md(name))
        except grpc.RpcError as e:
            raise_from(e)

    async def list_sessions(self) -> List["pb.Session"]:
        out: List[pb.Session] = []
        token = ""
        while True:
            try:
                resp = await self._stub.ListSessions(
                    pb.ListSessionsRequest(page_size=100, page_token=token),
                    timeout=self._deadline, metadata=self._md())
            except grpc.RpcError as e:
                raise_from(e)
            out.extend(resp.sessions)
            token = resp.next_page_token
            if not token:
                return out

    async def delete_session(self, name: str) -> None:
        self._policy.pop(name, None)
        try:
            await self._stub.DeleteSession(
                pb.DeleteSessionRequest(name=name), timeout=self._deadline,
                metadata=self._md(name))
        except grpc.RpcError as e:
            raise_from(e)

    async def open_steps(self, name: str,
                         first_step: Optional[int] = None) -> AsyncStepStream:
        s = await self.get_session(name)
        return AsyncStepStream(self._stub, name,
                               s.step + 1 if first_step is None
                               else first_step,
                               self._chunk_points,
                               s.options.point_id_policy ==
                               pb.POINT_ID_POLICY_CLIENT, self._auth)

    async def _uses_client_ids(self, name: str) -> bool:
        if name not in self._policy:
            s = await self.get_session(name)
            self._policy[name] = (s.options.point_id_policy ==
                                  pb.POINT_ID_POLICY_CLIENT)
        return self._policy[name]

    async def query(self, request: "pb.QueryRequest") -> Neighbors:
        out = NeighborsBuilder()
        # Targets beyond one message go by StreamQuery, cut into messages.
        msgs = query_messages(request, 2 * self._chunk_points)
        call = None
        try:
            call = (self._stub.Query(request, timeout=self._deadline,
                                     metadata=self._md(request.session))
                    if msgs is None else
                    self._stub.StreamQuery(iter(msgs), timeout=self._deadline,
                                           metadata=self._md(request.session)))
            async for chunk in call:
                out.add(chunk)
        except grpc.RpcError as e:
            raise_from(e)
        except KinetriError:
            # A chunk was refused: the rest of the answer is not read.
            if call is not None:
                call.cancel()
            raise
        return out.result()

    async def nearest_all(self, name: str) -> Neighbors:
        return await self.query(query_request(name, pb.QUERY_KIND_NEAREST))

    async def knn(self, name: str, k: int, points=None, ids=None,
                  exclude_self: bool = True) -> Neighbors:
        client = ids is not None and points is None and \
            await self._uses_client_ids(name)
        return await self.query(query_request(
            name, pb.QUERY_KIND_K_NEAREST, k=k, exclude_self=exclude_self,
            points=points, ids=ids, client_ids=client))

    async def radius(self, name: str, r: float, points=None, ids=None,
                     exclude_self: bool = True,
                     max_per_row: int = 0) -> Neighbors:
        client = ids is not None and points is None and \
            await self._uses_client_ids(name)
        return await self.query(query_request(
            name, pb.QUERY_KIND_RADIUS, radius=r, exclude_self=exclude_self,
            max_per_row=max_per_row, points=points, ids=ids,
            client_ids=client))

    async def export(self, name: str) -> Export:
        out = ExportBuilder()
        try:
            async for chunk in self._stub.ExportTriangulation(
                    pb.ExportTriangulationRequest(session=name),
                    timeout=self._deadline, metadata=self._md(name)):
                out.add(chunk)
        except grpc.RpcError as e:
            raise_from(e)
        return out.result()
