"""Is the learned egos' lead over the rule particular to IDM traffic? Per alternation run and flow
(IDM, three learned flows that only brake, the run's FailMaker-1): each driver's success, and each
learned ego's lead over the better of the two scripted drivers in that flow (paired on the same
(scenario, case, seed) starts; 95 % t intervals; p Holm-corrected over each run's ten
comparisons).

    python3 crates/lab/scripts/results/l7_alternation_references/learned_flows.py \
        docs/ladder/l7-steering-adversary/attempt-alternation/references/learned-flows-seed-{2,5}/episodes.csv

Each file is one training run of the egos (the alternation's seeds 2 and 5), reported on its own;
the learned flows are one run (the 2026-11-27 paper-small graph).
"""

import argparse
import sys
from pathlib import Path

from statsmodels.stats.multitest import multipletests

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # crates/lab/scripts
from results.l7_alternation.alternation import load, values as success
from results.l7_lateral_rarl.recovery import paired

FLOWS = ("IDM", "MACAD", "CoPO", "SocialComm", "FailMaker-1")
LEARNED = ("RL/IDM", "RARL-3")
SCRIPTED = ("IDM driver", "IDM+MOBIL")


def main(paths):
    print("| run | flow | " + " | ".join(LEARNED + SCRIPTED) + " | RL/IDM - better scripted | RARL-3 - better scripted |")
    print("|---|---|" + "---|" * (len(LEARNED) + len(SCRIPTED) + 2))
    for path in paths:
        table(path)
    print()


def table(path):
    run = path.split("learned-flows-seed-")[1].split("/")[0]
    c = load(path)
    mean = lambda e, f: 100 * sum(success(c[(e, f)]).values()) / len(c[(e, f)])
    rows = []
    for f in FLOWS:
        best = max(SCRIPTED, key=lambda e: mean(e, f))
        for e in LEARNED:
            rows.append((f, e, best, paired(success(c[(best, f)]), success(c[(e, f)]))))
    holm = multipletests([r[3][2] for r in rows], method="holm")[1]
    for k, f in enumerate(FLOWS):
        cells = " | ".join(f"{mean(e, f):.1f}" for e in LEARNED + SCRIPTED)
        leads = []
        for (_, _, best, (m, h, _)), p in zip(rows[2 * k:2 * k + 2], holm[2 * k:2 * k + 2]):
            leads.append(f"{100 * m:+.1f} +- {100 * h:.1f} (Holm p {p:.2g}; {best})")
        print(f"| {run} | {f} | {cells} | " + " | ".join(leads) + " |")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("episodes", nargs="+", help="references/learned-flows-seed-N/episodes.csv")
    main(ap.parse_args().episodes)
