"""Ladder rung L5 against the noise-matched IDM flow, from `socialflow eval` episodes.

Reads the `episodes.csv` of an evaluation of `configs/eval/l5-noise-matched.toml` (flows on
their own, `flow_quality` cells: the all-IDM flow, `IDM+noise` and the learned flows) and
tests, per learned flow and scenario, the flow's success against the noise-matched IDM flow's
on the same stored cases: each case's success averaged over its seeds (the stored case is the
unit), a paired two-sided t-test over the cases, Holm-corrected over the run's family (every
flow x scenario test of the file). The gate: the flow is at least `--min-gain` points above
`IDM+noise`, with Holm p < `--alpha`, in at least `--need` of the scenarios.

    python3 crates/lab/scripts/l5_noise.py runs/l5-noise/s27/episodes.csv --run "seed 9" \\
        --json docs/ladder/l5-flows/noise-matched/s27.json

Prints a markdown table and the verdicts; `--json` also writes them for the ladder table.
Needs scipy (the CI's report venv has it).
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
from collections import defaultdict

from scipy import stats

from csv_files import open_csv, write_json

BASELINES = ("IDM", "IDM+noise")


def read_case_means(path: str) -> dict[tuple[str, str], dict[int, float]]:
    """(flow, scenario) -> {case: success averaged over the case's seeds}, flow_quality only."""
    sums: dict[tuple[str, str], dict[int, list[float]]] = defaultdict(lambda: defaultdict(list))
    with open_csv(path) as f:
        for row in csv.DictReader(f):
            if row["experiment"] != "flow_quality" or row["ego"]:
                continue
            sums[(row["flow"], row["scenario"])][int(row["case"])].append(float(row["success"]))
    return {k: {c: sum(v) / len(v) for c, v in cases.items()} for k, cases in sums.items()}


def paired(a: dict[int, float], b: dict[int, float]) -> tuple[float, float, float, int]:
    """Mean difference a - b in points over the shared cases, its 95 % half-width, the
    two-sided p and the number of cases."""
    cases = sorted(set(a) & set(b))
    d = [100.0 * (a[c] - b[c]) for c in cases]
    n = len(d)
    mean = sum(d) / n
    var = sum((x - mean) ** 2 for x in d) / (n - 1) if n > 1 else 0.0
    se = math.sqrt(var / n)
    if se == 0.0:
        return mean, 0.0, 1.0 if mean == 0.0 else 0.0, n
    t = mean / se
    p = float(2.0 * stats.t.sf(abs(t), n - 1))
    return mean, float(stats.t.ppf(0.975, n - 1) * se), p, n


def paired_mde(a: dict[int, float], b: dict[int, float]) -> tuple[float, float, float, int, float]:
    """`paired`, and the test's minimum detectable effect at 80 % power (two-sided 0.05):
    (z_0.975 + z_0.8) x its standard error, in points."""
    diff, ci, p, n = paired(a, b)
    se = ci / float(stats.t.ppf(0.975, n - 1)) if n > 1 and ci > 0 else 0.0
    return diff, ci, p, n, (1.959964 + 0.841621) * se


def paired_row(a: dict, b: dict, labels: dict, names: tuple[str, str] = ("a", "b")) -> dict:
    """One paired test as a result row: `labels` first, then the cases, each side's success
    (keyed by `names`), the difference with its 95 % interval, p and the MDE."""
    diff, ci, p, n, mde = paired_mde(a, b)
    return {**labels, "cases": n, names[0]: pct(a), names[1]: pct(b),
            "diff": diff, "ci95": ci, "p": p, "mde80": mde}


def pct(case_means: dict[int, float]) -> float:
    """Mean success over the cases, in percent."""
    return 100.0 * sum(case_means.values()) / len(case_means)


def holm(ps: list[float]) -> list[float]:
    order = sorted(range(len(ps)), key=lambda i: ps[i])
    out = [0.0] * len(ps)
    running = 0.0
    for rank, i in enumerate(order):
        running = max(running, min(1.0, (len(ps) - rank) * ps[i]))
        out[i] = running
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("episodes", help="episodes.csv (or .csv.gz) of a l5-noise-matched evaluation")
    ap.add_argument("--run", default="", help="the run's label in the output")
    ap.add_argument("--baseline", default="IDM+noise")
    ap.add_argument("--min-gain", type=float, default=3.0, help="points above the baseline")
    ap.add_argument("--alpha", type=float, default=0.05)
    ap.add_argument("--need", type=int, default=3, help="scenarios that must pass")
    ap.add_argument("--json", help="also write the results here")
    a = ap.parse_args()

    means = read_case_means(a.episodes)
    scenarios = sorted({s for _, s in means}, key=["intersection", "bottleneck", "merge", "roundabout"].index)
    flows = sorted({f for f, _ in means if f not in BASELINES})
    if not any(f == a.baseline for f, _ in means):
        print(f"{a.episodes}: no flow_quality cells of the baseline `{a.baseline}`", file=sys.stderr)
        return 2
    tests = []
    for f in flows:
        for s in scenarios:
            if (f, s) not in means or (a.baseline, s) not in means:
                print(f"{a.episodes}: flow `{f}` or `{a.baseline}` has no cells in {s}", file=sys.stderr)
                return 2
            diff, ci, p, n = paired(means[(f, s)], means[(a.baseline, s)])
            tests.append({
                "flow": f, "scenario": s, "cases": n,
                "success": pct(means[(f, s)]),
                "idm": pct(means[("IDM", s)]) if ("IDM", s) in means else None,
                "baseline": pct(means[(a.baseline, s)]), "diff": diff, "ci95": ci, "p": p,
            })
    for t, ph in zip(tests, holm([t["p"] for t in tests])):
        t["p_holm"] = ph
        t["pass"] = bool(t["diff"] >= a.min_gain and ph < a.alpha)
    verdicts = {}
    for f in flows:
        passed = sum(t["pass"] for t in tests if t["flow"] == f)
        verdicts[f] = {"scenarios_passed": passed, "met": passed >= a.need}

    print(f"### {a.run or a.episodes}: each flow against `{a.baseline}` ({tests[0]['cases']} stored cases per scenario, paired by case)\n")
    print(f"| flow | scenario | success | IDM | {a.baseline} | flow - {a.baseline} (points) | p | Holm p | >= +{a.min_gain:g} and Holm p < {a.alpha:g} |")
    print("|---|---|---|---|---|---|---|---|---|")
    for t in tests:
        idm = "-" if t["idm"] is None else f"{t['idm']:.1f}"
        print(f"| {t['flow']} | {t['scenario']} | {t['success']:.1f} | {idm} | {t['baseline']:.1f} | {t['diff']:+.1f} +- {t['ci95']:.1f} | {t['p']:.2g} | {t['p_holm']:.2g} | {'yes' if t['pass'] else 'no'} |")
    print()
    for f, v in verdicts.items():
        state = "met" if v["met"] else "not met"
        print(f"- **{f}**: {v['scenarios_passed']} of {len(scenarios)} scenarios: {state} (needs {a.need})")
    if a.json:
        out = {"run": a.run, "episodes": a.episodes, "baseline": a.baseline, "min_gain": a.min_gain,
               "alpha": a.alpha, "need": a.need, "tests": tests, "verdicts": verdicts}
        write_json(a.json, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
