"""Plots the curve.csv files of sb3_sac.py / cleanrl_sac.py runs side by side, with each run's
evaluated success (trained actor dotted, IDM driver dashed) from its eval.json, and prints each
run's paired difference to the IDM driver on the same (case, seed) episodes.

    python python/examples/plot_curves.py runs/sb3-sac runs/cleanrl-sac --out curves.png --idm-reference merge

`--idm-reference SCENARIO` also drives the IDM driver (zero residual) on the training
distribution (random draws, 4 simulators, seed 0, as many env steps as the longest run) and
draws its success and mean return as a grey line: what the training curves start from.
"""

import argparse
import csv
import json
import math
import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import matplotlib.ticker  # noqa: E402


def paired(run):
    """Success of the trained actor minus the IDM driver's, paired by (case, seed): mean, 95 % CI
    (normal approximation), the episodes where exactly one of them succeeds and McNemar's exact
    two-sided p over those."""
    eps = {}
    for fn in sorted(os.listdir(run)):
        if fn.startswith("episodes-") and fn.endswith(".csv"):
            with open(os.path.join(run, fn)) as f:
                eps[fn[len("episodes-") : -len(".csv")]] = {(r["scenario"], r["case"], r["seed"]): float(r["success"]) for r in csv.DictReader(f)}
    idm = eps.pop("idm_driver")
    for name, mine in eps.items():
        d = [mine[k] - idm[k] for k in idm]
        n, mean = len(d), sum(d) / len(d)
        sd = math.sqrt(sum((x - mean) ** 2 for x in d) / (n - 1)) if n > 1 else float("nan")
        win, loss = sum(x > 0 for x in d), sum(x < 0 for x in d)
        p = min(1.0, 2 * sum(math.comb(win + loss, k) for k in range(min(win, loss) + 1)) / 2 ** (win + loss)) if win + loss else 1.0
        print(f"{run}: {name} - idm_driver success {mean:+.3f} +- {1.96 * sd / math.sqrt(n):.3f} over {n} paired episodes "
              f"(only {name} succeeds: {win}, only IDM: {loss}, McNemar p {p:.2g})")


def idm_reference(scenario, steps, envs=4, seed=0):
    """The IDM driver's success rate and mean return on the examples' training draws."""
    import numpy as np

    import socialflow

    v = socialflow.make_ego_vec(num_envs=envs, scenario=scenario, flow="idm", vehicles=(8, 20), action="idm-accel-residual", obs_format="flat", seed=seed)
    v.reset(seed=seed)
    ret, returns, successes = np.zeros(envs), [], []
    for _ in range(steps // envs):
        _, r, term, trunc, info = v.step(np.zeros((envs, 1), np.float32))
        ret += r
        for i in np.flatnonzero(term | trunc):
            returns.append(ret[i])
            successes.append(float(info["success"][i]))
            ret[i] = 0
    print(f"IDM driver on the training draws ({scenario}, {steps} env steps): success {np.mean(successes):.3f} over {len(successes)} episodes, mean return {np.mean(returns):.3f}")
    return float(np.mean(successes)), float(np.mean(returns))


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("runs", nargs="+", help="output directories of the examples")
    p.add_argument("--out", default="curves.png")
    p.add_argument("--idm-reference", metavar="SCENARIO", help="draw the IDM driver on the training distribution of SCENARIO")
    a = p.parse_args()
    max_steps, idm_heldout = 0, set()
    fig, (ax_s, ax_w, ax_r) = plt.subplots(1, 3, figsize=(16, 5))
    for run in a.runs:
        name = os.path.basename(os.path.normpath(run))
        with open(os.path.join(run, "curve.csv")) as f:
            rows = list(csv.DictReader(f))
        x = [int(r["env_steps"]) for r in rows]
        max_steps = max(max_steps, x[-1])
        success = [float(r["success_rate"]) for r in rows]
        (line,) = ax_s.plot(x, success, label=f"{name} (training, last 100 episodes)")
        ax_w.plot([float(r["wall_s"]) / 60 for r in rows], success, label=name, color=line.get_color())
        ax_r.plot(x, [float(r["mean_return"]) for r in rows], label=name, color=line.get_color())
        paired(run)
        ev = os.path.join(run, "eval.json")
        if os.path.exists(ev):
            with open(ev) as f:
                e = json.load(f)["eval"]
            for key, summ in e.items():
                if key == "idm_driver":
                    idm_heldout.add((summ[0]["success"]["mean"], summ[0]["episodes"]))
                else:
                    ax_s.axhline(summ[0]["success"]["mean"], ls=":", color=line.get_color(), lw=1.2, label=f"{name}: trained actor's mean action, held-out cases ({summ[0]['episodes']} episodes)")
    for mean, n in sorted(idm_heldout):
        ax_s.axhline(mean, ls="--", color="black", lw=1, label=f"IDM driver, the same held-out cases ({n} episodes)")
    if a.idm_reference:
        success, ret = idm_reference(a.idm_reference, max_steps)
        for ax, y in ((ax_s, success), (ax_w, success), (ax_r, ret)):
            ax.axhline(y, color="grey", lw=2, alpha=0.5, label="IDM driver on the training draws")
    ax_s.set(xlabel="env steps", ylabel="success rate", title="training success (last 100 episodes)")
    ax_w.set(xlabel="wall minutes of training", ylabel="success rate", title="the same against wall time")
    ax_r.set(xlabel="env steps", ylabel="mean episode return", title="return (last 100 episodes)")
    kilo = matplotlib.ticker.FuncFormatter(lambda v, _: f"{v / 1000:.0f}k")
    for ax in (ax_s, ax_r):
        ax.xaxis.set_major_formatter(kilo)
    lo = ax_s.get_ylim()[0]
    ax_s.set_ylim(lo - 0.25, None)  # room for the legend
    for ax in (ax_s, ax_w, ax_r):
        ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    fig.savefig(a.out, dpi=110)
    print(a.out)


if __name__ == "__main__":
    main()
