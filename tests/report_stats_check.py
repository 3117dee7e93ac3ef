"""An independent check of `socialflow report`'s statistics with scipy and statsmodels.

Usage:
    socialflow report RUN1 RUN2 --out DIR > findings.json
    python tests/report_stats_check.py findings.json RUN1/episodes.csv.gz RUN2/episodes.csv.gz

Each episodes file may be plain (`episodes.csv`) or gzipped (`episodes.csv.gz`, as committed);
a plain name that is absent is read from the `.gz` beside it.

The unit of every test is the stored case (scenario, case): a start's seeds (and, in the pooled
findings, its runs) are averaged first, then the starts one case has under several SVOs, flows
or egos. The check recomputes, from the episodes alone:

- every finding of every run and of the runs pooled: the paired tests (a one-sample t over the
  per-case differences, scipy), the "larger in merge" Welch tests over per-case differences and
  the intersection-union rule over their parts (the weakest part while every part points the
  claim's way; otherwise the strongest part against it, its p times the number of parts), with
  effect, standard error, p, the number of cases and of starts;
- each family's Holm-adjusted p (statsmodels' multipletests) and each verdict from it:
  "holds", "opposite" (the reverse shown: every part against the claim, each at least as
  clearly as the corrected p), "refuted" (a part against the claim, not the reverse) or "not
  significant", and the verdict across runs from the runs' verdicts;
- across runs, the DerSimonian-Laird estimate and tau2 (statsmodels' combine_effects, tau2
  truncated at 0 as DerSimonian and Laird define it) and the Hartung-Knapp-Sidik-Jonkman
  interval: t with k - 1 degrees of freedom, the variance scaled by the runs' weighted spread
  about the estimate (statsmodels' var_hksj), the scale floored at 1.

Exits non-zero naming the first number that differs, or a finding it does not know how to
recompute.
"""

import json
import re
import sys
from pathlib import Path

import numpy as np
import pandas as pd
from scipy import stats
from statsmodels.stats.meta_analysis import combine_effects
from statsmodels.stats.multitest import multipletests

ALPHA = 0.05
CASE = ["scenario", "case"]
SCENARIOS = ["intersection", "bottleneck", "merge", "roundabout"]


def close(what, ours, ref, rtol=1e-6, atol=1e-9):
    if not np.isclose(ours, ref, rtol=rtol, atol=atol):
        sys.exit(f"MISMATCH {what}: socialflow {ours!r}, reference {ref!r}")


def same(what, ours, ref):
    if ours != ref:
        sys.exit(f"MISMATCH {what}: socialflow {ours!r}, reference {ref!r}")


def read(path, replicate):
    """Episodes as the report reads them: the metric parsed as a 32-bit float."""
    path = str(path)
    if not path.endswith(".gz") and not Path(path).exists() and Path(path + ".gz").exists():
        path += ".gz"
    # pandas gunzips by the `.gz` suffix.
    e = pd.read_csv(path, dtype={"success": np.float32, "ego": str}, keep_default_na=False)
    e["success"] = e["success"].astype(np.float64)
    for col in ["svo_deg", "vehicles"]:
        e[col] = e[col].astype(str)
    e["replicate"] = replicate
    return e


def per_case(a, b, pair_on):
    """Per-case differences `a - b` of success: episodes paired on (replicate, seed, case) and
    `pair_on`, averaged per start (the pairing columns but replicate and seed), then per stored
    case. Returns (values, number of starts)."""
    key = ["replicate", "seed"] + CASE + pair_on
    d = (a.set_index(key).success - b.set_index(key).success).dropna().reset_index()
    starts = d.groupby(CASE + pair_on).success.mean().reset_index()
    cases = starts.groupby(CASE).success.mean()
    return 100.0 * cases.to_numpy(), len(starts)


def paired(a, b, pair_on):
    d, starts = per_case(a, b, pair_on)
    n = len(d)
    se = d.std(ddof=1) / np.sqrt(n)
    p = stats.ttest_1samp(d, 0.0).pvalue if se > 0 else (1.0 if d.mean() == 0 else 0.0)
    return {"effect": d.mean(), "se": se, "df": n - 1, "p": p, "n": n, "starts": starts, "against": "reverses"}


