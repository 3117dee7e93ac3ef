"""The lateral graph's trained egos against the two scripted drivers, flow by flow.

    python3 crates/lab/scripts/results/paper_graph_lateral/references.py \
        docs/results/paper-graph-lateral/references/episodes.csv.gz > docs/results/paper-graph-lateral/references.md

For each flow: every driver's success (percent), and each trained ego's lead over the better of
the two scripted drivers (the lane-keeping IDM driver, IDM with MOBIL's lane changes) in that
flow, paired over distinct episode starts (scenario, case; a start's seeds averaged first, since
a deterministic driver among a deterministic flow repeats its episode under another seed), with
a 95 % t interval and a two-sided paired t-test; p Holm-corrected over the whole table (one
training run: the graph's seed 9).
"""

import csv
import math
import sys
from collections import defaultdict
from pathlib import Path

from scipy import stats
from statsmodels.stats.multitest import multipletests

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # crates/lab/scripts
from csv_files import open_csv

SCRIPTED = ("IDM driver", "IDM+MOBIL")


def load(path):
    """{(ego, flow): {(scenario, case): mean over seeds of (success, lane_change)}}."""
    acc = defaultdict(lambda: defaultdict(list))
    with open_csv(path) as f:
        for r in csv.DictReader(f):
            acc[(r["ego"], r["flow"])][(r["scenario"], r["case"])].append(
                (float(r["success"]), float(r.get("lane_change") or 0.0))
            )
    return {
        cell: {k: tuple(sum(x) / len(x) for x in zip(*v)) for k, v in starts.items()}
        for cell, starts in acc.items()
    }


def paired(a, b):
    keys = sorted(a.keys() & b.keys())
    d = [b[k][0] - a[k][0] for k in keys]
    n = len(d)
    mean = sum(d) / n
    sd = math.sqrt(sum((x - mean) ** 2 for x in d) / (n - 1))
    half = stats.t.ppf(0.975, n - 1) * sd / math.sqrt(n)
    p = stats.ttest_rel([b[k][0] for k in keys], [a[k][0] for k in keys]).pvalue if sd > 0 else 1.0
    return mean, half, p, n


def main(path):
    c = load(path)
    egos = list(dict.fromkeys(e for e, _ in c))
    flows = list(dict.fromkeys(f for _, f in c))
    learned = [e for e in egos if e not in SCRIPTED]
    mean = lambda e, f, i=0: 100 * sum(v[i] for v in c[(e, f)].values()) / len(c[(e, f)])
    print("## Success, % (episodes whose driver left its lane, %)\n")
    print("| flow | " + " | ".join(egos) + " |")
    print("|---|" + "---|" * len(egos))
    for f in flows:
        print(f"| {f} | " + " | ".join(f"{mean(e, f):.1f} ({mean(e, f, 1):.0f})" for e in egos) + " |")
    rows = []
    for f in flows:
        best = max(SCRIPTED, key=lambda e: mean(e, f))
        for e in learned:
            rows.append((f, e, best, paired(c[(best, f)], c[(e, f)])))
    holm = multipletests([r[3][2] for r in rows], method="holm")[1]
    n = rows[0][3][3]
    print(f"\n## Each trained ego's lead over the better scripted driver, points ({n} starts per flow; Holm p over {len(rows)})\n")
    print("| flow | better scripted | " + " | ".join(learned) + " |")
    print("|---|---|" + "---|" * len(learned))
    for k, f in enumerate(flows):
        part = rows[k * len(learned):(k + 1) * len(learned)]
        ps = holm[k * len(learned):(k + 1) * len(learned)]
        cells = [f"{100 * m:+.1f} +- {100 * h:.1f} ({p:.2g})" for (_, _, _, (m, h, _, _)), p in zip(part, ps)]
        print(f"| {f} | {part[0][2]} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    main(sys.argv[1])
