"""How often the lateral graph's egos leave their route's lane, from the grid's episodes.

Usage: python lanes.py <episodes.csv> > lanes.md

`lane_change` is the share of an episode's scored agents that left their route's lane at some
point; in cross-validation that is the ego. Prints each ego's share per evaluation flow, in
percent over the episodes, beside success. The flows' own shares (every vehicle, flow quality)
are the report's "Left its lane" column, per start with its interval.
"""
import csv
import sys
from collections import defaultdict


def main():
    rows = list(csv.DictReader(open(sys.argv[1])))
    if "lane_change" not in rows[0]:
        sys.exit(f"{sys.argv[1]} has no lane_change column (results written before 2026-11-28)")
    cross = defaultdict(list)
    for r in rows:
        if r["experiment"] == "cross":
            cross[(r["ego"], r["flow"])].append((float(r["lane_change"]), float(r["success"])))
    mean = lambda xs, i: 100.0 * sum(x[i] for x in xs) / len(xs)  # noqa: E731
    fl = list(dict.fromkeys(f for _, f in cross))
    print("## Cross-validation: episodes whose ego left its lane, % (success %)\n")
    print("| ego | " + " | ".join(fl) + " |")
    print("|---|" + "---|" * len(fl))
    for e in dict.fromkeys(e for e, _ in cross):
        cells = [
            f"{mean(cross[(e, f)], 0):.1f} ({mean(cross[(e, f)], 1):.1f})" if (e, f) in cross else "-"
            for f in fl
        ]
        print(f"| {e} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
