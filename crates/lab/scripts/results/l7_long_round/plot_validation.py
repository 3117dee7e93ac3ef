"""The carried RARL rounds' validation among FailMaker, by update: this attempt's 120,000-transition
rounds beside attempt-replay-carry's 40,000-transition ones. Each line is one training run (its
`validation.csv`: 200 held-out episodes every 1,000 updates). Reads the committed seed-N/jobs/ of
docs/ladder/l7-steering-adversary/attempt-long-round/ and attempt-replay-carry/ and writes
attempt-long-round/validation.png (or `--out PNG`).

    /path/to/venv/bin/python crates/lab/scripts/results/l7_long_round/plot_validation.py
"""

import argparse
import csv
import glob
import os
import sys
from pathlib import Path

import matplotlib
import matplotlib.pyplot as plt

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # crates/lab/scripts
from csv_files import REPO

matplotlib.use("Agg")

L7 = REPO / "docs/ladder/l7-steering-adversary"
DATA = L7 / "attempt-long-round"


def series(path):
    with open(path) as f:
        rows = list(csv.DictReader(f))
    return [int(r["updates"]) for r in rows], [float(r["success"]) for r in rows]


ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
ap.add_argument("--out", default=str(DATA / "validation.png"), help="the PNG to write")
out = ap.parse_args().out
fig, ax = plt.subplots(figsize=(8, 4.5))
for path in sorted(glob.glob(os.path.join(DATA, "seed-*/jobs/*-ego-failmaker-long-seed*/validation.csv"))):
    seed = path.split("seed-")[1].split("/")[0]
    ax.plot(*series(path), marker="o", ms=3, label=f"120k carried round, seed {seed}")
old = L7 / "attempt-replay-carry"
for path in sorted(glob.glob(os.path.join(old, "seed-*/jobs/*-ego-failmaker-carry-seed*/validation.csv"))):
    seed = path.split("seed-")[1].split("/")[0]
    ax.plot(*series(path), ls="--", alpha=0.7, label=f"40k carried round, seed {seed} (attempt-replay-carry)")
ax.set_xlabel("updates in the RARL round")
ax.set_ylabel("validation success among FailMaker")
ax.set_ylim(0, 1)
ax.grid(alpha=0.3)
ax.legend(fontsize=8, loc="lower right")
fig.tight_layout()
fig.savefig(out, dpi=110)
print("wrote", out)
