"""End-to-end tests of the Python client against a real kinetri-server."""

import os
import re
import shutil
import subprocess
import tempfile
import unittest

import grpc
import numpy as np

from kinetri_client import Client, KinetriError


def server_binary():
    """KINETRI_SERVER, else the build tree's server (build/server)."""
    binary = os.environ.get("KINETRI_SERVER")
    if not binary:
        here = os.path.dirname(os.path.abspath(__file__))
        binary = os.path.join(here, "..", "..", "..", "build", "server",
                              "kinetri-server")
    if not os.path.exists(binary):
        raise unittest.SkipTest(
            f"no kinetri-server at {binary}: build it (bash scripts/build.sh) "
            "or set KINETRI_SERVER")
    return binary


def start_server(*flags):
    binary = server_binary()
    proc = subprocess.Popen(
        [binary, "--listen=127.0.0.1:0", "--metrics_listen=", *flags],
        stdout=subprocess.PIPE, text=True)
    for line in proc.stdout:
        m = re.search(r"listening on port (\d+)", line)
        if m:
            return proc, f"127.0.0.1:{m.group(1)}"
    raise RuntimeError("server did not start")


class ServerTestCase(unittest.TestCase):
    """A real kinetri-server (defaults, loopback) for the whole class."""

    @classmethod
    def setUpClass(cls):
        cls.proc, cls.target = start_server()

    @classmethod
    def tearDownClass(cls):
        cls.proc.terminate()
        cls.proc.wait(timeout=30)


