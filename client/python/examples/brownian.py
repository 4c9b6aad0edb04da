"""Moves 10 000 points by Brownian steps through kinetri-server and prints
nearest-neighbour statistics. Usage: python3 brownian.py [host:port]"""

import sys
import time

import numpy as np

from kinetri_client import Client


def main(target: str) -> None:
    rng = np.random.default_rng(1)
    n = 10_000
    points = rng.random((n, 2))
    with Client(target) as client:
        session = client.create_session(points)
        print(f"created {session.name} with {session.point_count} points")
        steps = client.open_steps(session.name)
        for s in range(20):
            t0 = time.perf_counter()
            ack = steps.move_by(rng.normal(0, 0.1 / np.sqrt(n), (n, 2)))
            nn = client.nearest_all(session.name)
            print(f"step {ack.step}: {ack.stats.path}, "
                  f"{ack.stats.delaunay_flips} flips, mean NN distance "
                  f"{nn.distances.mean():.5f}, "
                  f"{1e3 * (time.perf_counter() - t0):.1f} ms")
        steps.close()
        client.delete_session(session.name)


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "127.0.0.1:50051")
