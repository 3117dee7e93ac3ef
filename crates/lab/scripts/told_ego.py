"""The told-ego probe: does what a flow's observers are told about the ego's SVO move the ego?

Reads an `episodes.csv` (or `.csv.gz`) of a `socialflow eval` grid whose `adversary` experiment
puts egos in a flow told the truth (`<flow>`) and in the same flow with the ego's SVO as every
observer is told it forced to a constant (`<flow> told0`, `<flow> told90`: `messages = {
told_ego_deg = ... }`), e.g. `configs/eval/stage1-told-ego-s13.toml`. For every ego and told arm,
the ego's success told the constant minus told the truth, paired by stored case (each case's
success averaged over its seeds: the case is the unit), per scenario and over all the scenarios'
cases, a two-sided paired t-test, Holm over the file's family, and the test's minimum detectable
effect (80 % power). A lever for SocialCommAdv exists where a told arm moves an ego's success by
>= 3 points (Holm p < 0.05) in either direction.

    python3 crates/lab/scripts/told_ego.py runs/stage1/told-ego-s13/episodes.csv \\
        --json docs/curves/stage1/told-ego-s13/told-ego.json

Needs scipy (the CI's report venv has it).
"""

from __future__ import annotations

import argparse
import csv
import re
import sys
from collections import defaultdict

from csv_files import open_csv, write_json
from l5_noise import holm, paired_row

SCENARIOS = ["intersection", "bottleneck", "merge", "roundabout"]
TOLD = re.compile(r"^(.*) (told-?\d+)$")


def read_ego_case_means(path: str) -> dict[tuple[str, str, str], dict[int, float]]:
    """(ego, flow, scenario) -> {case: the ego's success averaged over the case's seeds}."""
    sums: dict = defaultdict(lambda: defaultdict(list))
    with open_csv(path) as f:
        for row in csv.DictReader(f):
            if row["experiment"] != "adversary" or not row["ego"]:
                continue
            sums[(row["ego"], row["flow"], row["scenario"])][int(row["case"])].append(float(row["success"]))
    return {k: {c: sum(v) / len(v) for c, v in cases.items()} for k, cases in sums.items()}


def test(a: dict, b: dict, ego: str, arm: str, scenario: str) -> dict:
    return paired_row(a, b, {"ego": ego, "arm": arm, "scenario": scenario}, ("told", "truth"))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("episodes", help="episodes.csv (or .csv.gz) of a told-ego grid")
    ap.add_argument("--alpha", type=float, default=0.05)
    ap.add_argument("--min-effect", type=float, default=3.0, help="points that make a lever")
    ap.add_argument("--json", help="also write the results here")
    a = ap.parse_args()

    means = read_ego_case_means(a.episodes)
    tests = []
    for ego, flow in sorted({(e, f) for e, f, _ in means}):
        m = TOLD.match(flow)
        if not m:
            continue
        base = m.group(1)
        if not all((ego, base, s) in means and (ego, flow, s) in means for s in SCENARIOS):
            print(f"ego `{ego}`: `{flow}` or `{base}` lacks a scenario's cells", file=sys.stderr)
            return 2
        for s in SCENARIOS:
            tests.append(test(means[(ego, flow, s)], means[(ego, base, s)], ego, flow, s))
        pooled = [{(s, c): v for s in SCENARIOS for c, v in means[(ego, f, s)].items()} for f in (flow, base)]
        tests.append(test(pooled[0], pooled[1], ego, flow, "pooled"))
    if not tests:
        print(f"{a.episodes}: no `<flow> told<deg>` arm beside its `<flow>` in an adversary experiment",
              file=sys.stderr)
        return 2
    for t, ph in zip(tests, holm([t["p"] for t in tests])):
        t["p_holm"] = ph

    print("### Told-ego probe: the ego's success told a constant minus told the truth, paired by stored case\n")
    print("| ego | arm | scenario | cases | told (%) | truth (%) | difference (points) | Holm p | MDE (80 %) |")
    print("|---|---|---|---|---|---|---|---|---|")
    for t in tests:
        print(f"| {t['ego']} | {t['arm']} | {t['scenario']} | {t['cases']} | {t['told']:.1f} | {t['truth']:.1f} "
              f"| {t['diff']:+.1f} +- {t['ci95']:.1f} | {t['p_holm']:.2g} | {t['mde80']:.1f} |")
    levers = [t for t in tests if abs(t["diff"]) >= a.min_effect and t["p_holm"] < a.alpha]
    where = ", ".join(f"{t['ego']} {t['arm']} {t['scenario']} ({t['diff']:+.1f})" for t in levers) or "nowhere"
    print(f"\n- **A lever** (>= {a.min_effect:g} points either way, Holm p < {a.alpha:g}): {where}")
    if a.json:
        write_json(a.json, {"tests": tests, "levers": levers, "min_effect": a.min_effect, "alpha": a.alpha})
    return 0


if __name__ == "__main__":
    sys.exit(main())
