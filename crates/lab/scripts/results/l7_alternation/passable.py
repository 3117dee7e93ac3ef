"""An optimistic bound on L7's recovery from the egos already evaluated: among FailMaker-1, the
share of starts (scenario, case, seed) that no evaluated ego completes, per scenario, and the
success of picking, per start, an ego that arrives (after the fact, among runs whose traffic
differs: optimistic). Each file is one training seed's `episodes.csv`; its egos are every ego
evaluated among FailMaker-1 in it and in the further files given with `--also`.

    python3 crates/lab/scripts/results/l7_alternation/passable.py \
      docs/ladder/l7-steering-adversary/attempt-alternation/seed-1/results/episodes.csv.gz \
      --also docs/ladder/l7-steering-adversary/attempt-alternation/probe-unanchored/seed-1/results/episodes.csv.gz
"""

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # crates/lab/scripts
from results.l7_alternation.alternation import load

FLOW = "FailMaker-1"


def main(path, also):
    cells = load(path)
    for extra in also:
        for (ego, flow), eps in load(extra).items():
            cells.setdefault((ego, flow), eps)
    egos = sorted(e for e, f in cells if f == FLOW)
    starts = sorted(cells[("RL/IDM", FLOW)])
    arrived = {k: any(float(cells[(e, FLOW)][k]["success"]) == 1 for e in egos) for k in starts}
    rl = sum(float(cells[("RL/IDM", FLOW)][k]["success"]) for k in starts) / len(starts)
    rl_idm = sum(float(r["success"]) for r in cells[("RL/IDM", "IDM")].values()) / len(cells[("RL/IDM", "IDM")])
    best = sum(arrived.values()) / len(starts)
    loss = rl_idm - rl
    print(f"{path}: egos {', '.join(egos)}")
    print(f"  no ego arrives in {100 * (1 - best):.1f} % of {len(starts)} starts; per scenario:", end="")
    for sc in sorted({k[0] for k in starts}):
        ks = [k for k in starts if k[0] == sc]
        print(f" {sc} {100 * sum(not arrived[k] for k in ks) / len(ks):.1f} %", end="")
    print()
    share = f"{100 * (best - rl) / loss:.0f} %" if loss > 0 else "(no loss)"
    print(f"  best-of-egos success {100 * best:.1f} % vs RL/IDM {100 * rl:.1f} % (among IDM {100 * rl_idm:.1f} %): recovers {share} of the loss")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("episodes", help="a seed-N/results/episodes.csv file")
    ap.add_argument("--also", action="append", default=[], metavar="CSV", help="more episodes of the same seed (e.g. a probe's)")
    a = ap.parse_args()
    main(a.episodes, a.also)
