#!/usr/bin/env python3
"""Why the Stage-1 flows' training-curve success sits 11-15 points below their validation.

Reads only committed files (docs/curves/paper-small-s24, -s25: <job>.csv, <job>.validation.csv,
<job>.config.toml) and prints the tables of docs/results/flow-curve-gap.md. Standard library only.

    python3 crates/lab/scripts/results/flow_curve_gap/flow_curve_gap.py

Method. A curve point's `success` is the mean over the learner's rolling window of the last
`train.window` (100) finished episodes, and its `episodes` column is the *cumulative* episode
count (services/learner/src/job.rs:333-338, 406, 415). The flows finish fewer than 100 episodes
in the whole run, so every point is the mean over all episodes so far, and the success of the
episodes that ended between two points is recovered exactly:
    block sum = n_k * S_k - n_(k-1) * S_(k-1),  block n = n_k - n_(k-1).
Each block is placed at the env_steps where its episodes were driven: the block's midpoint minus
half an episode lifetime L (all 8 envs run one episode each in L transitions, so
L = 8 * transitions / episodes over the policy phase; 8 = `--embedded 2` workers x `worker.envs`
4). Validation (same job, same env, every 1,000 updates) is interpolated over env_steps there.
Episodes ending before warmup_steps + L were driven (partly) by the IDM warm-up demonstrator.

Final gap  curve_last - val_last  =  (a) warm-up episodes in the window      (A - A_pol)
                                   + (b) residual at matched policy age      (A_pol - Vd_pol)
                                   + (c) older policies in the window         (Vd_pol - V_last)
   with (c) = (c1) episodes span ~2,500 updates (Vd_pol - Ve_pol) + (c2) window spans the run.
Gap to the kept actor adds (d) selection: V_last - V_kept (the best of 25 validations).
"""
import csv
import glob
import os
import re
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # crates/lab/scripts
import itertools

from csv_files import REPO

ROOT = os.fspath(REPO / "docs" / "curves")
RUNS = ["paper-small-s24", "paper-small-s25"]
ENVS_TOTAL = 8  # 2 embedded workers x worker.envs = 4 (1 env per scenario per worker)


def rows(path):
    with open(path) as f:
        return [{k: float(v) for k, v in r.items()} for r in csv.DictReader(f)]


def toml_int(text, key):
    return int(float(re.search(rf"^{key} = (\S+)", text, re.MULTILINE).group(1)))


def interp(pts, x):
    """Piecewise-linear over (env_steps, success), clamped at the ends."""
    if x <= pts[0][0]:
        return pts[0][1]
    for (x0, y0), (x1, y1) in itertools.pairwise(pts):
        if x0 <= x <= x1:
            return y0 if x1 == x0 else y0 + (y1 - y0) * (x - x0) / (x1 - x0)
    return pts[-1][1]


