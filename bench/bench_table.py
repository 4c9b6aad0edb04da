"""Turns kinetri-bench JSON into the Markdown tables of docs/BENCHMARKS.md.

Usage: /usr/bin/python3 bench/bench_table.py results.json [N] [--all-sizes]
       [--goals]
Prints one table per workload: the median (p90) milliseconds per step of
every engine and phase at size N (default: the largest; --all-sizes: every
N); with --goals, the ratios that issues 13 (the CPU executor) and 15
(queries) set as goals, at N, computed from the same run (the service's
goal comes from kinetri-bench-service, re-inserted vertices from
kinetri_quick_bench).
"""

import json
import sys
from collections import defaultdict

ENGINES = ["kinetri", "kinetri-1t", "kinetri-rounds", "kinetri-device",
           "cgal-rebuild", "cgal-move", "grid", "grid-device", "nanoflann"]
PHASES = ["update", "all_nn", "knn8", "radius8", "radius32", "points_nn",
          "points_knn8", "points_radius8"]


def index(recs, n):
    table = defaultdict(dict)
    for r in recs:
        if r["n"] == n:
            table[(r["workload"], r["param"], r["phase"])][r["engine"]] = r
    return table


def med(table, workload, param, phase, engine):
    r = table.get((workload, param, phase), {}).get(engine)
    return r["median_ms"] if r else None


def goals(table, n):
    def ratio(a, b):
        return f"{a / b:.3f}" if a is not None and b is not None else "n/a"

    def add(*xs):
        return None if any(x is None for x in xs) else sum(xs)

    b = ("brownian", 0.1)
    c = ("clustered", 0.1)

    def step(load, engine):
        return add(med(table, *load, "update", engine),
                   med(table, *load, "all_nn", engine))

    # Issue 13 (the CPU executor).
    rows = [
        ("13. update, brownian 0.1: Kinetri / CGAL rebuild", "<= 0.125",
         ratio(med(table, *b, "update", "kinetri"),
               med(table, *b, "update", "cgal-rebuild"))),
        ("13. update, brownian 0.01: Kinetri / CGAL rebuild", "<= 0.04",
         ratio(med(table, "brownian", 0.01, "update", "kinetri"),
               med(table, "brownian", 0.01, "update", "cgal-rebuild"))),
    ]
    for load, target in ((("brownian", 0.01), "<= 1"), (b, "<= 1"),
                         (("paper", 0.0005), "<= 1"), (("shear", 0.5), "<= 2"),
                         (("vortex", 0.5), "<= 2"), (c, "<= 2")):
        rows.append((f"13. update + all-NN, {load[0]} {load[1]:g}: "
                     "Kinetri / grid (sort + all-NN)", target,
                     ratio(step(load, "kinetri"), step(load, "grid"))))
    rows.append(("13. update, brownian 0.1: 1 thread / all threads "
                 "(speed-up)", ">= 1.7",
                 ratio(med(table, *b, "update", "kinetri-1t"),
                       med(table, *b, "update", "kinetri"))))
    for load in (b, c):
        rows.append((f"15. all-points 8-NN, {load[0]} {load[1]:g}: "
                     "Kinetri / nanoflann build+query", "<= 0.333",
                     ratio(med(table, *load, "knn8", "kinetri"),
                           add(med(table, *load, "update", "nanoflann"),
                               med(table, *load, "knn8", "nanoflann")))))
    rows.append(("15. radius (32), clustered 0.1: Kinetri / grid", "< 1",
                 ratio(med(table, *c, "radius32", "kinetri"),
                       med(table, *c, "radius32", "grid"))))
    # Issue 15 (queries), on every workload of the run.
    loads = sorted({(w, p) for (w, p, _) in table})
    for load in loads:
        name = f"{load[0]} {load[1]:g}"
        rows.append((f"15. radius (8), {name}: Kinetri / grid", "< 1",
                     ratio(med(table, *load, "radius8", "kinetri"),
                           med(table, *load, "radius8", "grid"))))
        if load[0] != "clustered":
            rows.append((f"15. radius (32), {name}: Kinetri / grid", "<= 1.2",
                         ratio(med(table, *load, "radius32", "kinetri"),
                               med(table, *load, "radius32", "grid"))))
        for phase in ("points_nn", "points_knn8", "points_radius8"):
            rows.append((f"15. {phase} (positions), {name}: "
                         "Kinetri / nanoflann query alone", "< 1",
                         ratio(med(table, *load, phase, "kinetri"),
                               med(table, *load, phase, "nanoflann"))))
    print(f"\nGoals at n = {n} (ratios of medians from this run):\n")
    print("| goal | target | measured |")
    print("|---|---:|---:|")
    for name, target, got in rows:
        print(f"| {name} | {target} | {got} |")


def main(argv):
    path = argv[1]
    rest = [a for a in argv[2:] if not a.startswith("--")]
    doc = json.load(open(path))
    recs = doc["records"]
    sizes = sorted({r["n"] for r in recs})
    n = int(rest[0]) if rest else max(sizes)
    m = doc["machine"]
    print(f"Machine: {m['cpu']}, {m['cores']} cores, GPU {m['gpu'] or 'none'}, "
          f"commit {m['commit']}; median (p90) ms per step; steps measured "
          f"in the last column.\n")
    by_load = defaultdict(list)
    for r in recs:
        if "--all-sizes" in argv or r["n"] == n:
            by_load[(r["workload"], r["param"])].append(r)
    for (w, p), rs in sorted(by_load.items()):
        present = [e for e in ENGINES if any(r["engine"] == e for r in rs)]
        cell = {(r["phase"], r["n"], r["engine"]): r for r in rs}
        print(f"**{w} {p}**\n")
        print("| phase | n | " + " | ".join(present) + " | steps |")
        print("|---|---:|" + "---:|" * (len(present) + 1))
        keys = sorted({(r["phase"], r["n"]) for r in rs},
                      key=lambda k: (PHASES.index(k[0]), k[1]))
        for ph, nn in keys:
            cells, steps = [], set()
            for e in present:
                r = cell.get((ph, nn, e))
                cells.append(f"{r['median_ms']:.2f} ({r['p90_ms']:.2f})"
                             if r else "")
                if r:
                    steps.add(r["steps"])
            st = "/".join(str(x) for x in sorted(steps))
            print(f"| {ph} | {nn} | " + " | ".join(cells) + f" | {st} |")
        print()
    if "--goals" in argv:
        goals(index(recs, n), n)


if __name__ == "__main__":
    main(sys.argv)
