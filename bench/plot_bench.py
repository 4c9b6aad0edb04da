"""Plots kinetri-bench JSON: cost per step vs N, log-log, one SVG per workload.

Usage: /usr/bin/python3 bench/plot_bench.py results.json OUT_DIR
Needs gnuplot (Debian: gnuplot-nox). For each workload it writes
OUT_DIR/step_<workload>_<param>.svg with one line per engine: the median of
update + all-points NN per step (CGAL engines: update only, they answer no
query themselves), and OUT_DIR/radius32_<workload>_<param>.svg with the
radius phase (mean 32 neighbours).
"""

import json
import os
import subprocess
import sys
from collections import defaultdict

STYLE = {
    "kinetri": ("Kinetri (all cores)", 1),
    "kinetri-1t": ("Kinetri (1 thread)", 2),
    "cgal-rebuild": ("CGAL rebuild (update only)", 3),
    "cgal-move": ("CGAL move() (update only)", 4),
    "grid": ("uniform grid", 6),
    "nanoflann": ("nanoflann k-d tree", 7),
}


def series(recs, phases):
    """{(workload, param): {engine: [(n, ms)]}} summing the given phases."""
    acc = defaultdict(lambda: defaultdict(dict))
    for r in recs:
        if r["phase"] in phases:
            key = (r["workload"], r["param"])
            acc[key][r["engine"]].setdefault(r["n"], {})[r["phase"]] = r[
                "median_ms"]
    out = defaultdict(dict)
    for key, engines in acc.items():
        for e, by_n in engines.items():
            pts = []
            for n, ph in sorted(by_n.items()):
                # An engine missing a phase (CGAL: no queries) plots what it has.
                pts.append((n, sum(ph.values())))
            out[key][e] = pts
    return out


def plot(path, title, ylabel, engines):
    lines, data = [], []
    for e, pts in engines.items():
        if e not in STYLE or len(pts) < 1:
            continue
        label, color = STYLE[e]
        lines.append(f"'-' using 1:2 with linespoints lw 2 pt 7 lc {color} "
                     f"title '{label}'")
        data.append("\n".join(f"{n} {ms}" for n, ms in pts) + "\ne")
    if not lines:
        return False
    script = "\n".join([
        "set terminal svg size 720,480 dynamic background rgb 'white' "
        "font 'sans,12'",
        f"set output '{path}'",
        f"set title '{title}'",
        "set logscale xy",
        "set xlabel 'points (N)'",
        f"set ylabel '{ylabel}'",
        "set key top left",
        "set grid",
        "plot " + ", ".join(lines),
    ] + data) + "\n"
    subprocess.run(["gnuplot"], input=script.encode(), check=True)
    return True


def main(path, out_dir):
    doc = json.load(open(path))
    recs = doc["records"]
    os.makedirs(out_dir, exist_ok=True)
    m = doc["machine"]
    written = []
    for key, engines in sorted(series(recs, {"update", "all_nn"}).items()):
        name = f"step_{key[0]}_{key[1]}.svg"
        if plot(os.path.join(out_dir, name),
                f"{key[0]} {key[1]}: update + all-points NN per step "
                f"({m['cores']} cores)", "ms per step (median)", engines):
            written.append(name)
    for key, engines in sorted(series(recs, {"radius32"}).items()):
        name = f"radius32_{key[0]}_{key[1]}.svg"
        if plot(os.path.join(out_dir, name),
                f"{key[0]} {key[1]}: all-points radius, mean 32 neighbours",
                "ms per step (median)", engines):
            written.append(name)
    for w in written:
        print(os.path.join(out_dir, w))


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    main(sys.argv[1], sys.argv[2])
