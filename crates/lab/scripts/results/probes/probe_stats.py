"""The decisive probes' comparisons, with the report's rules: per-start differences (a start's
seeds averaged), a one-sample t-test, 95 % interval, Holm within each probe's family.

    python3 crates/lab/scripts/results/probes/probe_stats.py > docs/results/probes/probes.md

Reads the probes' episodes.csv files under docs/results/probes/ (written by `socialflow eval` of
configs/eval/probe-*.toml) and prints markdown tables.
"""

import os
import sys
from pathlib import Path

import numpy as np
import pandas as pd
from scipy import stats
from statsmodels.stats.multitest import multipletests

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # crates/lab/scripts
from csv_files import REPO

DATA = os.fspath(REPO / "docs/results/probes")


def compare(rows, a, b, by, unit):
    """Per-unit success difference a - b of column `by`'s values, over the rows both ran."""
    key = unit + ["seed"]
    x = rows[rows[by] == a].set_index(key).success
    y = rows[rows[by] == b].set_index(key).success
    both = pd.concat([x.rename("a"), y.rename("b")], axis=1).dropna()
    d = (both.a - both.b).rename("success").reset_index().groupby(unit).success.mean().to_numpy() * 100.0
    t = stats.ttest_1samp(d, 0.0)
    half = stats.t.ppf(0.975, len(d) - 1) * d.std(ddof=1) / np.sqrt(len(d))
    return {"n": len(d), "effect": d.mean(), "ci": half, "p": t.pvalue, "a": both.a.mean() * 100.0, "b": both.b.mean() * 100.0}


def table(title, lines):
    ps = [l[1]["p"] for l in lines]
    holm = multipletests(ps, method="holm")[1] if ps else []
    print(f"\n### {title}\n")
    print("| comparison | starts | means (points) | difference ± 95 % | p | p (Holm) |")
    print("|---|---|---|---|---|---|")
    for (name, r), h in zip(lines, holm):
        print(f"| {name} | {r['n']} | {r['a']:.1f} vs {r['b']:.1f} | {r['effect']:+.1f} ± {r['ci']:.1f} | {r['p']:.2e} | {h:.2e} |")


def main():
    print("## The decisive probes (seed 6, 2026-11-27)")
    mf = pd.read_csv(os.path.join(DATA, "messages-and-flow-actors/results/episodes.csv.gz"))
    fq = mf[mf.experiment == "flow_quality"]
    if len(fq):
        lines = []
        for s in ["intersection", "bottleneck", "merge", "roundabout", None]:
            rows = fq if s is None else fq[fq.scenario == s]
            lines.append((f"SocialComm - SocialComm msg45, {s or 'all scenarios'}", compare(rows, "SocialComm", "SocialComm msg45", "flow", ["scenario", "case"])))
        table("Does SocialComm use its messages? Flow success, neighbour SVOs told as 45 deg", lines)
    cross = mf[mf.experiment == "cross"]
    if len(cross):
        lines = []
        for x in ["MACAD", "CoPO", "SocialComm"]:
            for f in ["IDM", "MACAD", "CoPO", "SocialComm", None]:
                rows = cross if f is None else cross[cross.flow == f]
                lines.append((f"RL/{x} - {x} actor, in {f or 'all four flows'}", compare(rows, f"RL/{x}", f"{x} actor", "ego", ["flow", "scenario", "case"])))
        table("Does ego training add anything among learned flows? Each flow's actor in the ego's seat", lines)
    path = os.path.join(DATA, "constant-message-adversary/results/episodes.csv.gz")
    if os.path.exists(path):
        adv = pd.read_csv(path)
        adv = adv[adv.experiment == "adversary"]
        lines = []
        for e in ["RL/IDM", "RL/MACAD", "RL/CoPO", "RL/SocialComm", None]:
            rows = adv if e is None else adv[adv.ego == e]
            for a, b in [("SocialComm", "SocialComm told0"), ("SocialComm", "SocialComm told90"), ("SocialComm told90", "SocialComm told0")]:
                lines.append((f"{e or 'all four egos'}: {a} - {b}", compare(rows, a, b, "flow", ["ego", "scenario", "case"])))
        table("Is there a lever for SocialCommAdv? Ego success with the ego's SVO told as 0 or 90 deg", lines)


if __name__ == "__main__":
    sys.exit(main())