class ClientTest(ServerTestCase):

    def test_lifecycle_against_brute_force(self):
        rng = np.random.default_rng(5)
        n = 3000
        pts = rng.random((n, 2))
        with Client(self.target, chunk_points=500) as c:  # force chunking
            s = c.create_session(pts, session_id="py-life")
            self.assertEqual(s.name, "sessions/py-life")
            self.assertEqual(s.point_count, n)
            steps = c.open_steps(s.name)
            for i in range(100):
                d = rng.normal(0, 0.1 / np.sqrt(n), (n, 2))
                ack = steps.move_by(d)
                pts = pts + d
                self.assertEqual(ack.step, i + 1)
            ids = np.arange(0, 40)
            d = rng.normal(0, 0.01, (40, 2))
            steps.move_by(d, ids=ids)
            pts[ids] += d
            steps.close()

            diff = pts[:, None, :] - pts[None, :, :]
            dist2 = (diff ** 2).sum(-1)
            np.fill_diagonal(dist2, np.inf)
            nn = c.nearest_all(s.name)
            self.assertEqual(nn.step, 101)
            self.assertTrue(np.array_equal(nn.ids, dist2.argmin(1)))
            self.assertTrue(np.allclose(nn.distances, np.sqrt(dist2.min(1))))

            q = rng.random((50, 2))
            knn = c.knn(s.name, 4, points=q)
            qd = ((q[:, None, :] - pts[None, :, :]) ** 2).sum(-1)
            want = np.argsort(qd, axis=1)[:, :4]
            for r in range(len(q)):
                self.assertTrue(np.array_equal(knn.row(r), want[r]))

            knn_ids = c.knn(s.name, 5, ids=np.arange(0, n, 97))
            for row, i in enumerate(range(0, n, 97)):
                self.assertTrue(np.array_equal(knn_ids.row(row),
                                               np.argsort(dist2[i])[:5]))

            r = 0.03
            rad = c.radius(s.name, r, ids=np.arange(100))
            for i in range(100):
                inside = np.nonzero(dist2[i] <= r * r)[0]
                self.assertEqual(sorted(rad.row(i).tolist()),
                                 sorted(inside.tolist()))

            step, xy, tris = c.export(s.name)
            self.assertEqual(step, 101)
            self.assertTrue(np.array_equal(xy, pts))
            self.assertGreater(len(tris), n)
            c.delete_session(s.name)
            with self.assertRaises(KinetriError) as e:
                c.get_session(s.name)
            self.assertEqual(e.exception.code, grpc.StatusCode.NOT_FOUND)

    def test_rows_split_across_chunks(self):
        from kinetri_client._common import query_request, pb
        rng = np.random.default_rng(8)
        with Client(self.target) as c:
            s = c.create_session(rng.random((300, 2)), session_id="py-split")
            req = query_request(s.name, pb.QUERY_KIND_K_NEAREST, k=100,
                                ids=[0, 5, 9])
            whole = c.query(req)
            req.results_per_chunk = 7
            req.rows_per_chunk = 2
            split = c.query(req)
            np.testing.assert_array_equal(split.offsets, whole.offsets)
            np.testing.assert_array_equal(split.ids, whole.ids)
            np.testing.assert_array_equal(split.distances, whole.distances)
            self.assertEqual(len(split), 3)
            self.assertEqual(len(split.row(1)), 100)
            c.delete_session(s.name)

    def test_resent_steps_are_idempotent(self):
        rng = np.random.default_rng(4)
        pts = rng.random((300, 2))
        d = rng.normal(0, 0.01, pts.shape)
        with Client(self.target) as c:
            s = c.create_session(pts, session_id="py-idem")
            with c.open_steps(s.name) as steps:
                ack = steps.move_by(d, request_id="py-step-1")
            # The acknowledgement was "lost": resend on a new stream.
            with c.open_steps(s.name, first_step=1) as steps:
                again = steps.move_by(d, request_id="py-step-1")
                self.assertEqual(again.step, 1)
                self.assertEqual(again.stats.delaunay_flips,
                                 ack.stats.delaunay_flips)
                self.assertEqual(steps.next_step, 2)
            step, positions, _ = c.export(s.name)
            self.assertEqual(step, 1)
            np.testing.assert_array_equal(positions, pts + d)
            with c.open_steps(s.name, first_step=1) as steps:
                with self.assertRaises(KinetriError) as e:
                    steps.move_by(d, request_id="another")
            self.assertEqual(e.exception.code,
                             grpc.StatusCode.FAILED_PRECONDITION)
            c.delete_session(s.name)

    def test_client_ids(self):
        rng = np.random.default_rng(9)
        pts = rng.random((300, 2))
        ids = (np.arange(300, dtype=np.uint64) * 7919 + 10**12)
        with Client(self.target) as c:
            s = c.create_session(pts, ids=ids)
            self.assertEqual(s.options.point_id_policy, 2)
            nn = c.nearest_all(s.name)
            d2 = ((pts[:, None, :] - pts[None, :, :]) ** 2).sum(-1)
            np.fill_diagonal(d2, np.inf)
            self.assertTrue(np.array_equal(nn.client_ids, ids[d2.argmin(1)]))
            c.delete_session(s.name)

    def test_client_ids_end_to_end(self):
        rng = np.random.default_rng(9)
        n = 400
        pts = rng.random((n, 2))
        ids = (np.arange(n, dtype=np.uint64) * 7919 + (1 << 40)).astype(
            np.uint64)
        with Client(self.target) as c:
            s = c.create_session(pts, session_id="py-cids", ids=ids)
            # k-NN of points named by client id, answered in client ids.
            sel = ids[::37]
            knn = c.knn(s.name, 3, ids=sel)
            d2 = ((pts[:, None, :] - pts[None, :, :]) ** 2).sum(-1)
            np.fill_diagonal(d2, np.inf)
            for row, i in enumerate(range(0, n, 37)):
                want = ids[np.argsort(d2[i], kind="stable")[:3]]
                self.assertTrue(np.array_equal(knn.row(row), want))
            # Sparse moves by client id.
            steps = c.open_steps(s.name)
            steps.move_to(np.array([[0.5, 0.5]]), ids=[ids[5]])
            steps.close()
            step, xy, tris = c.export(s.name)
            self.assertEqual(step, 1)
            exported = c.export(s.name)
            self.assertTrue(np.array_equal(exported.ids, ids))
            self.assertTrue(np.array_equal(exported.positions[5], [0.5, 0.5]))
            # An unknown client id is NOT_FOUND.
            with self.assertRaises(KinetriError) as e:
                c.knn(s.name, 1, ids=[12345])
            self.assertEqual(e.exception.code, grpc.StatusCode.NOT_FOUND)
            c.delete_session(s.name)

    def test_ids_never_wrap(self):
        with Client(self.target) as c:
            s = c.create_session(np.random.default_rng(7).random((50, 2)))
            for bad in ([(1 << 32) + 1], [-1]):
                with self.assertRaises(KinetriError) as e:
                    c.knn(s.name, 1, ids=bad)
                self.assertEqual(e.exception.code, grpc.StatusCode.NOT_FOUND)
                steps = c.open_steps(s.name)
                with self.assertRaises(KinetriError) as e:
                    steps.move_by(np.zeros((1, 2)), ids=bad)
                self.assertEqual(e.exception.code, grpc.StatusCode.NOT_FOUND)
            self.assertEqual(c.get_session(s.name).step, 0)
            c.delete_session(s.name)

    def test_errors(self):
        with Client(self.target) as c:
            s = c.create_session(np.random.default_rng(6).random((200, 2)))
            steps = c.open_steps(s.name)
            bad = np.zeros((200, 2))
            bad[3, 0] = np.nan
            with self.assertRaises(KinetriError) as e:
                steps.move_by(bad)
            self.assertEqual(e.exception.code, grpc.StatusCode.INVALID_ARGUMENT)
            self.assertIn("deltas[3].x", e.exception.message)
            self.assertEqual(c.get_session(s.name).step, 0)
            with self.assertRaises(KinetriError) as e:
                c.knn(s.name, 0, ids=[1])
            self.assertEqual(e.exception.code, grpc.StatusCode.INVALID_ARGUMENT)
            with self.assertRaises(KinetriError) as e:
                c.radius(s.name, -1.0, ids=[1])
            self.assertEqual(e.exception.code, grpc.StatusCode.INVALID_ARGUMENT)
            with self.assertRaises(KinetriError) as e:
                c.nearest_all("sessions/missing")
            self.assertEqual(e.exception.code, grpc.StatusCode.NOT_FOUND)
            c.delete_session(s.name)


