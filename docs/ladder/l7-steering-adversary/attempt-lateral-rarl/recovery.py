"""L7's second clause per training seed: what the RARL round recovers. Among FailMaker, the RARL
ego's success minus RL/IDM's (the recovery), and among IDM the same difference (what the round
costs where it was not trained), each paired on the same (scenario, case, seed) starts with a
95 % t interval and a paired t-test's p; the share of FailMaker's effect recovered; Holm's
correction over every p the table prints.

    python3 docs/ladder/l7-steering-adversary/attempt-lateral-rarl/recovery.py docs/ladder/l7-steering-adversary/attempt-lateral-rarl/seed-*/results/episodes.csv
"""

import csv
import math
import sys

from scipy import stats
from statsmodels.stats.multitest import multipletests


def paired(a, b):
    """Mean of b - a over the shared keys, its 95 % t half-width and the paired t-test's p."""
    keys = sorted(a.keys() & b.keys())
    d = [b[k] - a[k] for k in keys]
    n = len(d)
    mean = sum(d) / n
    sd = math.sqrt(sum((x - mean) ** 2 for x in d) / (n - 1))
    half = stats.t.ppf(0.975, n - 1) * sd / math.sqrt(n)
    p = stats.ttest_rel([b[k] for k in keys], [a[k] for k in keys]).pvalue
    return mean, half, p


def main(paths):
    rows = []
    for path in paths:
        seed = path.split("seed-")[1].split("/")[0]
        succ = {}
        with open(path) as f:
            for r in csv.DictReader(f):
                succ.setdefault((r["ego"], r["flow"]), {})[(r["scenario"], r["case"], r["seed"])] = float(r["success"])
        attack = paired(succ[("RL/IDM", "IDM")], succ[("RL/IDM", "FailMaker")])
        rec = paired(succ[("RL/IDM", "FailMaker")], succ[("RARL/FailMaker", "FailMaker")])
        cost = paired(succ[("RL/IDM", "IDM")], succ[("RARL/FailMaker", "IDM")])
        rows.append((seed, attack, rec, cost))
    adj = multipletests([x for _, a, r, c in rows for x in (a[2], r[2], c[2])], method="holm")[1]
    print("| seed | FailMaker's effect on RL/IDM (points) | RARL - RL/IDM among FailMaker (recovery) | share recovered | RARL - RL/IDM among IDM |")
    print("|---|---|---|---|---|")
    for i, (seed, a, r, c) in enumerate(rows):
        fmt = lambda x, p: f"{100 * x[0]:+.1f} +- {100 * x[1]:.1f} (p {x[2]:.1e}, Holm {p:.1e})"
        share = r[0] / -a[0] if a[0] < 0 else float("nan")
        print(f"| {seed} | {fmt(a, adj[3 * i])} | {fmt(r, adj[3 * i + 1])} | {100 * share:.0f} % | {fmt(c, adj[3 * i + 2])} |")


if __name__ == "__main__":
    main(sys.argv[1:])
