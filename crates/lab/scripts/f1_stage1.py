"""F1 at Stage 1's kept actors: SocialComm against MACAD as flows, seed by seed.

Reads one or more `episodes.csv` (or `.csv.gz`) of `socialflow eval` runs of
`configs/eval/stage1-f1-s<seed>.toml` (flow_quality cells named `MACAD-s<seed>@<mark>`,
`SocialComm-s<seed>@<mark>` and `SocialComm-s<seed>@<mark> msg45`) and tests, for every seed that
has both flows, SocialComm's flow success against MACAD's of the same seed on the same stored
cases: each case's success averaged over its seeds (the stored case is the unit), a paired
two-sided t-test per scenario and one over all the scenarios' cases, Holm-corrected over the
file's family (every seed x (scenarios + pooled) test). The messages probe beside it: SocialComm
with every neighbour's SVO told as 45 deg against the same actor told the truth.

`--pairs 15:14,13:13` tests the SocialComm run of one seed against the MACAD run of another
(each SocialComm run against each MACAD run that reached the plateau, when a seed's two runs did
not both get there); its rows' `seed` is `<SocialComm seed>:<MACAD seed>`.

The issue's rule: SocialComm - MACAD >= +2 points with Holm p < 0.05 (pooled) in every seed:
reproduced; <= -3 points in every seed: does not reproduce at these updates; otherwise mixed.
Messages count as used where the probe moves success by >= 3 points (Holm p < 0.05).
The minimum detectable effect (80 % power, two-sided 0.05) of each pooled test is printed.

    python3 crates/lab/scripts/f1_stage1.py runs/stage1/f1-s11/episodes.csv \\
        runs/stage1/f1-s12/episodes.csv --mark 120k --json docs/curves/stage1/f1-120k/f1.json

Needs scipy (the CI's report venv has it).
"""

from __future__ import annotations

import argparse
import re
import sys

from csv_files import write_json
from l5_noise import holm, paired_row, read_case_means

SCENARIOS = ["intersection", "bottleneck", "merge", "roundabout"]
FLOW = re.compile(r"^(MACAD|SocialComm)-s(\d+)@(\S+)( msg45)?$")


def pooled_cases(means: dict, flow: str) -> dict[tuple[str, int], float]:
    """Every scenario's case means of one flow, keyed by (scenario, case)."""
    return {(s, c): v for s in SCENARIOS for c, v in means.get((flow, s), {}).items()}


def test(a: dict, b: dict, label: str, scenario: str, seed: int) -> dict:
    return paired_row(a, b, {"test": label, "seed": seed, "scenario": scenario})


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("episodes", nargs="+", help="episodes.csv (or .csv.gz) files, concatenated")
    ap.add_argument("--mark", default="120k", help="the kept actors' mark in the flow names")
    ap.add_argument("--alpha", type=float, default=0.05)
    ap.add_argument("--pairs", help="SocialComm seed:MACAD seed pairs to test, comma-separated "
                    "(runs that are not a seed's pair: 15:14,13:13); default every seed with both")
    ap.add_argument("--json", help="also write the results here")
    a = ap.parse_args()

    means: dict = {}
    for path in a.episodes:
        for key, cases in read_case_means(path).items():
            if not FLOW.match(key[0]):
                continue  # the baselines (IDM, IDM+noise) an evaluation carries beside the flows
            if key in means:
                print(f"{path}: cells of flow `{key[0]}` in {key[1]} appear in two files", file=sys.stderr)
                return 2
            means[key] = cases
    if a.pairs:
        try:
            pairs = [(int(x), int(y)) for x, y in (p.split(":") for p in a.pairs.split(","))]
        except ValueError:
            print(f"--pairs {a.pairs!r}: expected SocialComm seed:MACAD seed pairs, e.g. 15:14,13:13",
                  file=sys.stderr)
            return 2
    else:
        seeds = sorted({int(m.group(2)) for f, _ in means if (m := FLOW.match(f)) and m.group(3) == a.mark})
        pairs = [(s, s) for s in seeds]
    tests = []
    probed = set()
    for sc_seed, mac_seed in pairs:
        seed = sc_seed if sc_seed == mac_seed else f"{sc_seed}:{mac_seed}"
        mac, sc, msg = (f"MACAD-s{mac_seed}@{a.mark}", f"SocialComm-s{sc_seed}@{a.mark}",
                        f"SocialComm-s{sc_seed}@{a.mark} msg45")
        for f in (mac, sc):
            missing = [s for s in SCENARIOS if (f, s) not in means]
            if missing:
                print(f"flow `{f}` has no flow_quality cells in {', '.join(missing)}", file=sys.stderr)
                return 2
        for s in SCENARIOS:
            tests.append(test(means[(sc, s)], means[(mac, s)], "SocialComm - MACAD", s, seed))
        tests.append(test(pooled_cases(means, sc), pooled_cases(means, mac), "SocialComm - MACAD", "pooled", seed))
        if sc_seed not in probed and all((msg, s) in means for s in SCENARIOS):
            probed.add(sc_seed)
            for s in SCENARIOS:
                tests.append(test(means[(msg, s)], means[(sc, s)], "told 45 deg - told the truth", s, sc_seed))
    if not tests:
        print(f"no seed has both MACAD-s<seed>@{a.mark} and SocialComm-s<seed>@{a.mark}", file=sys.stderr)
        return 2
    for family in {t["test"] for t in tests}:
        members = [t for t in tests if t["test"] == family]
        for t, ph in zip(members, holm([t["p"] for t in members])):
            t["p_holm"] = ph

    print(f"### F1 at the kept actors of {a.mark} updates: SocialComm against MACAD, paired by stored case\n")
    print("| test | seed | scenario | cases | SocialComm (%) | against (%) | difference (points) | Holm p | MDE (80 %) |")
    print("|---|---|---|---|---|---|---|---|---|")
    for t in tests:
        print(f"| {t['test']} | {t['seed']} | {t['scenario']} | {t['cases']} | {t['a']:.1f} | {t['b']:.1f} "
              f"| {t['diff']:+.1f} +- {t['ci95']:.1f} | {t['p_holm']:.2g} | {t['mde80']:.1f} |")
    pooled = [t for t in tests if t["test"] == "SocialComm - MACAD" and t["scenario"] == "pooled"]
    if all(t["diff"] >= 2.0 and t["p_holm"] < a.alpha for t in pooled):
        verdict = "reproduced: SocialComm >= MACAD + 2 points (Holm p < 0.05) in every seed"
    elif all(t["diff"] <= -3.0 for t in pooled):
        verdict = f"does not reproduce at {a.mark} updates: SocialComm <= MACAD - 3 points in every seed"
    else:
        verdict = "mixed: neither rule holds in every seed"
    seeds_text = ", ".join(str(t["seed"]) for t in pooled)
    print(f"\n- **F1 (seeds {seeds_text}, pooled over scenarios)**: {verdict}")
    probe = [t for t in tests if t["test"] == "told 45 deg - told the truth"]
    used = [t for t in probe if abs(t["diff"]) >= 3.0 and t["p_holm"] < a.alpha]
    if probe:
        where = ", ".join(f"seed {t['seed']} {t['scenario']}" for t in used) or "nowhere"
        print(f"- **Messages** (>= 3 points either way, Holm p < {a.alpha:g}): used in {where}")
    if a.json:
        write_json(a.json, {"mark": a.mark, "episodes": a.episodes, "alpha": a.alpha,
                            "tests": tests, "verdict": verdict})
    return 0


if __name__ == "__main__":
    sys.exit(main())
