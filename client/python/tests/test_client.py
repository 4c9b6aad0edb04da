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
            # The same rows in fixed-width fields.
            req.encoding = pb.ANSWER_ENCODING_FIXED
            fixed = c.query(req)
            np.testing.assert_array_equal(fixed.offsets, whole.offsets)
            np.testing.assert_array_equal(fixed.ids, whole.ids)
            np.testing.assert_array_equal(fixed.distances, whole.distances)
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


class StreamQueryTest(ServerTestCase):
    """Query targets beyond one message go by StreamQuery (sync and
    asyncio); the answers equal brute force."""

    def test_many_targets(self):
        import asyncio
        from kinetri_client.aio import AsyncClient
        rng = np.random.default_rng(12)
        pts = rng.random((1500, 2))
        q = rng.random((2500, 2))
        ids = np.arange(0, 1500, 1)
        with Client(self.target, chunk_points=200) as c:
            s = c.create_session(pts)
            knn = c.knn(s.name, 3, points=q)
            self.assertEqual(len(knn.offsets), len(q) + 1)
            for r in range(0, len(q), 17):
                want, _ = rank(pts, q[r])
                self.assertTrue(np.array_equal(knn.row(r), want[:3]), r)
            by_id = c.knn(s.name, 2, ids=ids)
            for r in range(0, len(ids), 13):
                want, _ = rank(pts, pts[ids[r]], skip=ids[r])
                self.assertTrue(np.array_equal(by_id.row(r), want[:2]), r)

            async def run():
                async with AsyncClient(self.target, chunk_points=200) as a:
                    return await a.knn(s.name, 3, points=q)
            aknn = asyncio.run(run())
            self.assertTrue(np.array_equal(aknn.ids, knn.ids))
            c.delete_session(s.name)


class MalformedAnswerTest(unittest.TestCase):
    """A chunk that carries offsets, ids or client ids in both encodings
    is no answer a server writes: both clients (sync and asyncio) refuse it
    with INTERNAL, as the C++ client does. A fake server writes them."""

    def test_a_field_in_both_encodings_is_refused(self):
        import asyncio
        from concurrent import futures
        from kinetri_client._common import pb, pb_grpc, query_request
        from kinetri_client.aio import AsyncClient
        good = dict(offsets=[0, 1], ids=[4])
        bad = [dict(offsets=[0, 1], fixed_offsets=[0, 1], ids=[4]),
               dict(offsets=[0, 1], ids=[4], fixed_ids=[4]),
               dict(fixed_offsets=[0, 1], client_ids=[4],
                    fixed_client_ids=[4])]
        chunk = good

        class Fake(pb_grpc.KinetriServiceServicer):
            def Query(self, request, context):
                yield pb.QueryResponse(step=3, **chunk)
                yield pb.QueryResponse(step=3, offsets=[0, 1], ids=[5])

        server = grpc.server(futures.ThreadPoolExecutor(max_workers=4))
        pb_grpc.add_KinetriServiceServicer_to_server(Fake(), server)
        port = server.add_insecure_port("127.0.0.1:0")
        server.start()
        target = f"127.0.0.1:{port}"
        req = query_request("s", pb.QUERY_KIND_K_NEAREST, k=1, ids=[0])

        async def ask():
            async with AsyncClient(target) as a:
                return await a.query(req)
        try:
            with Client(target) as c:
                # Well-formed chunks are read.
                self.assertEqual(list(c.query(req).ids), [4, 5])
                self.assertEqual(list(asyncio.run(ask()).ids), [4, 5])
                for chunk in bad:
                    with self.assertRaises(KinetriError) as e:
                        c.query(req)
                    self.assertEqual(e.exception.code,
                                     grpc.StatusCode.INTERNAL, chunk)
                    self.assertIn("both as varints and fixed-width",
                                  e.exception.message)
                    with self.assertRaises(KinetriError) as e:
                        asyncio.run(ask())
                    self.assertEqual(e.exception.code,
                                     grpc.StatusCode.INTERNAL, chunk)
                    self.assertIn("both as varints and fixed-width",
                                  e.exception.message)
        finally:
            server.stop(None)


