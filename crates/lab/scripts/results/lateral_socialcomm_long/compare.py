"""SocialComm with twice the budget against the same seed's 24k-update SocialComm, MACAD and the
all-IDM flow, on the same starts (100 stored cases x 2 seeds x 4 scenarios), paired per start
(the two evaluation seeds of a stored case averaged: 400 starts; normal-approximation p, Holm over
each run's three comparisons), each training run on its own.

    python3 crates/lab/scripts/results/lateral_socialcomm_long/compare.py

Reads docs/results/lateral-socialcomm-long/seed-{7,8}/results/episodes.csv and the first run's
docs/results/lateral-flows/seed-{7,8}/results/episodes.csv.
"""

import csv
import math
import statistics
import sys
from collections import defaultdict
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # crates/lab/scripts
from csv_files import REPO, open_csv

DATA = REPO / "docs/results/lateral-socialcomm-long"
FIRST = DATA.parent / "lateral-flows"


def per_start(path, flow, metric="success"):
    by = defaultdict(list)
    with open_csv(path) as f:
        for r in csv.DictReader(f):
            if r["experiment"] == "flow_quality" and r["flow"] == flow:
                by[(r["scenario"], r["case"])].append(float(r[metric]))
    return {k: statistics.fmean(v) for k, v in by.items()}


def paired(a, b):
    keys = sorted(a.keys() & b.keys())
    d = [a[k] - b[k] for k in keys]
    m, sd = statistics.fmean(d), statistics.stdev(d)
    t = m / (sd / math.sqrt(len(d)))
    p = math.erfc(abs(t) / math.sqrt(2))  # normal approximation, n = 400
    return 100 * m, 100 * 1.96 * sd / math.sqrt(len(d)), p, len(d)


def main():
    print("| seed | SocialComm-long | vs IDM | vs SocialComm (24k) | vs MACAD (24k) | left its lane |")
    print("|---|---|---|---|---|---|")
    for seed in (7, 8):
        new = DATA / f"seed-{seed}" / "results" / "episodes.csv"
        old = FIRST / f"seed-{seed}" / "results" / "episodes.csv"
        long_ = per_start(new, "SocialComm-long")
        lanes = per_start(new, "SocialComm-long", "lane_change")
        cells = [f"{100 * statistics.fmean(long_.values()):.1f}"]
        tests = [paired(long_, per_start(path, other)) for other, path in (("IDM", new), ("SocialComm", old), ("MACAD", old))]
        # Holm over the run's three comparisons: the k-th smallest p times (3 - k), kept monotone.
        adj, run = {}, 0.0
        for rank, k in enumerate(sorted(range(3), key=lambda k: tests[k][2])):
            run = adj[k] = min(1.0, max(run, (3 - rank) * tests[k][2]))
        for k, (m, ci, p, _) in enumerate(tests):
            cells.append(f"{m:+.1f} ± {ci:.1f} (p {p:.1g}, Holm {adj[k]:.1g})")
        cells.append(f"{100 * statistics.fmean(lanes.values()):.1f} %")
        print(f"| {seed} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
