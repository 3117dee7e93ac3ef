"""The paper's findings in several pooled reports of the graph, side by side.

Usage:
  python3 crates/lab/scripts/results/paper_graph_lateral/compare.py NAME:SEEDS:FINDINGS [NAME:SEEDS:FINDINGS ...] \
      > docs/results/paper-graph-lateral/findings-compared.md

Each argument names a pooled report (`socialflow report run-1/results run-2/results ...`'s
findings.json, whose `across` holds every finding per run and the verdict over the runs), the
seeds of its runs in order, and the file, e.g.
  residual:5,6:docs/archive/2026-11-27-report-residual-seeds-5-6/findings.json
  lateral:9,10:docs/report/findings.json
A report of one run (no `across`) is read from its `checks`. Prints one markdown table: each
finding's effect in points with its Holm-adjusted p and verdict per run, and for a report of
several runs their random-effects estimate +- its 95 % half-width (DerSimonian-Laird, the
report's; with two runs a rough guide) and the verdict over the runs (the training run as the
unit).
"""
import json
import sys


def stem(claim):
    """A claim without the pooled numbers some carry in their text (e.g. "(pooled success ...")."""
    return claim.split(" (pooled success")[0]


def cell(c):
    if c is None:
        return "-"
    return f"{c['effect_points']:+.1f} ({c['p_adjusted']:.2g}, {c['verdict']})"


def parse(arg):
    try:
        name, seeds, path = arg.split(":", 2)
        seeds = [s for s in seeds.split(",") if s]
    except ValueError:
        sys.exit(f"argument {arg!r}: expected NAME:SEEDS:FINDINGS, e.g. residual:5,6:docs/archive/2026-11-27-report-residual-seeds-5-6/findings.json")
    try:
        with open(path) as f:
            data = json.load(f)
    except (OSError, json.JSONDecodeError) as e:
        sys.exit(f"{path}: {e}")
    if "across" in data:
        rows = {stem(a["key"]): (a["runs"], a["verdict"], a.get("combined")) for a in data["across"]}
    else:
        rows = {stem(c["claim"]): ([c], c["verdict"], None) for c in data["checks"]}
    width = max((len(r) for r, _, _ in rows.values()), default=0)
    if len(seeds) != width:
        sys.exit(f"{path}: its findings hold {width} run(s), {len(seeds)} seed(s) named ({arg!r})")
    return name, seeds, rows


def main():
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    reports = [parse(a) for a in sys.argv[1:]]
    keys = []
    for _, _, rows in reports:
        keys += [k for k in rows if k not in keys]
    head = ["finding"]
    for name, seeds, _ in reports:
        head += [f"{name}, seed {s}" for s in seeds]
        if len(seeds) > 1:
            head += [f"{name}: random effects", f"{name}: verdict over runs"]
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for k in keys:
        cells = [k]
        for _, seeds, rows in reports:
            runs, verdict, combined = rows.get(k, ([None] * len(seeds), None, None))
            cells += [cell(r) for r in runs]
            if len(seeds) > 1:
                re = f"{combined['estimate']:+.1f} +- {combined['ci95']:.1f}" if combined else "-"
                cells += [re, f"**{verdict}**" if verdict else "-"]
        print("| " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