def analyse(run, job):
    base = os.path.join(ROOT, run, job)
    with open(base + ".config.toml") as f:
        cfg = f.read()
    window, warm, total = toml_int(cfg, "window"), toml_int(cfg, "warmup_steps"), toml_int(cfg, "env_steps")
    curve = rows(base + ".csv")
    val = rows(base + ".validation.csv")
    vpts = sorted({(v["env_steps"], v["success"]) for v in val if v["updates"] <= 24000})
    blocks, prev = [], (0.0, 0, 0.0)  # (env_steps, n, success)
    for r in curve:
        n, s, e = int(r["episodes"]), r["success"], r["env_steps"]
        if n > window:
            raise SystemExit(f"{run}/{job}: window full at {e}; blocks not recoverable")
        if n > prev[1]:
            blocks.append(((prev[0] + e) / 2, n - prev[1], n * s - prev[1] * prev[2]))
        prev = (e, n, s) if n > 0 else (e, 0, 0.0)
    E = prev[1]
    A = sum(b[2] for b in blocks) / E
    pol = [b for b in blocks if b[0] > warm]
    L = ENVS_TOTAL * (total - warm) / sum(b[1] for b in pol)
    pol = [b for b in blocks if b[0] > warm + L]  # fully policy-driven episodes
    n_pol = sum(b[1] for b in pol)
    A_pol = sum(b[2] for b in pol) / n_pol
    Vd = sum(b[1] * interp(vpts, b[0] - L / 2) for b in pol) / n_pol
    Ve = sum(b[1] * interp(vpts, b[0]) for b in pol) / n_pol
    res = [(b[1], b[2] / b[1] - interp(vpts, b[0] - L / 2)) for b in pol]
    # SE of the episode-weighted mean residual (blocks independent; weights n)
    wm = sum(n * x for n, x in res) / n_pol
    var = sum(n * (x - wm) ** 2 for n, x in res) / n_pol
    se = (var * sum(n * n for n, _ in res)) ** 0.5 / n_pol
    sd_ep = (var * n_pol / len(res)) ** 0.5  # one episode's SD (blocks of n have var sd^2/n)
    # the last ~2 generations (16 episodes) against validation at their driving time
    tail, k = [], 0
    for b in reversed(pol):
        tail.append(b)
        k += b[1]
        if k >= 2 * ENVS_TOTAL:
            break
    n_t = sum(b[1] for b in tail)
    T = sum(b[2] for b in tail) / n_t
    Vt = sum(b[1] * interp(vpts, b[0] - L / 2) for b in tail) / n_t
    V_last = val[-1]["success"]
    V_kept = max(v["success"] for v in val)
    diffs = [b["success"] - a["success"] for a, b in zip(val[-12:], val[-11:])]
    return {"run": run, "job": job, "E": E, "window": window, "L": L, "warm_n": E - n_pol, "A": A, "A_pol": A_pol,
            "Vd": Vd, "Ve": Ve, "V_last": V_last, "V_kept": V_kept, "res": wm, "se": se, "n_t": n_t, "T": T, "Vt": Vt,
            "vsd": statistics.pstdev(diffs) / 2 ** 0.5, "curve_last": curve[-1]["success"],
            "W": (A * E - A_pol * n_pol) / (E - n_pol), "sd_ep": sd_ep}


def main():
    out = []
    for run in RUNS:
        for p in sorted(glob.glob(os.path.join(ROOT, run, "*-flow-*.validation.csv"))):
            job = os.path.basename(p)[: -len(".validation.csv")]
            if re.search(r"-flow-(copo|macad|socialcomm)$", job):
                out.append(analyse(run, job))
    print("| run | job | episodes (window) | L transitions | curve last | val last | val kept | gap last | gap kept |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in out:
        print(f"| {r['run'][-3:]} | {r['job']} | {r['E']} ({r['window']}) | {r['L']:.0f} | {r['curve_last']:.3f} | "
              f"{r['V_last']:.3f} | {r['V_kept']:.3f} | {100*(r['curve_last']-r['V_last']):+.1f} | {100*(r['curve_last']-r['V_kept']):+.1f} |")
    print()
    print("Decomposition, points (curve_last - val_last = a + b + c1 + c2; kept adds d):")
    print("| run | job | warm-up eps (mean) | (a) warm-up | (b) matched residual +- SE | (c1) in-episode lag | (c2) window spans run | (d) selection | last 16 eps vs val then (SE) |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in out:
        a = r["A"] - r["A_pol"]
        b = r["A_pol"] - r["Vd"]
        c1 = r["Vd"] - r["Ve"]
        c2 = r["Ve"] - r["V_last"]
        d = r["V_last"] - r["V_kept"]
        assert abs((a + b + c1 + c2) - (r["A"] - r["V_last"])) < 1e-9
        print(f"| {r['run'][-3:]} | {r['job']} | {r['warm_n']} ({r['W']:.3f}) | {100*a:+.1f} | {100*b:+.1f} +- {100*r['se']:.1f} | "
              f"{100*c1:+.1f} | {100*c2:+.1f} | {100*d:+.1f} | {r['T']:.3f} vs {r['Vt']:.3f} ({r['n_t']} eps, {r['sd_ep'] / r['n_t'] ** 0.5:.3f}) |")
    bs = [r["A_pol"] - r["Vd"] for r in out]
    print(f"\nMean of (b) over the {len(bs)} jobs: {100*statistics.mean(bs):+.1f} points (SD {100*statistics.stdev(bs):.1f}); "
          f"one episode's success SD ~{statistics.mean(r['sd_ep'] for r in out):.3f}")
    print()
    print("Validation point-to-point noise (SD of one point, last 12 points): "
          + ", ".join(f"{r['run'][-3:]}/{r['job']} {r['vsd']:.3f}" for r in out))


if __name__ == "__main__":
    main()