def welch(a, b, starts):
    n_a, n_b = len(a), len(b)
    se = np.sqrt(a.var(ddof=1) / n_a + b.var(ddof=1) / n_b)
    p = stats.ttest_ind(a, b, equal_var=False).pvalue
    return {"effect": a.mean() - b.mean(), "se": se, "p": p, "n": n_a + n_b, "starts": starts}


def all_of(parts):
    """The intersection-union rule over the parts' two-sided tests."""
    m = len(parts)
    if all(p["effect"] > 0 for p in parts):
        d = max(parts, key=lambda p: p["p"])
        return dict(d, against="reverses")
    against = [p for p in parts if p["effect"] <= 0]
    d = min(against, key=lambda p: (p["p"], p["effect"]))
    p_refutes = min(1.0, m * d["p"])
    reverses = all(p["effect"] < 0 for p in parts) and max(p["p"] for p in parts) <= p_refutes
    return dict(d, p=p_refutes, against="reverses" if reverses else "refutes")


def recompute(claim, e, meta):
    """The test of one finding on episodes `e`, or None for a claim this check does not know."""
    fq = e[e.experiment == "flow_quality"]
    flow = lambda rows, f: rows[rows.flow == f]
    if m := re.fullmatch(r"SocialComm flow succeeds more often than (.+) \(flow quality, all .*\)", claim):
        return paired(flow(fq, "SocialComm"), flow(fq, m[1]), ["ego"])
    if m := re.fullmatch(r"SocialComm flow succeeds more often than (.+) in merge", claim):
        merge = fq[fq.scenario == "merge"]
        return paired(flow(merge, "SocialComm"), flow(merge, m[1]), ["ego"])
    if m := re.fullmatch(r"SocialComm's advantage over (.+) is larger in merge than in each .*", claim):
        at = lambda s, f: flow(fq[fq.scenario == s], f)
        diffs = {
            s: per_case(at(s, "SocialComm"), at(s, m[1]), ["ego"])
            for s in SCENARIOS
            if (fq.scenario == s).any()
        }
        (dm, sm) = diffs["merge"]
        return all_of([welch(dm, d, sm + s) for k, (d, s) in diffs.items() if k != "merge"])
    if m := re.fullmatch(r"SocialComm beats (.+) over the SVO sweep in (.+)", claim):
        sw = e[(e.experiment == "svo_sweep") & (e.scenario == m[2])]
        return paired(flow(sw, "SocialComm"), flow(sw, m[1]), ["svo_deg"])
    ad = e[e.experiment == "adversary"]
    if m := re.fullmatch(r"Egos succeed less in (.+) than in (.+) \(pooled\)", claim):
        return paired(flow(ad, m[2]), flow(ad, m[1]), ["ego"])
    if m := re.fullmatch(r"(.+) degrades egos more than (.+?) \(pooled success .*\)", claim):
        return paired(flow(ad, m[2]), flow(ad, m[1]), ["ego"])
    cross = e[e.experiment == "cross"]
    ego = lambda rows, x: rows[rows.ego == x]
    if m := re.fullmatch(r"(.+) transfers best in (.+) \(success above every other .*\)", claim):
        ours, here = m[1], cross[cross.scenario == m[2]]
        others = [
            x
            for x in meta["egos"]
            if x not in (ours, meta.get("idm_ego")) and (here.ego == x).any()
        ]
        return all_of([paired(ego(here, ours), ego(here, x), ["flow"]) for x in others])
    if m := re.fullmatch(r"(.+) succeeds more often than the IDM driver in its seat \(.*\)", claim):
        return paired(ego(cross, m[1]), ego(cross, meta.get("idm_ego", "IDM ego")), ["flow"])
    return None


def verdict(effect, p_adjusted, against):
    if np.isfinite(p_adjusted) and p_adjusted < ALPHA and effect > 0:
        return "holds"
    if np.isfinite(p_adjusted) and p_adjusted < ALPHA and effect < 0:
        return "opposite" if against == "reverses" else "refuted"
    return "not-significant"


def runs_verdict(vs):
    n, holds, opposite = len(vs), vs.count("holds"), vs.count("opposite")
    against = opposite + vs.count("refuted")
    if n == 0:
        return "untested"
    if holds == n:
        return "holds"
    if opposite == n:
        return "opposite"
    if against == n:
        return "refuted"
    if holds and against:
        return "conflict"
    return "not-significant" if holds + against == 0 else "not-replicated"


