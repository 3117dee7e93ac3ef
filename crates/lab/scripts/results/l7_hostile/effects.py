"""FailMaker's effect on each ego per training seed, from the evaluation's episodes: success among
FailMaker minus among IDM, paired on the same (scenario, case, seed) starts, with a 95 % t
interval and a paired t-test's p; and how the episodes among FailMaker end.

    python3 crates/lab/scripts/results/l7_hostile/effects.py docs/ladder/l7-steering-adversary/attempt-hostile/seed-*/results/episodes.csv.gz
"""

import csv
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # crates/lab/scripts
from csv_files import open_csv
from results.l7_lateral_rarl.recovery import paired


def load(path):
    with open_csv(path) as f:
        return list(csv.DictReader(f))


def success(eps, keys):
    """{start: success} of `eps` (`{start: row}`) on `keys`."""
    return {k: float(eps[k]["success"]) for k in keys}


def ends(eps):
    """Shares of the episodes (`{start: row}`) that end in a collision, in another failure (off
    the road or the lane), or safely but not arrived, and the share with a lane change (0 where
    the file predates the `lane_change` column)."""
    n = len(eps)
    col = sum(float(r["collision"]) for r in eps.values()) / n
    unsafe = sum(1 - float(r["safety"]) for r in eps.values()) / n
    stuck = sum(float(r["safety"]) * (1 - float(r["success"])) for r in eps.values()) / n
    lane = sum(float(r.get("lane_change") or 0) for r in eps.values()) / n
    return col, unsafe - col, stuck, lane


def main(paths):
    print("| seed | ego | among IDM | among FailMaker | effect (points) | 95 % CI | paired p | FailMaker episodes: collision / other failure / not arrived safely |")
    print("|---|---|---|---|---|---|---|---|")
    for path in paths:
        seed = path.split("seed-")[1].split("/")[0]
        rows = load(path)
        for ego in sorted({r["ego"] for r in rows}, reverse=True):
            by = {}
            for r in rows:
                if r["ego"] == ego:
                    by.setdefault(r["flow"], {})[(r["scenario"], r["case"], r["seed"])] = r
            idm, fm = by["IDM"], by["FailMaker"]
            keys = sorted(idm.keys() & fm.keys())
            mean, half, p = paired(success(idm, keys), success(fm, keys))
            n = len(keys)
            a = sum(success(idm, keys).values()) / n
            b = sum(success(fm, keys).values()) / n
            col, other, stuck, _ = ends({k: fm[k] for k in keys})
            print(f"| {seed} | {ego} | {a:.3f} | {b:.3f} | {100 * mean:+.1f} | +-{100 * half:.1f} | {p:.1e} | {col:.3f} / {other:.3f} / {stuck:.3f} |")


if __name__ == "__main__":
    main(sys.argv[1:])
