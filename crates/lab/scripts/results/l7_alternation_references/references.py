"""L7's first clause scored against the reference drivers: for every adversary of the alternation
(FailMaker-k, trained against the ego of the round before: RL/IDM, RARL-1, RARL-2), how much it
costs the ego it attacked and how much it costs the two scripted drivers in the same seat (the
IDM driver, IDM with MOBIL's lane changes), per training seed:

- the attack on each (success among FailMaker-k minus among IDM, paired on the same (scenario,
  case, seed) starts);
- the part of the attack aimed at the attacked ego: its attack minus the IDM driver's, paired on
  the same starts (a difference in differences; negative: the ego loses more than the
  reference), with Holm-corrected p over the seed's adversaries;
- where the egos end among FailMaker-k: the attacked ego, and the ego retrained against
  FailMaker-k (RARL-k), each minus the better scripted driver there.

    python3 crates/lab/scripts/results/l7_alternation_references/references.py \
        docs/ladder/l7-steering-adversary/attempt-alternation/references/seed-{1,2,3,5}/episodes.csv

Each file's learned egos come from the committed
`docs/ladder/l7-steering-adversary/attempt-alternation/seed-N/results/episodes.csv`; each seed is
one training run of the whole alternation and is reported on its own.
"""

import argparse
import sys
from pathlib import Path

from statsmodels.stats.multitest import multipletests

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # crates/lab/scripts
from csv_files import REPO
from results.l7_alternation.alternation import attack, load, values as success
from results.l7_lateral_rarl.recovery import paired

ALTERNATION = REPO / "docs/ladder/l7-steering-adversary/attempt-alternation"

ATTACKED = {1: "RL/IDM", 2: "RARL-1", 3: "RARL-2"}
REFS = ("IDM driver", "IDM+MOBIL")


def did(c, ego, ref, fm):
    """Per start: (ego's attack) - (ref's attack)."""
    return paired(attack(c[(ref, "IDM")], c[(ref, fm)]), attack(c[(ego, "IDM")], c[(ego, fm)]))


def main(paths):
    print("| seed | adversary | attacked ego | attack on it | on the IDM driver | on IDM+MOBIL | aimed at the ego (its attack - the IDM driver's) | p (Holm) | attacked ego - better scripted driver among the adversary | retrained ego (RARL-k) - the same |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for path in paths:
        seed = path.split("seed-")[1].split("/")[0]
        c = load(ALTERNATION / f"seed-{seed}" / "results" / "episodes.csv")
        c.update(load(path))
        rows = []
        for k, ego in ATTACKED.items():
            fm = f"FailMaker-{k}"
            att = {e: paired(success(c[(e, "IDM")]), success(c[(e, fm)])) for e in (ego,) + REFS}
            aimed = did(c, ego, "IDM driver", fm)
            best = max(REFS, key=lambda e: sum(success(c[(e, fm)]).values()) / len(c[(e, fm)]))
            edge = paired(success(c[(best, fm)]), success(c[(ego, fm)]))
            retrained = paired(success(c[(best, fm)]), success(c[(f"RARL-{k}", fm)]))
            rows.append((fm, ego, att, aimed, best, edge, retrained))
        holm = multipletests([r[3][2] for r in rows], method="holm")[1]
        for (fm, ego, att, aimed, best, edge, retrained), p in zip(rows, holm):
            f = lambda t: f"{100 * t[0]:+.1f} +- {100 * t[1]:.1f}"
            print(f"| {seed} | {fm} | {ego} | {f(att[ego])} | {f(att['IDM driver'])} | {f(att['IDM+MOBIL'])} | "
                  f"{f(aimed)} | {p:.2g} | {f(edge)} ({best}) | {f(retrained)} |")
    print()


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("episodes", nargs="+", help="references/seed-N/episodes.csv")
    main(ap.parse_args().episodes)
