"""Turns kinetri-bench JSON into the Markdown tables of docs/BENCHMARKS.md.

Usage: /usr/bin/python3 bench/bench_table.py results.json [N]
Prints, for each workload at size N (default: the largest), the median
milliseconds per step of every engine and phase.
"""

import json
import sys
from collections import defaultdict

ENGINES = ["kinetri", "kinetri-1t", "cgal-rebuild", "grid", "nanoflann"]
PHASES = ["update", "all_nn", "knn8", "radius8", "radius32"]


def main(path, n=None):
    doc = json.load(open(path))
    recs = doc["records"]
    if n is None:
        n = max(r["n"] for r in recs)
    table = defaultdict(dict)
    for r in recs:
        if r["n"] == n:
            table[(r["workload"], r["param"], r["phase"])][r["engine"]] = r
    m = doc["machine"]
    print(f"Machine: {m['cpu']}, {m['cores']} cores, commit {m['commit']}; "
          f"n = {n}; median (p90) ms per step.\n")
    print("| workload | param | phase | " + " | ".join(ENGINES) + " |")
    print("|" + "---|" * (3 + len(ENGINES)))
    for key in sorted(table, key=lambda k: (k[0], k[1], PHASES.index(k[2]))):
        row = table[key]
        cells = [f"{row[e]['median_ms']:.2f} ({row[e]['p90_ms']:.2f})"
                 if e in row else "" for e in ENGINES]
        print(f"| {key[0]} | {key[1]} | {key[2]} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]) if len(sys.argv) > 2 else None)
