"""The IDM driver in the ego's seat beside every trained ego, on the grid's own episode starts.

The evaluation grid has no IDM ego (an ego is a trained policy), so the baseline comes from
`socialflow eval-flow --ego idm` on the same first 20 stored cases x seeds 0-1 of each scenario,
among the same flows (the IDM flow, or a trained flow's job directory). For replicate k of the
graph (run 1: `--data-dir runs/paper-small`, run 2: `runs/paper-small-seed1`):

    out=docs/archive/2026-11-25-report-seeds-0-1/run-$k/idm-ego; runs=runs/paper-small-seed1
    for s in intersection bottleneck merge roundabout; do
      socialflow eval-flow --flow idm --ego idm --scenario $s --cases 20 --seeds 2 --json > $out/IDM-$s.json
      socialflow eval-flow --policy $runs/jobs/3-flow-macad --ego idm --scenario $s --cases 20 --seeds 2 --json > $out/MACAD-$s.json
      # likewise 2-flow-copo (CoPO) and 4-flow-socialcomm (SocialComm)
    done
    python3 crates/lab/scripts/results/report_seeds_0_1/idm-ego-compare.py docs/archive/2026-11-25-report-seeds-0-1/run-$k/results/episodes.csv $out > $out/summary.md

Both replicates pooled (pairs within a replicate): give every run's pair of arguments, e.g.
`python3 crates/lab/scripts/results/report_seeds_0_1/idm-ego-compare.py
docs/archive/2026-11-25-report-seeds-0-1/run-1/results/episodes.csv.gz docs/archive/2026-11-25-report-seeds-0-1/run-1/idm-ego
docs/archive/2026-11-25-report-seeds-0-1/run-2/results/episodes.csv.gz docs/archive/2026-11-25-report-seeds-0-1/run-2/idm-ego > docs/archive/2026-11-25-report-seeds-0-1/idm-ego.md`.

Each trained ego's success is paired with the IDM ego's on the same (flow, scenario, case,
seed); the p-value is the paired t-test's in its normal approximation (160-640 pairs).
"""
import csv
import json
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # crates/lab/scripts
from csv_files import open_csv

FLOWS = ["IDM", "MACAD", "CoPO", "SocialComm"]
SCENARIOS = ["intersection", "bottleneck", "merge", "roundabout"]


def paired(d):
    n = len(d)
    m = sum(d) / n
    var = sum((x - m) ** 2 for x in d) / (n - 1)
    if var == 0:
        return m, 1.0 if m == 0 else 0.0
    return m, math.erfc(abs(m / math.sqrt(var / n)) / math.sqrt(2))


def main(sets):
    """`sets`: (episodes.csv, idm-ego dir) per replicate; pairs stay within a replicate."""
    idm, cross = {}, []
    for k, (episodes, idm_dir) in enumerate(sets):
        for f in FLOWS:
            for s in SCENARIOS:
                with open(f"{idm_dir}/{f}-{s}.json") as fh:
                    idm_episodes = json.load(fh)["episodes"]
                for e in idm_episodes:
                    idm[(k, f, s, e["case"], e["seed"])] = e["success"]
        cross += [dict(r, run=k) for r in csv.DictReader(open_csv(episodes)) if r["experiment"] == "cross"]
    key = lambda r, s=None: (r["run"], r["flow"], s or r["scenario"], int(r["case"]), int(r["seed"]))
    egos = list(dict.fromkeys(r["ego"] for r in cross))
    mean = lambda v: 100 * sum(v) / len(v)
    if len(sets) > 1:
        print(f"Pooled over {len(sets)} replicates (pairs within a replicate).")
        print()
    print("| ego | " + " | ".join(FLOWS) + " | mean | vs IDM ego (points, p) |")
    print("|---" * (len(FLOWS) + 3) + "|")
    base = [mean([v for k, v in idm.items() if k[1] == f]) for f in FLOWS]
    print("| IDM ego (zero residual) | " + " | ".join(f"{x:.1f}" for x in base) + f" | {sum(base) / 4:.1f} | |")
    for e in egos:
        rows = [r for r in cross if r["ego"] == e]
        per_flow = [mean([float(r["success"]) for r in rows if r["flow"] == f]) for f in FLOWS]
        d = [float(r["success"]) - idm[key(r)] for r in rows]
        m, p = paired(d)
        print(f"| {e} | " + " | ".join(f"{x:.1f}" for x in per_flow) + f" | {sum(per_flow) / 4:.1f} | {100 * m:+.1f}, p = {p:.1e} |")
    print()
    print("| ego | " + " | ".join(SCENARIOS) + " |")
    print("|---" * (len(SCENARIOS) + 1) + "|")
    for e in egos:
        cells = []
        for s in SCENARIOS:
            d = [float(r["success"]) - idm[key(r, s)] for r in cross if r["ego"] == e and r["scenario"] == s]
            m, p = paired(d)
            cells.append(f"{100 * m:+.1f} (p = {p:.1e})")
        print(f"| {e} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    args = sys.argv[1:]
    if not args or len(args) % 2:
        sys.exit("usage: idm-ego-compare.py EPISODES_CSV IDM_EGO_DIR [EPISODES_CSV IDM_EGO_DIR ...]")
    main(list(zip(args[0::2], args[1::2])))
