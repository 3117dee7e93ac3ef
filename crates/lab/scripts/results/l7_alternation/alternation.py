"""L7 with the paper's alternation, per training seed: the success of RL/IDM and of the ego after
each RARL round (RARL-1..3) among IDM and among each round's adversary (FailMaker-1..3), and the
differences that decide L7, each paired on the same (scenario, case, seed) starts with a 95 % t
interval and a paired t-test's p, Holm's correction over every p the tables print:

- the attack: RL/IDM among FailMaker-1 minus among IDM (the first clause, >= 20 points);
- each round's recovery: RARL-k minus RL/IDM among FailMaker-1, and its share of the attack;
- each continued adversary's attack on the ego it trained against: RARL-(k-1) among
  FailMaker-k minus among IDM;
- the last ego against every adversary and among IDM: RARL-3 minus RL/IDM.

    python3 crates/lab/scripts/results/l7_alternation/alternation.py docs/ladder/l7-steering-adversary/attempt-alternation/seed-*/results/episodes.csv.gz
"""

import argparse
import csv
import sys
from pathlib import Path

from statsmodels.stats.multitest import multipletests

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # crates/lab/scripts
from csv_files import open_csv
from results.l7_hostile.effects import ends
from results.l7_lateral_rarl.recovery import paired

EGOS = ["RL/IDM", "RARL-1", "RARL-2", "RARL-3"]
FLOWS = ["IDM", "FailMaker-1", "FailMaker-2", "FailMaker-3"]


def load(path):
    """{(ego, flow): {(scenario, case, seed): episode row}}."""
    cells = {}
    with open_csv(path) as f:
        for r in csv.DictReader(f):
            cells.setdefault((r["ego"], r["flow"]), {})[(r["scenario"], r["case"], r["seed"])] = r
    return cells


def values(eps, name="success", keys=None):
    """{(scenario, case, seed): float(row[name])} of one cell's episodes (only `keys` if given)."""
    return {k: float(r[name]) for k, r in eps.items() if keys is None or k in keys}


def column(cells, name):
    return {cell: values(eps, name) for cell, eps in cells.items()}


def attack(among_idm, among_flow):
    """Per start: success among a flow minus among IDM, for one ego's two cells."""
    a, b = values(among_idm), values(among_flow)
    return {k: b[k] - a[k] for k in b}


def rows_for(succ):
    """(label, (mean, half, p), share-of-attack or None) for one training seed."""
    attack = paired(succ[("RL/IDM", "IDM")], succ[("RL/IDM", "FailMaker-1")])
    out = [("attack: RL/IDM among FailMaker-1 - among IDM", attack, None)]
    for k in (1, 2, 3):
        rec = paired(succ[("RL/IDM", "FailMaker-1")], succ[(f"RARL-{k}", "FailMaker-1")])
        share = rec[0] / -attack[0] if attack[0] < 0 else None
        out.append((f"recovery: RARL-{k} - RL/IDM among FailMaker-1", rec, share))
    for k in (2, 3):
        prev = EGOS[k - 1]
        out.append((f"re-attack: {prev} among FailMaker-{k} - among IDM",
                    paired(succ[(prev, "IDM")], succ[(prev, f"FailMaker-{k}")]), None))
    for flow in ["IDM", "FailMaker-2", "FailMaker-3"]:
        out.append((f"RARL-3 - RL/IDM among {flow}", paired(succ[("RL/IDM", flow)], succ[("RARL-3", flow)]), None))
    return out


def main(paths):
    per_seed = []
    for path in paths:
        seed = path.split("seed-")[1].split("/")[0]
        cells = load(path)
        succ = column(cells, "success")
        per_seed.append((seed, succ, cells, rows_for(succ)))
    ps = [r[1][2] for _, _, _, rows in per_seed for r in rows]
    adj = iter(multipletests(ps, method="holm")[1])
    for seed, succ, cells, rows in per_seed:
        print(f"\n### Seed {seed}: success (%) of each ego among each flow\n")
        print("| ego | " + " | ".join(FLOWS) + " |")
        print("|---|" + "---|" * len(FLOWS))
        for ego in EGOS:
            row = []
            for flow in FLOWS:
                v = list(succ[(ego, flow)].values())
                row.append(f"{100 * sum(v) / len(v):.1f}")
            print(f"| {ego} | " + " | ".join(row) + " |")
        print(f"\n| seed {seed}: how episodes end | flow | collision | other failure | not arrived safely | lane change |")
        print("|---|---|---|---|---|---|")
        for ego in EGOS:
            for flow in ["IDM", "FailMaker-1"]:
                col, other, stuck, lane = ends(cells[(ego, flow)])
                print(f"| {ego} | {flow} | {col:.3f} | {other:.3f} | {stuck:.3f} | {lane:.3f} |")
        print(f"\n| seed {seed}: difference | points, 95 % CI | p | Holm | share of the attack |")
        print("|---|---|---|---|---|")
        for label, (m, h, p), share in rows:
            s = f"{100 * share:.0f} %" if share is not None else ""
            print(f"| {label} | {100 * m:+.1f} +- {100 * h:.1f} | {p:.1e} | {next(adj):.1e} | {s} |")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("episodes", nargs="+", help="seed-N/results/episodes.csv files")
    main(ap.parse_args().episodes)
