"""The lane-change share of the lateral flows, per flow and scenario and seed, from the
re-evaluation's episodes (docs/results/lateral-flows/lanes/seed-*/episodes.csv), and a check that
the re-evaluation reproduced the first evaluation's success, safety, speed and collision exactly.

    python3 crates/lab/scripts/results/lateral_flows/lanes.py
"""

import csv
import math
import statistics
import sys
from collections import defaultdict
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # crates/lab/scripts
from csv_files import REPO, open_csv

DATA = REPO / "docs/results/lateral-flows/lanes"
METRICS = ("success", "safety", "speed", "collision")


def load(path):
    with open_csv(path) as f:
        return list(csv.DictReader(f))


def key(r):
    return (r["flow"], r["scenario"], r["case"], r["seed"])


def mean_ci(xs):
    m = statistics.fmean(xs)
    if len(xs) < 2:
        return m, float("nan")
    return m, 1.96 * statistics.stdev(xs) / math.sqrt(len(xs))


def main():
    table = defaultdict(dict)
    for seed in (7, 8):
        new = load(DATA / f"seed-{seed}" / "episodes.csv")
        old = {key(r): r for r in load(DATA.parent / f"seed-{seed}" / "results" / "episodes.csv")}
        same = sum(all(float(r[m]) == float(old[key(r)][m]) for m in METRICS) for r in new)
        print(f"seed {seed}: {same} of {len(new)} episodes identical to the first evaluation's ({len(old)} there)")
        by = defaultdict(list)
        for r in new:
            by[(r["flow"], r["scenario"])].append(float(r["lane_change"]))
        for (flow, scen), xs in by.items():
            table[(flow, scen)][seed] = mean_ci(xs)
    print()
    print("| flow | scenario | left its lane, seed 7 (%) | seed 8 (%) |")
    print("|---|---|---|---|")
    for (flow, scen), per in table.items():
        cells = [f"{100 * m:.1f} ± {100 * ci:.1f}" for m, ci in (per[7], per[8])]
        print(f"| {flow} | {scen} | {cells[0]} | {cells[1]} |")


if __name__ == "__main__":
    main()
