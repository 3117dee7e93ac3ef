"""One row per seed of an L3 attempt: validation success at fixed updates, the sampled policy's
rolling success (first >= 0.90 and at the end, off-road share), the kept actor against the IDM ego
and the gate, from the files `socialflow ladder` writes (seed-<s>/validation.csv, seed-<s>/curve.csv,
summary.json). Curve points count as the gate counts them: after the first update and once the
rolling window (100 episodes) holds no warm-up episode.

    python3 crates/lab/scripts/results/l3_roundabout_direct/attempt_table.py docs/ladder/l3-roundabout-direct/attempt-hold-steer-actor
    python3 crates/lab/scripts/results/l3_roundabout_direct/attempt_table.py docs/ladder/l3-roundabout-direct 5000,5500,6000,8000,10000,11000

(the second argument: the updates whose validation to show, default 5000,5500,6000,7000,8000,9000)
"""
import csv
import json
import sys
from pathlib import Path

WINDOW = 100
DEFAULT_AT = [5000, 5500, 6000, 7000, 8000, 9000]


def rows(path):
    with open(path) as f:
        return list(csv.DictReader(f))


def main(attempt, at=None):
    AT = [int(u) for u in at.split(",")] if at else DEFAULT_AT
    attempt = Path(attempt)
    summary = json.loads((attempt / "summary.json").read_text())
    seeds = {s["train_seed"]: s for s in summary["seeds"]}
    print("| seed | validation " + " / ".join(f"{u / 1000:g}k" for u in AT)
          + " / end | rolling sampled success: first >= 0.90 / peak / end (off road) | kept actor (its update) vs IDM ego | gate |")
    print("|---|---|---|---|---|")
    for seed in sorted(seeds):
        d = attempt / f"seed-{seed}"
        val = {int(r["updates"]): float(r["success"]) for r in rows(d / "validation.csv")}
        last = max(val)
        vals = " / ".join(f"{val[u]:.2f}" if u in val else "-" for u in AT) + f" / {val[last]:.2f}"
        curve = rows(d / "curve.csv")
        warm = max(float(r["episodes"]) for r in curve if float(r["updates"]) == 0)
        pts = [r for r in curve if float(r["updates"]) > 0 and float(r["episodes"]) >= warm + WINDOW]
        first = next((int(float(r["updates"])) for r in pts if float(r["success"]) >= 0.9), None)
        peak = max(pts, key=lambda r: float(r["success"]))
        end = pts[-1]
        s = seeds[seed]
        gate = "met" if s["passed"] else "; ".join(s["failed_checks"])
        print(f"| {seed} | {vals} | {f'{first / 1000:.1f}k' if first else 'never'} / "
              f"{float(peak['success']):.2f} ({float(peak['updates']) / 1000:.1f}k) / "
              f"{float(end['success']):.2f} ({float(end['off_road']):.2f}) | "
              f"{s['success']:.3f} ({s['selected_updates']}) vs {s['idm_success']:.3f}, p {s['p_value']:.2f} | {gate} |")


if __name__ == "__main__":
    main(*sys.argv[1:3])