if __name__ == "__main__":
    unittest.main()


class SecureClientTest(unittest.TestCase):
    """TLS + bearer token (certificates made by openssl at test time)."""

    TOKEN = "py-tenant-token-0123456789"

    @classmethod
    def setUpClass(cls):
        cls.dir = tempfile.mkdtemp(prefix="kinetri-py-tls-")
        here = os.path.dirname(os.path.abspath(__file__))
        script = os.path.join(here, "..", "..", "..", "tests", "e2e",
                              "make_test_certs.sh")
        subprocess.run(["bash", script, cls.dir], check=True)
        tokens = os.path.join(cls.dir, "tokens")
        with open(tokens, "w") as f:
            f.write(f"{cls.TOKEN} py\n")
        f = lambda name: os.path.join(cls.dir, name)
        cls.proc, cls.target = start_server(
            f"--tls_cert={f('server.pem')}", f"--tls_key={f('server.key')}",
            f"--tls_client_ca={f('ca.pem')}", f"--auth_tokens_file={tokens}")
        cls.f = staticmethod(f)

    @classmethod
    def tearDownClass(cls):
        cls.proc.terminate()
        cls.proc.wait(timeout=30)
        shutil.rmtree(cls.dir, ignore_errors=True)

    def secure(self, **kw):
        args = dict(ca=self.f("ca.pem"), cert=self.f("client.pem"),
                    key=self.f("client.key"), token=self.TOKEN)
        args.update(kw)
        return Client(self.target, **args)

    def test_tls_and_token(self):
        rng = np.random.default_rng(9)
        pts = rng.random((500, 2))
        with self.secure() as c:
            s = c.create_session(pts, session_id="py-secure")
            steps = c.open_steps(s.name)
            steps.move_by(rng.normal(0, 1e-3, (500, 2)))
            nn = c.nearest_all(s.name)
            self.assertEqual(len(nn.offsets), 501)
            c.delete_session(s.name)

    def test_refusals(self):
        with self.secure(token="") as c:  # no token
            with self.assertRaises(KinetriError) as e:
                c.list_sessions()
            self.assertEqual(e.exception.code,
                             grpc.StatusCode.UNAUTHENTICATED)
        with self.secure(token="wrong-token-0123456789") as c:
            with self.assertRaises(KinetriError) as e:
                c.list_sessions()
            self.assertEqual(e.exception.code,
                             grpc.StatusCode.UNAUTHENTICATED)
        with self.secure(cert="", key="") as c:  # mutual TLS: no cert
            with self.assertRaises(KinetriError) as e:
                c.list_sessions()
            self.assertEqual(e.exception.code, grpc.StatusCode.UNAVAILABLE)
        with Client(self.target, token=self.TOKEN, ca="") as c:  # plaintext
            with self.assertRaises(KinetriError) as e:
                c.list_sessions()
            self.assertEqual(e.exception.code, grpc.StatusCode.UNAVAILABLE)

    def test_environment_variables(self):
        env = {"KINETRI_TOKEN": self.TOKEN, "KINETRI_CA": self.f("ca.pem"),
               "KINETRI_CERT": self.f("client.pem"),
               "KINETRI_KEY": self.f("client.key")}
        old = {k: os.environ.get(k) for k in env}
        os.environ.update(env)
        try:
            with Client(self.target) as c:
                self.assertIsInstance(c.list_sessions(), list)
        finally:
            for k, v in old.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v


