"""The Stage-1 plateau rule, per run, from each job directory's `validation.csv`.

A run has plateaued when its held-out validation success gained < 2 points over the last 25 % of
its updates: the mean of the points in its last 10,000 updates against the mean of the points
within 5,000 updates of the 75 % mark (means, not single points: one validation is 200 episodes
and moves by a few points on its own). Before 120,000 updates (half of `configs/stage1`'s
240,000) the rule gives no verdict ("too early"). Also prints the mean success near the marks
24k, 48k, ... (points within 4,000 updates of each) and the best point.

    python3 crates/lab/scripts/plateau.py docs/curves/stage1/macad-s11 runs/stage1/macad-s12/jobs/1-flow-macad

Stdlib only. `--json` also writes the rows.
"""

from __future__ import annotations

import argparse
import csv
import os
import sys

from csv_files import write_json

GAIN_POINTS = 2.0
MIN_UPDATES = 120_000
MARK_STEP = 24_000


def read(job: str) -> list[tuple[int, float]]:
    path = os.path.join(job, "validation.csv")
    with open(path, newline="", encoding="utf-8") as f:
        rows = [(int(r["updates"]), float(r["success"])) for r in csv.DictReader(f)]
    if not rows:
        raise ValueError(f"{path}: no validation points")
    return rows


def mean_near(rows: list[tuple[int, float]], at: float, within: float) -> float | None:
    pts = [s for u, s in rows if abs(u - at) <= within]
    return sum(pts) / len(pts) if pts else None


def verdict(rows: list[tuple[int, float]]) -> dict:
    end = rows[-1][0]
    last = [s for u, s in rows if u > end - 10_000]
    last_mean = sum(last) / len(last)
    q3 = mean_near(rows, 0.75 * end, 5_000)
    gain = None if q3 is None else 100.0 * (last_mean - q3)
    if end < MIN_UPDATES:
        state = "too early"
    elif gain is None:
        state = "no points near the 75 % mark"
    else:
        state = "plateau" if gain < GAIN_POINTS else "rising"
    best_u, best_s = max(rows, key=lambda r: r[1])
    marks = {m: mean_near(rows, m, 4_000) for m in range(MARK_STEP, end + 1, MARK_STEP)}
    return {"updates": end, "last_mean": last_mean, "q3_mean": q3, "gain_points": gain,
            "state": state, "best": best_s, "best_at": best_u,
            "marks": {str(m): v for m, v in marks.items() if v is not None}}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("jobs", nargs="+", help="job directories holding validation.csv")
    ap.add_argument("--json", help="also write the rows here")
    a = ap.parse_args()
    out = {}
    for job in a.jobs:
        try:
            out[job] = verdict(read(job))
        except (OSError, ValueError, KeyError) as e:
            print(f"{job}: {e}", file=sys.stderr)
            return 2
    marks = sorted({int(m) for v in out.values() for m in v["marks"]})
    print("| run | updates | " + " | ".join(f"{m // 1000}k" for m in marks)
          + " | last 10k | gain over the last quarter (points) | best | rule |")
    print("|---|---|" + "---|" * len(marks) + "---|---|---|---|")
    for job, v in out.items():
        cells = [f"{v['marks'][str(m)]:.3f}" if str(m) in v["marks"] else "" for m in marks]
        gain = "-" if v["gain_points"] is None else f"{v['gain_points']:+.1f}"
        print(f"| {job} | {v['updates']:,} | " + " | ".join(cells)
              + f" | {v['last_mean']:.3f} | {gain} | {v['best']:.3f} ({v['best_at'] // 1000}k) | {v['state']} |")
    if a.json:
        write_json(a.json, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