def check_family(name, checks, episodes, meta):
    """Every finding of one family: its test, Holm p and verdict. Returns the numbers checked."""
    checked = 0
    _, holm, _, _ = multipletests([c["p_value"] for c in checks], alpha=ALPHA, method="holm")
    for c, h in zip(checks, holm):
        what = f"{name} '{c['claim']}'"
        ref = recompute(c["claim"], episodes, meta)
        if ref is None:
            sys.exit(f"UNCHECKED {what}: this check does not know how to recompute it; teach it")
        close(f"{what} effect", c["effect_points"], ref["effect"])
        close(f"{what} se", c["se_points"], ref["se"])
        close(f"{what} p", c["p_value"], ref["p"], atol=1e-12)
        same(f"{what} cases", c["n"], ref["n"])
        same(f"{what} starts", c.get("starts"), ref["starts"])
        same(f"{what} against", c.get("against"), ref["against"])
        close(f"{what} Holm p", c["p_adjusted"], h, atol=1e-12)
        same(f"{what} verdict", c["verdict"], verdict(c["effect_points"], h, ref["against"]))
        checked += 8
    return checked


def hksj(eff, var):
    """DerSimonian-Laird with the floored HKSJ interval, from its definition and statsmodels."""
    k = len(eff)
    res = combine_effects(eff, var, method_re="dl", use_t=True)
    # statsmodels leaves DerSimonian-Laird's tau2 negative when Q < k - 1; the estimator
    # truncates it at 0, where the random-effects quantities are the fixed-effect ones.
    if res.tau2 < 0:
        est, se_dl, tau2, var_h = res.mean_effect_fe, res.sd_eff_w_fe, 0.0, res.var_hksj_fe
    else:
        est, se_dl, tau2, var_h = res.mean_effect_re, res.sd_eff_w_re, res.tau2, res.var_hksj_re
    w = 1.0 / (var + tau2)
    mu = (w * eff).sum() / w.sum()
    scale = (w * (eff - mu) ** 2).sum() / (k - 1)
    close("HKSJ variance, definition vs statsmodels", scale / w.sum(), var_h, atol=1e-12)
    se = np.sqrt(max(var_h, se_dl**2))
    t = stats.t(k - 1)
    return {
        "estimate": est,
        "tau2": tau2,
        "se_dl": se_dl,
        "ci95_z": stats.norm.ppf(0.975) * se_dl,
        "hksj_scale": scale,
        "se": se,
        "df": k - 1,
        "ci95": t.ppf(0.975) * se,
        "p_value": 2 * t.sf(abs(est / se)),
    }


def main(findings_path, *episode_paths):
    findings = json.loads(Path(findings_path).read_text())
    meta_path = Path(episode_paths[0]).parent / "meta.json"
    meta = json.loads(meta_path.read_text()) if meta_path.exists() else {"egos": [], "idm_ego": "IDM ego"}
    runs = [read(p, k) for k, p in enumerate(episode_paths)]
    checked = 0
    for k, (run, f) in enumerate(zip(runs, findings["replicates"])):
        checked += check_family(f"run {k + 1}", f["checks"], run, meta)
    checked += check_family("runs pooled", findings["checks"], pd.concat(runs), meta)
    for a in findings["across"]:
        # Each run's entry is that run's own check, as checked above.
        for k, r in enumerate(a["runs"]):
            if r is not None and r not in findings["replicates"][k]["checks"]:
                sys.exit(f"MISMATCH run {k + 1} of '{a['key']}' across runs: not its own check")
        verdicts = [r["verdict"] if r else None for r in a["runs"]]
        ref = runs_verdict(verdicts) if None not in verdicts else "untested"
        same(f"verdict across runs of '{a['key']}'", a["verdict"], ref)
        checked += 1
        if a["combined"] is None:
            continue
        eff = np.array([r["effect_points"] for r in a["runs"]])
        var = np.array([r["se_points"] ** 2 for r in a["runs"]])
        if np.any(var == 0):
            continue
        ref = hksj(eff, var)
        for field, value in ref.items():
            what = f"random effects {field} of '{a['key']}'"
            close(what, a["combined"][field], value, atol=1e-12)
        checked += len(ref)
    print(f"{checked} numbers and verdicts agree with scipy/statsmodels")


if __name__ == "__main__":
    main(*sys.argv[1:])