class RoutingHeaderTest(unittest.TestCase):
    """Every call about a session names it in the `kinetri-session` header
    (what a proxy in front of several servers hashes); checked against a
    stand-in server that records the metadata of every call."""

    @classmethod
    def setUpClass(cls):
        from concurrent import futures
        cls.seen = []
        seen = cls.seen

        class Recorder(grpc.GenericRpcHandler):
            def service(self, details):
                seen.append((details.method, dict(details.invocation_metadata)))
                return None  # UNIMPLEMENTED

        cls.server = grpc.server(futures.ThreadPoolExecutor(max_workers=2))
        cls.server.add_generic_rpc_handlers((Recorder(),))
        port = cls.server.add_insecure_port("127.0.0.1:0")
        cls.server.start()
        cls.target = f"127.0.0.1:{port}"

    @classmethod
    def tearDownClass(cls):
        cls.server.stop(None)

    def call(self, fn):
        self.seen.clear()
        with self.assertRaises(KinetriError):
            fn()
        self.assertEqual(len(self.seen), 1)
        return self.seen[0]

    def test_header_on_every_session_call(self):
        pts = np.zeros((3, 2))
        with Client(self.target) as c:
            for fn in (lambda: c.get_session("sessions/run-7"),
                       lambda: c.delete_session("sessions/run-7"),
                       lambda: c.nearest_all("sessions/run-7"),
                       lambda: c.knn("sessions/run-7", 2, points=pts),
                       lambda: c.export("sessions/run-7"),
                       lambda: c.create_session(pts, session_id="run-7")):
                method, md = self.call(fn)
                self.assertEqual(md.get("kinetri-session"), "run-7", method)
            # A session the caller does not name is named by the client,
            # and the creation is routed by that name.
            method, md = self.call(lambda: c.create_session(pts))
            self.assertRegex(md.get("kinetri-session", ""),
                             r"^s-[0-9a-f]{32}$")
            # Calls about no session carry no key.
            method, md = self.call(c.list_sessions)
            self.assertNotIn("kinetri-session", md)
            # Nor do names that cannot be a session id (huge or odd).
            method, md = self.call(
                lambda: c.get_session("sessions/" + "x" * 100000))
            self.assertNotIn("kinetri-session", md)


