"""The IDM driver in the ego's seat beside every trained ego, on the grid's own episode starts.

The evaluation grid has no IDM ego (an ego is a trained policy), so the baseline comes from
`socialflow eval-flow --ego idm` on the same first 20 stored cases x seeds 0-1 of each scenario,
among the same flows (the IDM flow, or a trained flow's job directory):

    for s in intersection bottleneck merge roundabout; do
      socialflow eval-flow --flow idm --ego idm --scenario $s --cases 20 --seeds 2 --json > IDM-$s.json
      socialflow eval-flow --policy runs/paper-small/jobs/3-flow-macad --ego idm --scenario $s --cases 20 --seeds 2 --json > MACAD-$s.json
      # likewise 2-flow-copo (CoPO) and 4-flow-socialcomm (SocialComm)
    done
    python3 docs/report/idm-ego/compare.py docs/report/results/episodes.csv docs/report/idm-ego

Each trained ego's success is paired with the IDM ego's on the same (flow, scenario, case,
seed); the p-value is the paired t-test's in its normal approximation (160-640 pairs).
"""
import collections, csv, json, math, sys

FLOWS = ["IDM", "MACAD", "CoPO", "SocialComm"]
SCENARIOS = ["intersection", "bottleneck", "merge", "roundabout"]


def paired(d):
    n = len(d)
    m = sum(d) / n
    var = sum((x - m) ** 2 for x in d) / (n - 1)
    if var == 0:
        return m, 1.0 if m == 0 else 0.0
    return m, math.erfc(abs(m / math.sqrt(var / n)) / math.sqrt(2))


def main(episodes, idm_dir):
    idm = {}
    for f in FLOWS:
        for s in SCENARIOS:
            for e in json.load(open(f"{idm_dir}/{f}-{s}.json"))["episodes"]:
                idm[(f, s, e["case"], e["seed"])] = e["success"]
    cross = [r for r in csv.DictReader(open(episodes)) if r["experiment"] == "cross"]
    egos = list(dict.fromkeys(r["ego"] for r in cross))
    mean = lambda v: 100 * sum(v) / len(v)
    print("| ego | " + " | ".join(FLOWS) + " | mean | vs IDM ego (points, p) |")
    print("|---" * (len(FLOWS) + 3) + "|")
    base = [mean([v for k, v in idm.items() if k[0] == f]) for f in FLOWS]
    print("| IDM ego (zero residual) | " + " | ".join(f"{x:.1f}" for x in base) + f" | {sum(base) / 4:.1f} | |")
    for e in egos:
        rows = [r for r in cross if r["ego"] == e]
        per_flow = [mean([float(r["success"]) for r in rows if r["flow"] == f]) for f in FLOWS]
        d = [float(r["success"]) - idm[(r["flow"], r["scenario"], int(r["case"]), int(r["seed"]))] for r in rows]
        m, p = paired(d)
        print(f"| {e} | " + " | ".join(f"{x:.1f}" for x in per_flow) + f" | {sum(per_flow) / 4:.1f} | {100 * m:+.1f}, p = {p:.1e} |")
    print()
    print("| ego | " + " | ".join(SCENARIOS) + " |")
    print("|---" * (len(SCENARIOS) + 1) + "|")
    for e in egos:
        cells = []
        for s in SCENARIOS:
            d = [float(r["success"]) - idm[(r["flow"], s, int(r["case"]), int(r["seed"]))] for r in cross if r["ego"] == e and r["scenario"] == s]
            m, p = paired(d)
            cells.append(f"{100 * m:+.1f} (p = {p:.1e})")
        print(f"| {e} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
