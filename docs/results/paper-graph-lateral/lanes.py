"""How often the lateral graph's agents leave their route's lane, from the grid's episodes.

Usage: python lanes.py <episodes.csv> > lanes.md

`lane_change` is the share of an episode's scored agents that left their route's lane at some
point (every vehicle in flow quality, the ego elsewhere). Prints, in percent over the episodes:
each flow's share per scenario (flow quality), and each ego's share per evaluation flow
(cross-validation), beside success.
"""
import csv
import sys
from collections import defaultdict


def main():
    rows = list(csv.DictReader(open(sys.argv[1])))
    if "lane_change" not in rows[0]:
        sys.exit(f"{sys.argv[1]} has no lane_change column (results written before 2026-11-28)")
    flows = defaultdict(list)
    cross = defaultdict(list)
    for r in rows:
        lc, ok = float(r["lane_change"]), float(r["success"])
        if r["experiment"] == "flow_quality":
            flows[(r["flow"], r["scenario"])].append((lc, ok))
        elif r["experiment"] == "cross":
            cross[(r["ego"], r["flow"])].append((lc, ok))
    mean = lambda xs, i: 100.0 * sum(x[i] for x in xs) / len(xs)
    scen = sorted({s for _, s in flows})
    print("## Flow quality: vehicles that left their lane, % (success %)\n")
    print("| flow | " + " | ".join(scen) + " |")
    print("|---|" + "---|" * len(scen))
    for f in dict.fromkeys(f for f, _ in flows):
        cells = [f"{mean(flows[(f, s)], 0):.1f} ({mean(flows[(f, s)], 1):.1f})" for s in scen]
        print(f"| {f} | " + " | ".join(cells) + " |")
    fl = list(dict.fromkeys(f for _, f in cross))
    print("\n## Cross-validation: episodes whose ego left its lane, % (success %)\n")
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
