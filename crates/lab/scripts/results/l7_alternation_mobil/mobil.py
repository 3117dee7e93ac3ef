"""What a driver that steers takes back from FailMaker-1: IDM with MOBIL's lane changes
(`job = "idm-mobil"`) in the ego's seat, beside RL/IDM (the ego FailMaker-1 attacked), RARL-3
and the IDM driver (lane keeping, the same longitudinal driver as IDM+MOBIL), per training seed:

- how each ego's episodes end among IDM and among FailMaker-1 (arrived, collision, other failure,
  timed out walled in, timed out with the road open) and how often it changed lanes;
- the attack on each ego (success among FailMaker-1 minus among IDM, paired on the same
  (scenario, case, seed) starts);
- what steering buys: IDM+MOBIL minus the IDM driver, and IDM+MOBIL minus RL/IDM as a share of
  RL/IDM's loss (L7's recovery clause, here met by a scripted driver rather than a retrained
  ego), on all starts and on the starts where RL/IDM's road stayed open; p-values Holm-corrected
  over the family of these comparisons in each seed.

    python3 crates/lab/scripts/results/l7_alternation_mobil/mobil.py \
        docs/ladder/l7-steering-adversary/attempt-alternation/mobil/seed-{1,5}/episodes.csv \
        --others docs/ladder/l7-steering-adversary/attempt-alternation/blockade/seed-{1,5}/episodes.csv

The MOBIL driver's episodes come from one evaluation per seed; the others are the committed
blockade episodes (same stored cases, seeds and batch). FailMaker-1 reacts to whoever drives the
ego, so IDM+MOBIL meets the attack that FailMaker learned against RL/IDM, as every other ego here
does. Each seed is one FailMaker training run: results are reported per run, not pooled.
"""

import argparse
import sys
from pathlib import Path

from statsmodels.stats.multitest import multipletests

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # crates/lab/scripts
from results.l7_alternation.alternation import load, values as col
from results.l7_alternation_blockade.blockade import FM, pct, seed_of, shares
from results.l7_lateral_rarl.recovery import paired

MOBIL = "IDM+MOBIL"
EGOS = ("IDM driver", MOBIL, "RL/IDM", "RARL-3")


def main(paths, others):
    cells = {}
    for p, o in zip(paths, others):
        c = load(o)
        c.update(load(p))
        cells[seed_of(p)] = c
    print("| seed | ego | flow | arrived | collision | other failure | walled in | timed out, road open | changed lanes |")
    print("|---|---|---|---|---|---|---|---|---|")
    for seed, c in cells.items():
        for ego in EGOS:
            for flow in ("IDM", FM):
                eps = c[(ego, flow)]
                lane = sum(float(r["lane_change"]) for r in eps.values()) / len(eps)
                print(f"| {seed} | {ego} | {flow} | " + " | ".join(pct(x) for x in shares(eps)) + f" | {pct(lane)} |")
    print()
    print("Paired differences in success (points, 95 % CI; p Holm-corrected within the seed):")
    print()
    print("| seed | comparison | starts | difference | p (Holm) | share of RL/IDM's loss |")
    print("|---|---|---|---|---|---|")
    for seed, c in cells.items():
        rl_fm = c[("RL/IDM", FM)]
        open_starts = {s for s, r in rl_fm.items() if float(r["road_closed"]) == 0}
        rows = []
        for ego in EGOS:
            rows.append((f"attack on {ego}: among {FM} - among IDM", "all",
                         paired(col(c[(ego, "IDM")], "success"), col(c[(ego, FM)], "success")), None))
        for keys, label in ((None, "all"), (open_starts, "RL/IDM's road open")):
            loss = paired(col(c[("RL/IDM", "IDM")], "success", keys), col(rl_fm, "success", keys))
            for a, b, flow in ((("IDM driver", MOBIL, FM)), ("IDM driver", MOBIL, "IDM"), ("RL/IDM", MOBIL, FM),
                               ("RARL-3", MOBIL, FM)):
                d = paired(col(c[(a, flow)], "success", keys), col(c[(b, flow)], "success", keys))
                share = d[0] / -loss[0] if a == "RL/IDM" and loss[0] < 0 else None
                rows.append((f"{b} - {a} among {flow}", label, d, share))
        holm = multipletests([r[2][2] for r in rows], method="holm")[1]
        for (label, starts, (m, h, _), share), p in zip(rows, holm):
            s = f"{100 * share:.0f} %" if share is not None else ""
            print(f"| {seed} | {label} | {starts} | {100 * m:+.1f} +- {100 * h:.1f} | {p:.2g} | {s} |")
    print()


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("episodes", nargs="+", help="mobil/seed-N/episodes.csv, one per seed")
    ap.add_argument("--others", nargs="+", required=True, help="blockade/seed-N/episodes.csv, in the same order")
    a = ap.parse_args()
    if len(a.others) != len(a.episodes):
        ap.error("--others needs one file per episodes file, in the same order")
    main(a.episodes, a.others)
