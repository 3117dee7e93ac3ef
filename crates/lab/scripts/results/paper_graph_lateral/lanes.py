"""How often the lateral graph's egos leave their route's lane, from the grid's episodes.

Usage: python3 crates/lab/scripts/results/paper_graph_lateral/lanes.py LABEL=<episodes.csv> [LABEL=<episodes.csv> ...] > lanes.md
e.g.   python3 crates/lab/scripts/results/paper_graph_lateral/lanes.py "seed 9=docs/report/run-1/results/episodes.csv.gz" "seed 10=docs/report/run-2/results/episodes.csv.gz"

`lane_change` is the share of an episode's scored agents that left their route's lane at some
point; in cross-validation that is the ego. Prints, per run, each ego's share per evaluation
flow, in percent over the episodes, beside success. The flows' own shares (every vehicle, flow
quality) are the report's "Left its lane" column, per start with its interval.
"""
import csv
import sys
from collections import defaultdict
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # crates/lab/scripts
from csv_files import open_csv


def table(label, path):
    try:
        with open_csv(path) as f:
            rows = list(csv.DictReader(f))
    except OSError as e:
        sys.exit(f"{path}: {e}")
    if not rows or "lane_change" not in rows[0]:
        sys.exit(f"{path} has no lane_change column (results written before 2026-11-28)")
    cross = defaultdict(list)
    for r in rows:
        if r["experiment"] == "cross":
            cross[(r["ego"], r["flow"])].append((float(r["lane_change"]), float(r["success"])))
    mean = lambda xs, i: 100.0 * sum(x[i] for x in xs) / len(xs)
    fl = list(dict.fromkeys(f for _, f in cross))
    print(f"## Cross-validation, {label}: episodes whose ego left its lane, % (success %)\n")
    print("| ego | " + " | ".join(fl) + " |")
    print("|---|" + "---|" * len(fl))
    for e in dict.fromkeys(e for e, _ in cross):
        cells = [
            f"{mean(cross[(e, f)], 0):.1f} ({mean(cross[(e, f)], 1):.1f})" if (e, f) in cross else "-"
            for f in fl
        ]
        print(f"| {e} | " + " | ".join(cells) + " |")
    print()


def main():
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    for arg in sys.argv[1:]:
        label, sep, path = arg.partition("=")
        if not sep:
            sys.exit(f"argument {arg!r}: expected LABEL=<episodes.csv>")
        table(label, path)


if __name__ == "__main__":
    main()
