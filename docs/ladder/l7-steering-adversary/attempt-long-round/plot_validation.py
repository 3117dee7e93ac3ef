"""The carried RARL rounds' validation among FailMaker, by update: this attempt's 120,000-transition
rounds beside attempt-replay-carry's 40,000-transition ones. Each line is one training run (its
`validation.csv`: 200 held-out episodes every 1,000 updates).

    /path/to/venv/bin/python docs/ladder/l7-steering-adversary/attempt-long-round/plot_validation.py
"""

import csv
import glob
import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

here = os.path.dirname(os.path.abspath(__file__))


def series(path):
    with open(path) as f:
        rows = list(csv.DictReader(f))
    return [int(r["updates"]) for r in rows], [float(r["success"]) for r in rows]


fig, ax = plt.subplots(figsize=(8, 4.5))
for path in sorted(glob.glob(os.path.join(here, "seed-*/jobs/*-ego-failmaker-long-seed*/validation.csv"))):
    seed = path.split("seed-")[1].split("/")[0]
    ax.plot(*series(path), marker="o", ms=3, label=f"120k carried round, seed {seed}")
old = os.path.join(here, "..", "attempt-replay-carry")
for path in sorted(glob.glob(os.path.join(old, "seed-*/jobs/*-ego-failmaker-carry-seed*/validation.csv"))):
    seed = path.split("seed-")[1].split("/")[0]
    ax.plot(*series(path), ls="--", alpha=0.7, label=f"40k carried round, seed {seed} (attempt-replay-carry)")
ax.set_xlabel("updates in the RARL round")
ax.set_ylabel("validation success among FailMaker")
ax.set_ylim(0, 1)
ax.grid(alpha=0.3)
ax.legend(fontsize=8, loc="lower right")
fig.tight_layout()
fig.savefig(os.path.join(here, "validation.png"), dpi=110)
print("wrote", os.path.join(here, "validation.png"))
