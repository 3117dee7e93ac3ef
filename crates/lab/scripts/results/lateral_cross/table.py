"""Success of each lateral ego and of the IDM driver in the ego's seat per flow (all four
scenarios), and each ego's paired effect against the IDM driver on the same starts (the two
evaluation seeds of a stored case averaged: 400 starts; normal-approximation p, Holm-adjusted
over the 12 comparisons of a table), one table per run of the learned flows (seeds 7 and 8).

    python3 crates/lab/scripts/results/lateral_cross/table.py

Reads docs/results/lateral-cross/results-flows-seed{7,8}/episodes.csv.
"""

import csv
import math
import statistics
import sys
from collections import defaultdict
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # crates/lab/scripts
from csv_files import REPO, open_csv

DATA = REPO / "docs/results/lateral-cross"


def holm(ps):
    """Holm-adjusted p-values, in the order given."""
    order, adj, run = sorted(range(len(ps)), key=ps.__getitem__), [0.0] * len(ps), 0.0
    for rank, i in enumerate(order):
        run = adj[i] = min(1.0, max(run, (len(ps) - rank) * ps[i]))
    return adj


def table(results):
    by = defaultdict(lambda: defaultdict(list))
    with open_csv(results / "episodes.csv") as f:
        for r in csv.DictReader(f):
            by[(r["ego"], r["flow"])][(r["scenario"], r["case"])].append(float(r["success"]))
    egos = sorted({e for e, _ in by if e != "IDM ego"}) + ["IDM ego"]
    flows = ["IDM", "MACAD", "SocialComm"]
    cells, tests = {}, []
    for e in egos:
        for fl in flows:
            mine = {k: statistics.fmean(v) for k, v in by[(e, fl)].items()}
            cells[(e, fl)] = f"{100 * statistics.fmean(mine.values()):.1f}"
            if e != "IDM ego":
                idm = {k: statistics.fmean(v) for k, v in by[("IDM ego", fl)].items()}
                d = [mine[k] - idm[k] for k in mine]
                dm, sd = statistics.fmean(d), statistics.stdev(d)
                tests.append(((e, fl), dm, math.erfc(abs(dm / (sd / math.sqrt(len(d)))) / math.sqrt(2))))
    for ((key, dm, p), adj) in zip(tests, holm([p for _, _, p in tests])):
        cells[key] += f" ({100 * dm:+.1f}, p {p:.2g}, Holm {adj:.2g})"
    print("| ego | " + " | ".join(flows) + " |")
    print("|---|" + "---|" * len(flows))
    for e in egos:
        print(f"| {e} | " + " | ".join(cells[(e, fl)] for fl in flows) + " |")


def main():
    for seed in (7, 8):
        print(f"flows of seed {seed}:")
        table(DATA / f"results-flows-seed{seed}")
        print()


if __name__ == "__main__":
    main()
