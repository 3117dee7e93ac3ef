"""Is each adversary aimed at its own ego, or at learned egos in general? RL/IDM of two runs among
FailMaker-1 of both (each FailMaker-1 trained against its own run's RL/IDM), with the IDM driver
as the reference. For each adversary F and ego E:

- aimed(E, F): E's attack by F (success among F minus among IDM) minus the IDM driver's attack by
  F, paired on the same (scenario, case, seed) starts (as `references.py`);
- own minus other: for the same adversary, its own run's ego's attack minus the other run's ego's
  attack, paired on the same starts (the reference cancels); negative: F hurts the ego it trained
  against more. p-values Holm-corrected over the adversaries.

    python3 crates/lab/scripts/results/l7_alternation_references/cross.py \
        docs/ladder/l7-steering-adversary/attempt-alternation/references/cross/seeds-{1-5,3-2}/episodes.csv

The egos' episodes among IDM come from the committed
`docs/ladder/l7-steering-adversary/attempt-alternation/seed-N/results/episodes.csv`, the IDM driver's from
`docs/ladder/l7-steering-adversary/attempt-alternation/references/seed-N/episodes.csv`. Two runs per pair: a comparison of training runs, each
reported on its own.
"""

import argparse
import os
import sys
from pathlib import Path

from statsmodels.stats.multitest import multipletests

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # crates/lab/scripts
from csv_files import REPO
from results.l7_alternation.alternation import attack, load
from results.l7_lateral_rarl.recovery import paired

ALTERNATION = REPO / "docs/ladder/l7-steering-adversary/attempt-alternation"


def main(paths):
    rows = []
    for path in paths:
        a, b = os.path.basename(os.path.dirname(path)).split("-")[1:]
        cross = load(path)
        runs = {}
        for s in (a, b):
            committed = load(ALTERNATION / f"seed-{s}" / "results" / "episodes.csv")
            refs = load(ALTERNATION / "references" / f"seed-{s}" / "episodes.csv")
            runs[s] = (committed[("RL/IDM", "IDM")], refs)
        for f in (a, b):
            fm = f"FailMaker-1 seed {f}"
            ref_eps = runs[f][1]
            ref = attack(ref_eps[("IDM driver", "IDM")], ref_eps[("IDM driver", "FailMaker-1")])
            atk = {e: attack(runs[e][0], cross[(f"RL/IDM seed {e}", fm)]) for e in (a, b)}
            other = b if f == a else a
            aimed = {e: paired(ref, atk[e]) for e in (a, b)}
            rows.append((fm, f, other, aimed, paired(atk[other], atk[f])))
    holm = multipletests([r[4][2] for r in rows], method="holm")[1]
    print("| adversary | aimed at its own run's RL/IDM | aimed at the other run's RL/IDM | own minus other | p (Holm) |")
    print("|---|---|---|---|---|")
    t = lambda x: f"{100 * x[0]:+.1f} +- {100 * x[1]:.1f}"
    for (fm, own, other, aimed, diff), p in zip(rows, holm):
        print(f"| {fm} | {t(aimed[own])} (seed {own}) | {t(aimed[other])} (seed {other}) | {t(diff)} | {p:.2g} |")
    print()


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("episodes", nargs="+", help="cross/seeds-A-B/episodes.csv")
    main(ap.parse_args().episodes)
