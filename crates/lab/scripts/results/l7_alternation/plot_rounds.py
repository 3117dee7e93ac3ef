"""The alternation's curves, one row per training seed: left, each ego phase's validation success
among the adversary it trains against (RL/IDM among IDM, then RARL-k among FailMaker-k; 200
held-out episodes every 1,000 updates), phases laid end to end by update; right, each adversary
phase's training-window ego success (the share of episodes whose ego succeeds, from the fifth
episode of each phase on; lower is a stronger attack), phases laid end to end by environment step.
Reads the committed seed-N/jobs/ of docs/ladder/l7-steering-adversary/attempt-alternation/ and
writes its rounds.png (or `--out PNG`).

    /path/to/venv/bin/python crates/lab/scripts/results/l7_alternation/plot_rounds.py
"""

import argparse
import csv
import glob
import os
import re
import sys
from pathlib import Path

import matplotlib
import matplotlib.pyplot as plt

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # crates/lab/scripts
from csv_files import REPO

matplotlib.use("Agg")

ALTERNATION = REPO / "docs/ladder/l7-steering-adversary/attempt-alternation"


def rows(path):
    with open(path) as f:
        return list(csv.DictReader(f))


def job(seed_dir, name):
    """The job directory `<id>-<name>-seed<N>` (exactly this name: `failmaker-1` must not find
    `ego-failmaker-1`)."""
    pattern = re.compile(rf"\d+-{re.escape(name)}-seed\d+")
    found = [d for d in glob.glob(os.path.join(seed_dir, "jobs", "*")) if pattern.fullmatch(os.path.basename(d))]
    return found[0] if found else None


def style(ax, title, xlabel):
    ax.set_title(title)
    ax.set_xlabel(xlabel)
    ax.set_ylim(0, 1)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="lower right")


ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
ap.add_argument("--out", default=str(ALTERNATION / "rounds.png"), help="the PNG to write")
out = ap.parse_args().out
seeds = sorted(glob.glob(os.path.join(ALTERNATION, "seed-*")))
fig, axes = plt.subplots(len(seeds), 2, figsize=(12, 3.6 * len(seeds)), squeeze=False)
for (ax_ego, ax_adv), seed_dir in zip(axes, seeds):
    seed = seed_dir.rsplit("seed-", 1)[1]
    offset = 0
    for name in ["ego-idm", "ego-failmaker-1", "ego-failmaker-2", "ego-failmaker-3"]:
        d = job(seed_dir, name)
        if d is None or not os.path.exists(os.path.join(d, "validation.csv")):
            continue
        r = rows(os.path.join(d, "validation.csv"))
        x = [offset + int(v["updates"]) for v in r]
        ax_ego.plot(x, [float(v["success"]) for v in r], marker="o", ms=2, label=name)
        offset = x[-1]
    style(ax_ego, f"seed {seed}: ego phases, validation success among their own flow", "updates (phases end to end)")
    offset = 0
    for name in ["failmaker-1", "failmaker-2", "failmaker-3"]:
        d = job(seed_dir, name)
        if d is None:
            continue
        r = [v for v in rows(os.path.join(d, "curve.csv")) if int(v["episodes"]) >= 5]
        x = [offset + int(v["env_steps"]) for v in r]
        ax_adv.plot(x, [float(v["success"]) for v in r], lw=1, label=name)
        offset = x[-1]
    style(ax_adv, f"seed {seed}: adversary phases, the ego's training-window success", "environment steps (phases end to end)")
fig.tight_layout()
fig.savefig(out, dpi=110)
print("wrote", out)
