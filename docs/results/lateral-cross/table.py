"""Success of each lateral ego and of the IDM driver in the ego's seat per flow (all four
scenarios), and each ego's paired effect against the IDM driver on the same starts (the two
evaluation seeds of a stored case averaged: 400 starts; normal-approximation p), one table per
run of the learned flows (seeds 7 and 8).

    python3 docs/results/lateral-cross/table.py
"""

import csv
import math
import statistics
from collections import defaultdict
from pathlib import Path

HERE = Path(__file__).resolve().parent


def table(results):
    by = defaultdict(lambda: defaultdict(list))
    with open(results / "episodes.csv") as f:
        for r in csv.DictReader(f):
            by[(r["ego"], r["flow"])][(r["scenario"], r["case"])].append(float(r["success"]))
    egos = sorted({e for e, _ in by if e != "IDM ego"}) + ["IDM ego"]
    flows = ["IDM", "MACAD", "SocialComm"]
    print("| ego | " + " | ".join(flows) + " |")
    print("|---|" + "---|" * len(flows))
    for e in egos:
        cells = []
        for fl in flows:
            mine = {k: statistics.fmean(v) for k, v in by[(e, fl)].items()}
            m = 100 * statistics.fmean(mine.values())
            if e == "IDM ego":
                cells.append(f"{m:.1f}")
                continue
            idm = {k: statistics.fmean(v) for k, v in by[("IDM ego", fl)].items()}
            d = [mine[k] - idm[k] for k in mine]
            dm, sd = statistics.fmean(d), statistics.stdev(d)
            p = math.erfc(abs(dm / (sd / math.sqrt(len(d)))) / math.sqrt(2))
            cells.append(f"{m:.1f} ({100 * dm:+.1f}, p {p:.1g})")
        print(f"| {e} | " + " | ".join(cells) + " |")


def main():
    for seed in (7, 8):
        print(f"flows of seed {seed}:")
        table(HERE / f"results-flows-seed{seed}")
        print()


if __name__ == "__main__":
    main()
