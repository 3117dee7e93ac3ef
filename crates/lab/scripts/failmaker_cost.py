"""What a FailMaker costs: the RL egos' success among it against among the SocialComm flow, from
`socialflow eval` episodes of `configs/eval/failmaker-paper-adversary.toml` (one file per graph
run). Its own flow quality is not scored: the evaluation cannot run a FailMaker without an ego.

The stored case is the unit: each (scenario, case)'s success is averaged over its seeds (and, for
the egos' cost, over the four egos, which meet the same stored cases), and two flows are compared
paired by case with a two-sided t-test, per scenario and pooled over the scenarios' cases; the
egos' cost is also given per ego (pooled over scenarios). Each run's family of tests is
Holm-corrected. The minimum detectable effect (80 % power, two-sided 0.05) is printed beside.

Issue 66's gate checked here, per run: the four RL egos' pooled drop (among it against among
SocialComm) >= 20 points (its other, the FailMaker's own flow success <= IDM's - 15, is not).

    python3 crates/lab/scripts/failmaker_cost.py runs/fm-eval-s9/out/episodes.csv \\
        runs/fm-eval-s10/out/episodes.csv --runs 9,10 --json docs/results/failmaker-paper/cost.json

Needs scipy (the CI's report venv has it).
"""

from __future__ import annotations

import argparse
import csv
import sys
from collections import defaultdict

from csv_files import open_csv, write_json
from l5_noise import holm, paired_row

SCENARIOS = ["intersection", "bottleneck", "merge", "roundabout"]
EGOS = ["RL/IDM", "RL/MACAD", "RL/CoPO", "RL/SocialComm"]


def read(path: str) -> dict:
    """The adversary cells' {(ego, flow, scenario): {case: success averaged over its seeds}}."""
    adv: dict = defaultdict(lambda: defaultdict(list))
    with open_csv(path) as f:
        for row in csv.DictReader(f):
            if row["experiment"] == "adversary":
                adv[(row["ego"], row["flow"], row["scenario"])][int(row["case"])].append(float(row["success"]))
    return {k: {c: sum(v) / len(v) for c, v in cases.items()} for k, cases in adv.items()}


def pooled(cells, flow: str, scenarios: list[str]) -> dict:
    """{(scenario, case): value} over `scenarios`, `cells(scenario, flow)` giving {case: value}."""
    return {(s, c): v for s in scenarios for c, v in cells(s, flow).items()}


def over_egos(adv: dict, flow: str, scenario: str, egos: list[str]) -> dict[int, float]:
    """Each case's success averaged over `egos` among `flow` (cases all of them met)."""
    cells = [adv.get((e, flow, scenario), {}) for e in egos]
    cases = set.intersection(*(set(c) for c in cells)) if cells else set()
    return {c: sum(cell[c] for cell in cells) / len(cells) for c in cases}


def run_rows(adv: dict, run: str, flows: list[str]) -> list[dict]:
    rows = []
    for flow in flows:
        tests = [(f"egos: {flow} - SocialComm", s, SCENARIOS if s == "pooled" else [s],
                  lambda x, f: over_egos(adv, f, x, EGOS)) for s in SCENARIOS + ["pooled"]]
        tests += [(f"{ego}: {flow} - SocialComm", "pooled", SCENARIOS,
                   lambda x, f, ego=ego: adv.get((ego, f, x), {})) for ego in EGOS]
        for test, scenario, sc, cells in tests:
            a, b = pooled(cells, flow, sc), pooled(cells, "SocialComm", sc)
            if a and b:
                rows.append(paired_row(a, b, {"run": run, "test": test, "scenario": scenario},
                                       ("flow", "reference")))
    for r, p in zip(rows, holm([r["p"] for r in rows])):
        r["p_holm"] = p
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("episodes", nargs="+", help="episodes.csv (or .csv.gz), one per graph run")
    ap.add_argument("--runs", default="", help="comma-separated labels of the files (default 1, 2, ...)")
    ap.add_argument("--flows", default="FailMaker-paper,FailMaker", help="the adversaries to score")
    ap.add_argument("--json", help="write every row here")
    ap.add_argument("--no-gate", action="store_true",
                    help="leave out issue 66's FailMaker gate (flows that are not FailMakers, e.g. told messages)")
    a = ap.parse_args()
    labels = a.runs.split(",") if a.runs else [str(i + 1) for i in range(len(a.episodes))]
    if len(labels) != len(a.episodes):
        print(f"--runs names {len(labels)} runs for {len(a.episodes)} files", file=sys.stderr)
        return 2
    flows = a.flows.split(",")
    rows: list[dict] = []
    gates: list[dict] = []
    for path, run in zip(a.episodes, labels):
        adv = read(path)
        missing = [f for f in flows + ["SocialComm"] if not any(k[1] == f for k in adv)]
        if missing:
            print(f"{path}: no adversary cells among {', '.join(missing)}", file=sys.stderr)
            return 2
        rr = run_rows(adv, run, flows)
        rows += rr
        for flow in [] if a.no_gate else flows:
            e = next(r for r in rr if r["test"] == f"egos: {flow} - SocialComm" and r["scenario"] == "pooled")
            gates.append({"run": run, "flow": flow, "egos_drop": -e["diff"], "egos_gate": -e["diff"] >= 20.0})
    for r in rows:
        print(f"run {r['run']:>3} {r['test']:42s} {r['scenario']:12s} {r['flow']:5.1f} vs {r['reference']:5.1f}: "
              f"{r['diff']:+6.1f} +- {r['ci95']:4.1f} (Holm p {r['p_holm']:.2g}, MDE {r['mde80']:.1f}, {r['cases']} cases)")
    for g in gates:
        print(f"run {g['run']} {g['flow']}: egos' drop {g['egos_drop']:+.1f} "
              f"(gate >= 20: {'met' if g['egos_gate'] else 'not met'})")
    if a.json:
        write_json(a.json, {"rows": rows} if a.no_gate else {"rows": rows, "gates": gates})
    return 0


if __name__ == "__main__":
    sys.exit(main())
