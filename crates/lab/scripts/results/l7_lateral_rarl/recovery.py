"""L7's second clause per training seed: what the RARL round recovers. Among FailMaker, the RARL
ego's success minus RL/IDM's (the recovery), and among IDM the same difference (what the round
costs where it was not trained), each paired on the same (scenario, case, seed) starts with a
95 % t interval and a paired t-test's p; the share of FailMaker's effect recovered; Holm's
correction over every p the table prints. `--rarl NAME` (up to twice) names the RARL egos
(default `RARL/FailMaker`); with two, the table adds the second minus the first. `--flow NAME`
names the hostile flow (default `FailMaker`).

    python3 crates/lab/scripts/results/l7_lateral_rarl/recovery.py docs/ladder/l7-steering-adversary/attempt-lateral-rarl/seed-*/results/episodes.csv.gz
"""

import argparse
import csv
import math
import sys
from pathlib import Path

from scipy import stats
from statsmodels.stats.multitest import multipletests

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # crates/lab/scripts
from csv_files import open_csv


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


def main(paths, rarl_names, fm="FailMaker"):
    """One row per (training seed, RARL ego); with two RARL egos, also the second minus the
    first, among FailMaker and among IDM (paired)."""
    rows = []
    for path in paths:
        seed = path.split("seed-")[1].split("/")[0]
        succ = {}
        with open_csv(path) as f:
            for r in csv.DictReader(f):
                succ.setdefault((r["ego"], r["flow"]), {})[(r["scenario"], r["case"], r["seed"])] = float(r["success"])
        attack = paired(succ[("RL/IDM", "IDM")], succ[("RL/IDM", fm)])
        for i, name in enumerate(rarl_names):
            rec = paired(succ[("RL/IDM", fm)], succ[(name, fm)])
            cost = paired(succ[("RL/IDM", "IDM")], succ[(name, "IDM")])
            # The attack's p is counted once per seed.
            rows.append((seed, name, attack if i == 0 else None, rec, cost, attack))
        if len(rarl_names) == 2:
            a, b = rarl_names
            among_fm = paired(succ[(a, fm)], succ[(b, fm)])
            among_idm = paired(succ[(a, "IDM")], succ[(b, "IDM")])
            rows.append((seed, f"{b} - {a}", None, among_fm, among_idm, None))
    ps = [x[2] for _, _, a, r, c, _ in rows for x in (a, r, c) if x is not None]
    adj = iter(multipletests(ps, method="holm")[1])
    fmt = lambda x: f"{100 * x[0]:+.1f} +- {100 * x[1]:.1f} (p {x[2]:.1e}, Holm {next(adj):.1e})"
    if len(rarl_names) == 1:
        print("| seed | FailMaker's effect on RL/IDM (points) | RARL - RL/IDM among FailMaker (recovery) | share recovered | RARL - RL/IDM among IDM |")
        print("|---|---|---|---|---|")
    else:
        print("| seed | RARL ego | FailMaker's effect on RL/IDM (points) | ego - RL/IDM among FailMaker (recovery) | share recovered | ego - RL/IDM among IDM |")
        print("|---|---|---|---|---|---|")
    for seed, name, a, r, c, effect in rows:
        attack = fmt(a) if a is not None else ""
        share = f"{100 * r[0] / -effect[0]:.0f} %" if effect is not None and effect[0] < 0 else ""
        lead = f"| {seed} |" if len(rarl_names) == 1 else f"| {seed} | {name} |"
        print(f"{lead} {attack} | {fmt(r)} | {share} | {fmt(c)} |")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rarl", action="append", metavar="NAME", help="a RARL ego (at most two; default RARL/FailMaker)")
    ap.add_argument("--flow", default="FailMaker", metavar="NAME", help="the hostile flow (default FailMaker)")
    ap.add_argument("episodes", nargs="+", help="seed-N/results/episodes.csv files")
    a = ap.parse_args()
    if a.rarl and len(a.rarl) > 2:
        ap.error("--rarl: at most two RARL egos")
    main(a.episodes, a.rarl or ["RARL/FailMaker"], a.flow)