class DeadlineAndRetryTest(unittest.TestCase):
    """Deadlines on every call and retries of the calls that change
    nothing, against a stand-in server whose GetSession fails with
    UNAVAILABLE a given number of times, or never answers."""

    @classmethod
    def setUpClass(cls):
        import threading
        from concurrent import futures
        from kinetri_client._common import pb
        cls.failures = 0
        cls.calls = 0
        cls.release = threading.Event()
        test = cls

        def get_session(request, context):
            test.calls += 1
            if request.name == "sessions/hang":
                test.release.wait(10)
                context.abort(grpc.StatusCode.CANCELLED, "released")
            if test.calls <= test.failures:
                context.abort(grpc.StatusCode.UNAVAILABLE, "restarting")
            return pb.Session(name=request.name, step=7)

        handler = grpc.method_handlers_generic_handler(
            "kinetri.v1.KinetriService",
            {"GetSession": grpc.unary_unary_rpc_method_handler(
                get_session,
                request_deserializer=pb.GetSessionRequest.FromString,
                response_serializer=pb.Session.SerializeToString)})
        cls.server = grpc.server(futures.ThreadPoolExecutor(max_workers=4))
        cls.server.add_generic_rpc_handlers((handler,))
        port = cls.server.add_insecure_port("127.0.0.1:0")
        cls.server.start()
        cls.target = f"127.0.0.1:{port}"

    @classmethod
    def tearDownClass(cls):
        cls.release.set()
        cls.server.stop(None)

    def test_unavailable_is_retried(self):
        type(self).calls, type(self).failures = 0, 2
        with Client(self.target) as c:
            self.assertEqual(c.get_session("sessions/a").step, 7)
        self.assertEqual(self.calls, 3)

    def test_retries_give_up(self):
        type(self).calls, type(self).failures = 0, 100
        with Client(self.target) as c:
            with self.assertRaises(KinetriError) as e:
                c.get_session("sessions/a")
        self.assertEqual(e.exception.code, grpc.StatusCode.UNAVAILABLE)
        self.assertEqual(self.calls, 4)  # maxAttempts

    def test_deadline(self):
        import time
        with Client(self.target, deadline=0.3) as c:
            t0 = time.monotonic()
            with self.assertRaises(KinetriError) as e:
                c.get_session("sessions/hang")
        self.assertEqual(e.exception.code, grpc.StatusCode.DEADLINE_EXCEEDED)
        self.assertLess(time.monotonic() - t0, 5)

    def test_async_deadline_and_retry(self):
        import asyncio
        from kinetri_client.aio import AsyncClient

        async def run():
            type(self).calls, type(self).failures = 0, 1
            async with AsyncClient(self.target) as c:
                self.assertEqual((await c.get_session("sessions/a")).step, 7)
            self.assertEqual(self.calls, 2)
            async with AsyncClient(self.target, deadline=0.3) as c:
                with self.assertRaises(KinetriError) as e:
                    await c.get_session("sessions/hang")
            self.assertEqual(e.exception.code,
                             grpc.StatusCode.DEADLINE_EXCEEDED)
        asyncio.run(run())


class AsyncClientTest(ServerTestCase):
    """kinetri_client.aio.AsyncClient end to end against the real server,
    checked against brute force."""

    def test_lifecycle(self):
        import asyncio
        from kinetri_client.aio import AsyncClient
        rng = np.random.default_rng(5)
        pts = rng.random((800, 2))
        deltas = rng.normal(0, 1e-3, (800, 2))

        async def run():
            async with AsyncClient(self.target, chunk_points=300) as c:
                s = await c.create_session(pts, session_id="py-async")
                async with await c.open_steps(s.name) as steps:
                    ack = await steps.move_by(deltas)
                    self.assertEqual(ack.step, 1)
                    ack = await steps.move_to([[0.5, 0.5]], ids=[3])
                    self.assertEqual(ack.step, 2)
                moved = pts + deltas
                moved[3] = [0.5, 0.5]
                step, positions, triangles = await c.export(s.name)
                self.assertEqual(step, 2)
                np.testing.assert_array_equal(positions, moved)
                nn = await c.nearest_all(s.name)
                d = ((moved[:, None, :] - moved[None, :, :]) ** 2).sum(-1)
                np.fill_diagonal(d, np.inf)
                np.testing.assert_array_equal(
                    [nn.row(i)[0] for i in range(len(nn))], d.argmin(1))
                near = await c.radius(s.name, 0.05, points=[[0.5, 0.5]])
                want = np.flatnonzero(((moved - 0.5) ** 2).sum(1) <= 0.05**2)
                self.assertEqual(sorted(near.row(0)), sorted(want))
                names = [x.name for x in await c.list_sessions()]
                self.assertIn(s.name, names)
                await c.delete_session(s.name)
                with self.assertRaises(KinetriError) as e:
                    await c.get_session(s.name)
                self.assertEqual(e.exception.code, grpc.StatusCode.NOT_FOUND)
                # A step the server refuses ends the stream with its status.
                s = await c.create_session(pts, session_id="py-async-2")
                steps = await c.open_steps(s.name)
                with self.assertRaises(KinetriError) as e:
                    await steps.move_by(np.full((800, 2), np.nan))
                self.assertEqual(e.exception.code,
                                 grpc.StatusCode.INVALID_ARGUMENT)
        asyncio.run(run())
