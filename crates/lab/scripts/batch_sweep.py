"""The compute-optimal batch sweep: held-out validation against wall time and against updates.

Two halves. `extract` reads runs' data directories (each a `socialflow train` run: its
`socialflow.log` has one timestamped `validation` line per held-out validation, its job's
`config.toml` the batch size and seed) and writes one CSV row per validation point, the wall time
counted from the run's first log line (when `train` started, the clock `timeout` stopped it by).
`table` reads that CSV and prints a row per arm (batch size), each cell one value per run: the
held-out success at its last validation before given wall times and the wall time each run first
reached a level, both on the 3-point trailing mean of its validations (so one lucky 200-episode
validation does not count as arrival).

    python3 crates/lab/scripts/batch_sweep.py extract /work/runs/batch/b*-s1? --out points.csv
    python3 crates/lab/scripts/batch_sweep.py table points.csv --level 0.75 --at 240,480,720

Stdlib only. `table --json` also writes the rows.
"""

from __future__ import annotations

import argparse
import csv
import os
import re
import sys
import tomllib
from datetime import datetime

from csv_files import write_json

LINE = re.compile(r"^(\S+Z) .*validation job_id=\d+ updates=(\d+) success=([0-9.eE+-]+)")
FIELDS = ["run", "batch", "seed", "updates", "wall_s", "success"]


def job_config(run_dir: str) -> dict:
    jobs = os.path.join(run_dir, "jobs")
    found = sorted(
        os.path.join(jobs, j, "config.toml")
        for j in os.listdir(jobs)
        if os.path.isfile(os.path.join(jobs, j, "config.toml"))
    )
    if len(found) != 1:
        raise ValueError(f"{run_dir}: expected one job with a config.toml, found {len(found)}")
    with open(found[0], "rb") as f:
        return tomllib.load(f)


def extract(run_dir: str) -> list[dict]:
    cfg = job_config(run_dir)
    log = os.path.join(run_dir, "socialflow.log")
    rows, start = [], None
    with open(log, encoding="utf-8") as f:
        for line in f:
            t = line.split(" ", 1)[0]
            if start is None and t.endswith("Z"):
                start = datetime.fromisoformat(t)
            m = LINE.match(line)
            if m:
                rows.append({
                    "run": os.path.basename(os.path.normpath(run_dir)),
                    "batch": cfg["sac"]["batch_size"],
                    "seed": cfg["sac"]["seed"],
                    "updates": int(m.group(2)),
                    "wall_s": round((datetime.fromisoformat(m.group(1)) - start).total_seconds(), 1),
                    "success": round(float(m.group(3)), 4),
                })
    if not rows:
        raise ValueError(f"{log}: no validation lines")
    return rows


def read_points(path: str) -> dict[str, list[dict]]:
    runs: dict[str, list[dict]] = {}
    with open(path, newline="", encoding="utf-8") as f:
        for r in csv.DictReader(f):
            row = {k: (r[k] if k == "run" else float(r[k])) for k in FIELDS}
            runs.setdefault(row["run"], []).append(row)
    return runs


def smoothed(points: list[dict]) -> list[tuple[float, float, float]]:
    """(wall_s, updates, 3-point trailing mean of success) per validation point."""
    out = []
    for i, p in enumerate(points):
        w = points[max(0, i - 2) : i + 1]
        out.append((p["wall_s"], p["updates"], sum(q["success"] for q in w) / len(w)))
    return out


def summary(points: list[dict], level: float, at: list[float]) -> dict:
    """One run's trailing-mean success near each of `at` and when it first reached `level`."""
    sm = smoothed(points)
    hit = next(((w, u) for w, u, s in sm if s >= level), None)
    return {
        "near": {f"{t:.0f}": next((s for w, _, s in reversed(sm) if w <= t), None) for t in at},
        "reaches_s": hit[0] if hit else None,
        "reaches_updates": hit[1] if hit else None,
        "last_updates": points[-1]["updates"],
    }


def joined(values: list, fmt: str, none: str = "-") -> str:
    """One table cell: the runs' values, `none` where a run has none."""
    return " / ".join(none if v is None else fmt.format(v) for v in values)


def table(path: str, level: float, at: list[float]) -> list[dict]:
    runs = read_points(path)
    arms: dict[int, list[str]] = {}
    for name in sorted(runs):
        arms.setdefault(int(runs[name][0]["batch"]), []).append(name)
    head = ["batch", "runs"] + [f"success near {t:.0f} s" for t in at]
    head += [f"first reaches {level:.2f} (s)", "updates then", "last updates"]
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    rows = []
    for batch in sorted(arms):
        sums = [summary(runs[name], level, at) for name in arms[batch]]
        for name, r in zip(arms[batch], sums):
            near = {k: None if v is None else round(v, 4) for k, v in r["near"].items()}
            rows.append({"run": name, "batch": batch, "level": level, **r, "near": near})
        cells = [str(batch), str(len(sums))]
        cells += [joined([r["near"][f"{t:.0f}"] for r in sums], "{:.3f}") for t in at]
        cells.append(joined([r["reaches_s"] for r in sums], "{:.0f}", none="not"))
        cells += [joined([r[k] for r in sums], "{:.0f}") for k in ("reaches_updates", "last_updates")]
        print("| " + " | ".join(cells) + " |")
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    ex = sub.add_parser("extract")
    ex.add_argument("runs", nargs="+")
    ex.add_argument("--out", required=True)
    tb = sub.add_parser("table")
    tb.add_argument("points")
    tb.add_argument("--level", type=float, default=0.75)
    tb.add_argument("--at", default="240,480,720")
    tb.add_argument("--json", help="also write the rows here")
    a = ap.parse_args()
    try:
        if a.cmd == "extract":
            rows = [r for d in a.runs for r in extract(d)]
            with open(a.out, "w", newline="", encoding="utf-8") as f:
                w = csv.DictWriter(f, fieldnames=FIELDS, lineterminator="\n")
                w.writeheader()
                w.writerows(rows)
        else:
            rows = table(a.points, a.level, [float(x) for x in a.at.split(",")])
            if a.json:
                write_json(a.json, rows)
    except (OSError, ValueError, KeyError) as e:
        print(f"batch_sweep.py: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