def rank(xy, q, skip=None):
    """Indices of `xy` in the order queries answer from `q`: squared
    distance, ties between distinct positions to the larger x, then the
    larger y, ties between coincident points to the smaller index (the
    server's documented total order, core/queries.h); and the squared
    distances. `skip`: an index left out (exclude_self)."""
    d2 = ((xy - q) ** 2).sum(1)
    order = np.lexsort((np.arange(len(xy)), -xy[:, 1], -xy[:, 0], d2))
    if skip is not None:
        order = order[order != skip]
    return order, d2


def hull_area(xy):
    """Area of the convex hull (monotone chain)."""
    pts = sorted(set(map(tuple, xy.tolist())))
    if len(pts) < 3:
        return 0.0

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])
    lower, upper = [], []
    for p in pts:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], p) <= 0:
            lower.pop()
        lower.append(p)
    for p in reversed(pts):
        while len(upper) >= 2 and cross(upper[-2], upper[-1], p) <= 0:
            upper.pop()
        upper.append(p)
    h = np.array(lower[:-1] + upper[:-1])
    x, y = h[:, 0], h[:, 1]
    return 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


class JoinLeaveTest(ServerTestCase):
    """Points that join and leave with steps (StepRequest remove/add), on
    both id policies: after every step the session equals a numpy model of
    the documented numbering (survivors renumbered in order, joining points
    after them; client ids unchanged), and queries equal brute force on
    the model."""

    def check_state(self, c, name, step, xy, ids):
        """Session, export, triangulation and queries against the model:
        positions `xy` in id order, `ids` each point's id (uint64)."""
        n = len(xy)
        client = not np.array_equal(ids, np.arange(n, dtype=np.uint64))
        s = c.get_session(name)
        self.assertEqual(s.step, step)
        self.assertEqual(s.point_count, n)
        self.assertEqual(s.site_count, len(np.unique(xy, axis=0)))
        ex = c.export(name)
        self.assertEqual(ex.step, step)
        np.testing.assert_array_equal(ex.positions, xy)
        np.testing.assert_array_equal(ex.ids, ids)
        self.check_delaunay(xy, ex.triangles)

        def name_of(idx):  # model indices -> ids as queries name points
            return ids[idx] if client else idx
        # k nearest of points named by id (exclude_self).
        sel = np.arange(0, n, 9)
        knn = c.knn(name, 5, ids=name_of(sel))
        self.assertEqual(knn.step, step)
        self.assertEqual(len(knn), len(sel))
        for row, i in enumerate(sel):
            order, d2 = rank(xy, xy[i], skip=i)
            np.testing.assert_array_equal(knn.row(row), ids[order[:5]],
                                          f"knn row {row} (point {i})")
        # k nearest of positions, one on the model's most crowded site.
        uniq, inverse, counts = np.unique(xy, axis=0, return_inverse=True,
                                          return_counts=True)
        crowded = uniq[np.argmax(counts)]
        q = np.vstack([np.random.default_rng(step).random((15, 2)),
                       crowded[None, :]])
        knq = c.knn(name, 4, points=q)
        for row in range(len(q)):
            order, d2 = rank(xy, q[row])
            np.testing.assert_array_equal(knq.row(row), ids[order[:4]],
                                          f"knn of position {q[row]}")
        # Radius (inclusive, closest first) of points named by id.
        r = 0.07
        sel = np.arange(0, n, 13)
        rad = c.radius(name, r, ids=name_of(sel))
        for row, i in enumerate(sel):
            order, d2 = rank(xy, xy[i], skip=i)
            inside = order[d2[order] <= r * r]
            np.testing.assert_array_equal(rad.row(row), ids[inside],
                                          f"radius row {row} (point {i})")
            np.testing.assert_allclose(
                rad.distances[rad.offsets[row]:rad.offsets[row + 1]],
                np.sqrt(d2[inside]), rtol=1e-12, atol=1e-15)
        # Nearest neighbour of every point.
        nn = c.nearest_all(name)
        self.assertEqual(len(nn), n)
        want = [ids[rank(xy, xy[i], skip=i)[0][0]] for i in range(n)]
        got = [nn.row(i)[0] for i in range(n)]
        np.testing.assert_array_equal(got, want)

    def check_delaunay(self, xy, tris):
        """The exported mesh: corners are the smallest index of each
        distinct position, every one used; counter-clockwise triangles that
        tile the convex hull and have empty circumcircles."""
        _, first = np.unique(xy, axis=0, return_index=True)
        self.assertEqual(set(tris.ravel().tolist()), set(first.tolist()))
        a, b, d = (xy[tris[:, k].astype(np.int64)] for k in range(3))
        area2 = ((b[:, 0] - a[:, 0]) * (d[:, 1] - a[:, 1]) -
                 (b[:, 1] - a[:, 1]) * (d[:, 0] - a[:, 0]))
        self.assertTrue((area2 > 0).all(), "triangles not counter-clockwise")
        self.assertAlmostEqual(area2.sum() / 2, hull_area(xy), places=9)
        sites = xy[np.sort(first)]
        for lo in range(0, len(tris), 256):
            A, B, D = (m[lo:lo + 256, None, :] - sites[None, :, :]
                       for m in (a, b, d))
            la, lb, ld = ((m ** 2).sum(-1) for m in (A, B, D))
            ax, ay, bx, by, dx, dy = (m[..., k] for m in (A, B, D)
                                      for k in (0, 1))

            incircle = (ax * (by * ld - lb * dy) - ay * (bx * ld - lb * dx) +
                        la * (bx * dy - by * dx))
            ax, ay, bx, by, dx, dy = map(np.abs, (ax, ay, bx, by, dx, dy))
            bound = (ax * (by * ld + lb * dy) + ay * (bx * ld + lb * dx) +
                     la * (bx * dy + by * dx))
            inside = incircle > 1e-9 * bound
            self.assertFalse(inside.any(), "a site inside a circumcircle")

    def run_join_leave(self, client: bool):
        rng = np.random.default_rng(31 if client else 30)
        n = 500
        xy = rng.random((n, 2))
        ids = (np.arange(n, dtype=np.uint64) * 7919 + (1 << 40)) if client \
            else np.arange(n, dtype=np.uint64)
        next_cid = 1 << 50
        left_earlier = []  # client ids that left in an earlier step
        # Few points per message: moves, removals and additions of one step
        # span several chunks.
        with Client(self.target, chunk_points=37) as c:
            s = c.create_session(xy, ids=ids if client else None)
            name = s.name
            steps = c.open_steps(name)

            def named(idx):
                return ids[idx] if client else idx
            for step in range(1, 9):
                count = len(xy)
                gone = rng.choice(count, size=int(rng.integers(5, 40)),
                                  replace=False)
                keep = np.ones(count, bool)
                keep[gone] = False
                moved = xy.copy()
                kind = step % 4
                if kind == 0:  # dense deltas (leaving points' ignored)
                    values = rng.normal(0, 2e-3, (count, 2))
                    mids = None
                    moved += values
                elif kind in (1, 2):  # sparse deltas / positions
                    mids = np.flatnonzero(keep)[step % 11::11]
                    if kind == 1:
                        values = rng.normal(0, 5e-3, (len(mids), 2))
                        moved[mids] += values
                    else:
                        values = rng.random((len(mids), 2))
                        moved[mids] = values
                else:  # no moves
                    values = mids = None
                stay = moved[keep]
                # Joining points: inside, outside the hull, on a remaining
                # point (twice), where a leaving point was, and on each
                # other.
                m = int(rng.integers(10, 60))
                add = rng.random((m, 2))
                add[0] = [-0.5 - 0.25 * step, 1.0 + 0.3 * step]
                add[1] = [2.0 + 0.1 * step, -0.1 * step]
                add[2] = add[3] = stay[int(rng.integers(len(stay)))]
                add[4] = xy[gone[0]]  # a leaving point never moves
                add[5] = add[6]
                if client:
                    add_ids = np.arange(next_cid, next_cid + m,
                                        dtype=np.uint64)
                    next_cid += m
                    # A leaving id joins again at once, and one that left
                    # in an earlier step joins again now.
                    add_ids[-1] = ids[gone[0]]
                    if left_earlier:
                        add_ids[-2] = left_earlier.pop(0)
                    left_earlier += ids[gone[1:3]].tolist()
                else:
                    add_ids = None
                remove = named(gone)
                if kind == 0:
                    ack = steps.move_by(values, add=add, add_ids=add_ids,
                                        remove=remove)
                elif kind == 1:
                    ack = steps.move_by(values, ids=named(mids), add=add,
                                        add_ids=add_ids, remove=remove)
                elif kind == 2:
                    ack = steps.move_to(values, ids=named(mids), add=add,
                                        add_ids=add_ids, remove=remove)
                else:
                    ack = steps.change(add=add, add_ids=add_ids,
                                       remove=remove)
                    self.assertEqual(ack.stats.moved_points, 0)
                xy = np.vstack([stay, add])
                ids = np.concatenate([ids[keep], add_ids]) if client else \
                    np.arange(len(xy), dtype=np.uint64)
                self.assertEqual(ack.step, step)
                self.assertEqual(ack.stats.removed_points, len(gone))
                self.assertEqual(ack.stats.added_points, m)
                self.assertEqual(ack.stats.point_count, len(xy))
                if not client:
                    self.assertEqual(ack.stats.first_added_id, len(stay))
                with self.subTest(step=step, kind=kind):
                    self.check_state(c, name, step, xy, ids)
            steps.close()
            self.check_refusals(c, name, client, xy, ids)
            c.delete_session(name)

    def check_refusals(self, c, name, client, xy, ids):
        """Refused steps end the stream with their status and change
        nothing."""
        n = len(xy)
        step = c.get_session(name).step

        def refused(code, **kw):
            with c.open_steps(name) as steps:
                with self.assertRaises(KinetriError) as e:
                    if "values" in kw:
                        values = kw.pop("values")
                        steps.move_by(values, **kw)
                    else:
                        steps.change(**kw)
                self.assertEqual(e.exception.code, code, e.exception)
            s = c.get_session(name)
            self.assertEqual((s.step, s.point_count), (step, n))
            return e.exception.message
        if client:
            known = [int(ids[1]), int(ids[2])]
            refused(grpc.StatusCode.NOT_FOUND, remove=[123456789])
            refused(grpc.StatusCode.NOT_FOUND, remove=[known[0], 5])
            # An id that stays cannot join again.
            refused(grpc.StatusCode.ALREADY_EXISTS, add=[[0.25, 0.25]],
                    add_ids=[known[0]])
            refused(grpc.StatusCode.ALREADY_EXISTS, add=[[0.25, 0.25]],
                    add_ids=[known[1]], remove=[known[0]])
            refused(grpc.StatusCode.INVALID_ARGUMENT,
                    add=[[0.1, 0.1], [0.2, 0.2]], add_ids=[77, 77])
            refused(grpc.StatusCode.INVALID_ARGUMENT,
                    remove=[known[0], known[1], known[0]])
            # Every joining point needs its id.
            refused(grpc.StatusCode.INVALID_ARGUMENT, add=[[0.25, 0.25]])
            refused(grpc.StatusCode.INVALID_ARGUMENT, values=[[0.01, 0.0]],
                    ids=[known[1]], remove=[known[1]])
        else:
            refused(grpc.StatusCode.NOT_FOUND, remove=[n])
            refused(grpc.StatusCode.NOT_FOUND, remove=[3, n + 10])
            # Sequential sessions number joining points themselves.
            refused(grpc.StatusCode.INVALID_ARGUMENT, add=[[0.25, 0.25]],
                    add_ids=[7])
            refused(grpc.StatusCode.INVALID_ARGUMENT, remove=[4, 9, 4])
            refused(grpc.StatusCode.INVALID_ARGUMENT, values=[[0.01, 0.0]],
                    ids=[6], remove=[6])
        refused(grpc.StatusCode.INVALID_ARGUMENT, add=[[0.25, np.nan]],
                add_ids=[99] if client else None)
        # Checked before anything is sent.
        with c.open_steps(name) as steps:
            for kw in (dict(add=[0.5, 0.5]), dict(add=np.zeros((2, 3))),
                       dict(add=[[0.5, 0.5]], add_ids=[1, 2]),
                       dict(add_ids=[5]),
                       dict(add=[[0.5, 0.5]], add_ids=[-1]),
                       dict(add=[[0.5, 0.5]], add_ids=[2 ** 64]),
                       dict(add=[[0.5, 0.5]], add_ids=[[1]]),
                       dict(add=[[0.5, 0.5]], add_ids=[1.5])):
                with self.assertRaises(ValueError, msg=str(kw)):
                    steps.change(**kw)
            for bad in ([-1], [] if client else [1 << 32]):
                if not bad:
                    continue
                with self.assertRaises(KinetriError) as e:
                    steps.change(remove=bad)
                self.assertEqual(e.exception.code, grpc.StatusCode.NOT_FOUND)
            self.assertEqual(steps.next_step, step + 1)
        self.assertEqual(c.get_session(name).step, step)

    def test_sequential_ids(self):
        self.run_join_leave(client=False)

    def test_client_ids(self):
        self.run_join_leave(client=True)

    def test_emptied_and_refilled(self):
        """Down to no points, then a line, then a triangle again; the
        client's cached id policy and the export of an empty session."""
        cids = np.array([10, 20, 30, 40, 50], dtype=np.uint64)
        pts = np.random.default_rng(3).random((5, 2))
        with Client(self.target) as c:
            s = c.create_session(pts, ids=cids)
            self.assertEqual(len(c.knn(s.name, 1, ids=[30]).row(0)), 1)
            with c.open_steps(s.name) as steps:
                ack = steps.change(remove=cids[::-1])
                self.assertEqual(ack.stats.point_count, 0)
                self.assertEqual(c.get_session(s.name).point_count, 0)
                ex = c.export(s.name)
                self.assertEqual((ex.positions.shape, len(ex.ids),
                                  len(ex.triangles)), ((0, 2), 0, 0))
                line = [[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]]
                ack = steps.change(add=line, add_ids=[30, 31, 32])
                self.assertEqual(ack.stats.point_count, 3)
                knn = c.knn(s.name, 2, ids=[30])
                np.testing.assert_array_equal(knn.row(0), [31, 32])
                ack = steps.move_by([[0.0, 1.0]], ids=[32], add=[[2.0, 0.0]],
                                    add_ids=[10], remove=[31])
                self.assertEqual(ack.stats.point_count, 3)
            ex = c.export(s.name)
            np.testing.assert_array_equal(ex.ids, [30, 32, 10])
            np.testing.assert_array_equal(
                ex.positions, [[0.0, 0.0], [2.0, 3.0], [2.0, 0.0]])
            self.assertEqual(len(ex.triangles), 1)
            self.check_delaunay(ex.positions, ex.triangles)
            c.delete_session(s.name)

    def test_resent_changes_are_idempotent(self):
        """A step of joins and leaves resent under its request_id (its
        acknowledgement was lost) gets the original acknowledgement
        (StepRequest.request_id) and applies nothing, also after a later
        step."""
        rng = np.random.default_rng(12)
        pts = rng.random((200, 2))
        add = rng.random((5, 2))
        with Client(self.target) as c:
            s = c.create_session(pts, session_id="py-change-idem")
            with c.open_steps(s.name) as steps:
                ack = steps.change(add=add, remove=[0, 1], request_id="j-1")
            with c.open_steps(s.name, first_step=1) as steps:
                again = steps.change(add=add, remove=[0, 1],
                                     request_id="j-1")
            self.assertEqual(again, ack)
            self.assertEqual(c.get_session(s.name).point_count, 203)
            with c.open_steps(s.name) as steps:
                ack2 = steps.change(add=add[:3], request_id="j-2")
            self.assertEqual(ack2.stats.point_count, 206)
            # The original acknowledgement, also after a later step.
            with c.open_steps(s.name, first_step=1) as steps:
                again = steps.change(add=add, remove=[0, 1],
                                     request_id="j-1")
            self.assertEqual(again.stats.point_count, 203)
            self.assertEqual(again.stats.first_added_id, 198)
            self.assertEqual(again, ack)
            ex = c.export(s.name)
            np.testing.assert_array_equal(
                ex.positions, np.vstack([pts[2:], add, add[:3]]))
            c.delete_session(s.name)

    def test_chunks(self):
        """step_requests: every list split over messages of at most
        chunk_points entries (moves first, then removals, then additions),
        request_id on the first, end_of_step on the last; what the chunks
        carry concatenates to the step."""
        from kinetri_client._common import CHUNK_POINTS, pb, step_requests
        rng = np.random.default_rng(2)
        for client in (False, True):
            for nv, nr, na in ((0, 0, 0), (25, 0, 0), (0, 7, 0), (0, 0, 9),
                               (10, 3, 4), (7, 7, 7), (31, 12, 50)):
                values = rng.random((nv, 2))
                ids = rng.permutation(1000)[:nv] if nv % 2 else None
                remove = rng.permutation(1000)[:nr]
                add = rng.random((na, 2))
                add_ids = np.arange(na) + 5000 if client else None
                reqs = step_requests("sessions/x", 4,
                                     pb.DISPLACEMENT_MODE_ABSOLUTE,
                                     values if nv else None, ids, client, 7,
                                     "rid", add=add, add_ids=add_ids,
                                     remove=remove)
                total = nv + nr + na
                self.assertEqual(len(reqs), max(1, -(-total // 7)))
                self.assertEqual([r.request_id for r in reqs],
                                 ["rid"] + [""] * (len(reqs) - 1))
                self.assertEqual([r.end_of_step for r in reqs],
                                 [False] * (len(reqs) - 1) + [True])
                for r in reqs:
                    self.assertEqual((r.step, r.session, r.mode),
                                     (4, "sessions/x",
                                      pb.DISPLACEMENT_MODE_ABSOLUTE))
                    self.assertLessEqual(
                        len(r.xy) // 2 + len(r.remove_ids) +
                        len(r.remove_client_ids) + len(r.add_xy) // 2, 7)

                def cat(field):
                    return [v for r in reqs for v in getattr(r, field)]
                self.assertEqual(cat("xy"), values.ravel().tolist())
                self.assertEqual(cat("client_ids" if client else "ids"),
                                 [] if ids is None else ids.tolist())
                self.assertEqual(
                    cat("remove_client_ids" if client else "remove_ids"),
                    remove.tolist())
                self.assertEqual(cat("add_xy"), add.ravel().tolist())
                self.assertEqual(cat("add_client_ids"),
                                 [] if add_ids is None else add_ids.tolist())
        # At the default chunk size, no message reaches 4 MiB.
        big = CHUNK_POINTS + 1000
        reqs = step_requests(
            "sessions/x", 1, pb.DISPLACEMENT_MODE_DELTA,
            np.ones((big, 2)), np.arange(big) + (1 << 60), True,
            CHUNK_POINTS, add=np.ones((big, 2)),
            add_ids=np.arange(big) + (1 << 62),
            remove=np.arange(big) + (1 << 61))
        self.assertEqual(len(reqs), 4)
        self.assertLess(max(r.ByteSize() for r in reqs), 4 << 20)


class AsyncJoinLeaveTest(ServerTestCase):
    """AsyncStepStream.change and points joining with moves, asyncio."""

    def test_change(self):
        import asyncio
        from kinetri_client.aio import AsyncClient
        rng = np.random.default_rng(17)
        pts = rng.random((120, 2))
        cids = np.arange(120, dtype=np.uint64) * 3 + (1 << 33)

        async def run():
            async with AsyncClient(self.target, chunk_points=16) as c:
                s = await c.create_session(pts, ids=cids)
                add = rng.random((30, 2))
                add[0] = pts[7]
                add_ids = np.arange(30, dtype=np.uint64) + (1 << 45)
                add_ids[1] = cids[3]  # leaves and joins again
                gone = [3, 50, 51, 119]
                async with await c.open_steps(s.name) as steps:
                    ack = await steps.change(add=add, add_ids=add_ids,
                                             remove=cids[gone])
                    self.assertEqual(ack.step, 1)
                    self.assertEqual(ack.stats.moved_points, 0)
                    self.assertEqual((ack.stats.removed_points,
                                      ack.stats.added_points,
                                      ack.stats.point_count), (4, 30, 146))
                    keep = np.ones(120, bool)
                    keep[gone] = False
                    xy = np.vstack([pts[keep], add])
                    ids = np.concatenate([cids[keep], add_ids])
                    # Moves by client id with a leaving point.
                    ack = await steps.move_to([[0.5, 0.5]], ids=[ids[0]],
                                              remove=[ids[1]])
                    self.assertEqual(ack.stats.point_count, 145)
                    xy[0] = [0.5, 0.5]
                    xy, ids = np.delete(xy, 1, 0), np.delete(ids, 1)
                    # Removal only, then addition only.
                    ack = await steps.change(remove=[ids[-1]])
                    xy, ids = xy[:-1], ids[:-1]
                    ack = await steps.change(add=[[0.5, 0.5]], add_ids=[5])
                    self.assertEqual((ack.step, ack.stats.point_count),
                                     (4, 145))
                    xy = np.vstack([xy, [[0.5, 0.5]]])
                    ids = np.append(ids, np.uint64(5))
                ex = await c.export(s.name)
                self.assertEqual(ex.step, 4)
                np.testing.assert_array_equal(ex.positions, xy)
                np.testing.assert_array_equal(ex.ids, ids)
                knn = await c.knn(s.name, 3, ids=ids[::10])
                for row, i in enumerate(range(0, len(xy), 10)):
                    order, _ = rank(xy, xy[i], skip=i)
                    np.testing.assert_array_equal(knn.row(row),
                                                  ids[order[:3]])
                near = await c.radius(s.name, 0.1, points=[[0.5, 0.5]])
                order, d2 = rank(xy, np.array([0.5, 0.5]))
                np.testing.assert_array_equal(
                    near.row(0), ids[order[d2[order] <= 0.01]])
                # A refused change ends the stream with its status.
                steps = await c.open_steps(s.name)
                with self.assertRaises(KinetriError) as e:
                    await steps.change(add=[[0.1, 0.1]], add_ids=[5])
                self.assertEqual(e.exception.code,
                                 grpc.StatusCode.ALREADY_EXISTS)
                await steps.close()
                self.assertEqual((await c.get_session(s.name)).step, 4)
                await c.delete_session(s.name)
                # Sequential: joining points numbered after the others.
                s = await c.create_session(pts)
                async with await c.open_steps(s.name) as steps:
                    ack = await steps.change(add=[[2.0, 2.0]], remove=[0])
                    self.assertEqual((ack.stats.first_added_id,
                                      ack.stats.point_count), (119, 120))
                ex = await c.export(s.name)
                np.testing.assert_array_equal(
                    ex.positions, np.vstack([pts[1:], [[2.0, 2.0]]]))
                await c.delete_session(s.name)
        asyncio.run(run())


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
