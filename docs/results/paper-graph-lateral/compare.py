"""The paper's findings on the lateral graph beside the residual graph's two replicates.

Usage: python compare.py <lateral findings.json> <residual findings.json> > findings-compared.md

Reads the `checks` of the lateral run's report (one replicate) and the per-run checks of the
residual report (`across[*].runs`, seeds 5 and 6) and prints one markdown table: each finding's
effect in points with its Holm-adjusted p and verdict per run.
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


def main():
    lateral = json.load(open(sys.argv[1]))
    residual = json.load(open(sys.argv[2]))
    lat = {stem(c["claim"]): c for c in lateral["checks"]}
    print("| finding | residual, seed 5 | residual, seed 6 | lateral, seed 9 |")
    print("|---|---|---|---|")
    for f in residual["across"]:
        runs = f["runs"]
        key = stem(f["key"])
        print(f"| {key} | {cell(runs[0])} | {cell(runs[1])} | {cell(lat.pop(key, None))} |")
    for key, c in lat.items():
        print(f"| {key} | - | - | {cell(c)} |")


if __name__ == "__main__":
    main()
