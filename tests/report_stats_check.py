"""An independent check of `socialflow report`'s statistics with scipy and statsmodels.

Usage:
    socialflow report RUN1 RUN2 --out DIR > findings.json
    python tests/report_stats_check.py findings.json RUN1/episodes.csv RUN2/episodes.csv

Checks, for every run: each "... than the IDM driver in its seat" finding's effect, standard
error and p from a one-sample t-test (scipy) on per-start differences (seeds averaged within a
start); every run's Holm-adjusted p over its findings (statsmodels' multipletests); and, across
runs, each claim's DerSimonian-Laird random-effects estimate, its standard error and tau2
(statsmodels' combine_effects, tau2 truncated at 0 as DerSimonian and Laird define it). Exits non-zero naming the first number that differs.
"""

import json
import sys

import numpy as np
import pandas as pd
from scipy import stats
from statsmodels.stats.meta_analysis import combine_effects
from statsmodels.stats.multitest import multipletests


def close(what, ours, ref, tol=1e-6):
    if not np.isclose(ours, ref, rtol=tol, atol=tol):
        sys.exit(f"MISMATCH {what}: socialflow {ours!r}, reference {ref!r}")


def ego_vs_idm(episodes, ego, idm):
    """Per-start (flow, scenario, case) success differences of `ego` - `idm` in the cross cells."""
    cross = episodes[episodes.experiment == "cross"]
    key = ["flow", "scenario", "case", "seed"]
    a = cross[cross.ego == ego].set_index(key).success
    b = cross[cross.ego == idm].set_index(key).success
    d = (a - b).dropna().reset_index()
    return d.groupby(["flow", "scenario", "case"]).success.mean().to_numpy()


def main(findings_path, *episode_paths):
    findings = json.load(open(findings_path))
    runs = [pd.read_csv(p) for p in episode_paths]
    checked = 0
    for k, (run, f) in enumerate(zip(runs, findings["replicates"])):
        checks = f["checks"]
        # Holm over the run's family.
        raw = [c["p_value"] for c in checks]
        _, holm, _, _ = multipletests(raw, alpha=0.05, method="holm")
        for c, h in zip(checks, holm):
            close(f"run {k + 1} Holm p of '{c['claim']}'", c["p_adjusted"], h)
            checked += 1
        # One-sample t on per-start differences.
        for c in checks:
            if "than the IDM driver in its seat" not in c["claim"]:
                continue
            ego = c["claim"].split(" succeeds")[0]
            d = 100.0 * ego_vs_idm(run, ego, "IDM ego")
            t = stats.ttest_1samp(d, 0.0)
            close(f"run {k + 1} effect of '{ego}'", c["effect_points"], d.mean())
            close(f"run {k + 1} se of '{ego}'", c["se_points"], d.std(ddof=1) / np.sqrt(len(d)))
            close(f"run {k + 1} p of '{ego}'", c["p_value"], t.pvalue, tol=1e-9)
            assert c["n"] == len(d), (c["n"], len(d))
            checked += 4
    # Random effects across runs.
    for a in findings["across"]:
        if a["combined"] is None:
            continue
        eff = np.array([r["effect_points"] for r in a["runs"]])
        var = np.array([r["se_points"] ** 2 for r in a["runs"]])
        if np.any(var == 0):
            continue
        res = combine_effects(eff, var, method_re="dl")
        # statsmodels leaves DerSimonian-Laird's tau2 negative when Q < k - 1; the estimator
        # truncates it at 0, where the random-effects estimate is the fixed-effect one.
        if res.tau2 < 0:
            est, se, tau2 = res.mean_effect_fe, res.sd_eff_w_fe, 0.0
        else:
            est, se, tau2 = res.mean_effect_re, res.sd_eff_w_re, res.tau2
        close(f"random-effects estimate of '{a['key']}'", a["combined"]["estimate"], est)
        close(f"random-effects se of '{a['key']}'", a["combined"]["se"], se)
        close(f"tau2 of '{a['key']}'", a["combined"]["tau2"], tau2)
        checked += 3
    print(f"{checked} numbers agree with scipy/statsmodels")


if __name__ == "__main__":
    main(*sys.argv[1:])
