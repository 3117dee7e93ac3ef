"""Where L7's egos end among the FailMaker that attacked RL/IDM, with the closed-road share
(`road_closed`, recorded since 2026-11-29: the ego timed out with standing vehicles leaving no
gap a car fits through on the lanes running its way within 30 m ahead), per training seed:

- how each ego's episodes end among IDM and among FailMaker-1: arrived, collision, other
  failure, not arrived safely with the road closed, not arrived safely with the road open;
- how much of RL/IDM's loss is closed roads: the attack (success among FailMaker-1 minus among
  IDM) beside the rise in closed-road endings, paired on the same (scenario, case, seed) starts;
- what is left to recover: on the starts where RL/IDM's road was closed, whether any ego
  arrived; on the others, RL/IDM's loss and RARL-3's recovery there;
- with `--committed`, that the learned egos' episodes reproduce the committed ones (the
  evaluation is deterministic and the new column changes no trajectory);
- with `--crawl`, the same split where vehicles slower than 1.5 m/s count as standing
  (`grid-crawl-seed-N.toml`, built with `crawling.patch`), after checking that those episodes
  are the same ones.

    python3 crates/lab/scripts/results/l7_alternation_blockade/blockade.py \
        docs/ladder/l7-steering-adversary/attempt-alternation/blockade/seed-{1,5}/episodes.csv \
        --committed docs/ladder/l7-steering-adversary/attempt-alternation/seed-{1,5}/results/episodes.csv \
        --crawl docs/ladder/l7-steering-adversary/attempt-alternation/blockade/crawl-seed-{1,5}/episodes.csv

Closed-road starts are chosen by how RL/IDM's episode ended, and FailMaker reacts to the ego, so
the split is descriptive: it says where the loss sits, not what another ego would meet there.
"""

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # crates/lab/scripts
from results.l7_alternation.alternation import load, values
from results.l7_lateral_rarl.recovery import paired

FM = "FailMaker-1"
SAME = ("success", "safety", "speed", "collision", "lane_change")


def shares(eps, column="road_closed"):
    """Shares of `{start: row}` that arrive, collide, fail otherwise, end safe and not arrived
    with the road closed (`column`), and with it open."""
    n = len(eps)
    f = lambda k: sum(float(r[k]) for r in eps.values()) / n
    arrived, safe, col, closed = f("success"), f("safety"), f("collision"), f(column)
    return arrived, col, 1 - safe - col, closed, safe - arrived - closed


def pct(x):
    return f"{100 * x + 0.0:.1f}" if abs(x) >= 5e-4 else "0.0"


def seed_of(path):
    return path.split("seed-")[1].split("/")[0]


def check(path, committed):
    new, old = load(path), load(committed)
    n = bad = 0
    for key, eps in new.items():
        if key not in old:
            continue
        for start, r in eps.items():
            n += 1
            o = old[key][start]
            bad += any(float(r[k]) != float(o[k]) for k in SAME)
    return n, bad


def main(paths, committed, crawl):
    for k, path in enumerate(paths):
        if committed:
            n, bad = check(path, committed[k])
            print(f"seed {seed_of(path)}: {n} episodes also in {committed[k]}, {bad} differ in {', '.join(SAME)}")
        if crawl:
            n, bad = check(crawl[k], path)
            print(f"seed {seed_of(path)}: {n} episodes also in {crawl[k]}, {bad} differ in {', '.join(SAME)}")
    print()
    splits(paths, "road_closed", "standing: slower than 0.5 m/s")
    if crawl:
        # The crawl files hold the same episodes with the lenient rule's column.
        splits(crawl, "road_closed", "standing: slower than 1.5 m/s", base_from=paths)


def splits(paths, column, rule, base_from=None):
    print(f"Closed roads with {rule}:")
    print()
    print("| seed | ego | flow | arrived | collision | other failure | not arrived, road closed | not arrived, road open |")
    print("|---|---|---|---|---|---|---|---|")
    cells = {seed_of(p): load(p) for p in paths}
    if base_from:
        # Cells among IDM come from the main files.
        for p in base_from:
            for key, eps in load(p).items():
                cells[seed_of(p)].setdefault(key, eps)
    for seed, c in cells.items():
        for ego in ("RL/IDM", "RARL-3", "IDM driver"):
            for flow in ("IDM", FM):
                s = shares(c[(ego, flow)], column)
                print(f"| {seed} | {ego} | {flow} | " + " | ".join(pct(x) for x in s) + " |")
    print()
    print("| seed | ego | attack on success (points, 95 % CI) | rise in closed-road endings (points, 95 % CI) |")
    print("|---|---|---|---|")
    for seed, c in cells.items():
        for ego in ("RL/IDM", "RARL-3", "IDM driver"):
            a, b = c[(ego, "IDM")], c[(ego, FM)]
            m, h, _ = paired(values(a), values(b))
            mc, hc, _ = paired(values(a, column), values(b, column))
            print(f"| {seed} | {ego} | {100 * m:+.1f} +- {100 * h:.1f} | {100 * mc:+.1f} +- {100 * hc:.1f} |")
    print()
    print("| seed | starts | RL/IDM's road closed | ... where RARL-3 / the IDM driver / any arrives | other starts: RL/IDM's loss | RARL-3's recovery there (points, 95 % CI, share of the loss) |")
    print("|---|---|---|---|---|---|")
    for seed, c in cells.items():
        rl, rarl, drv = c[("RL/IDM", FM)], c[("RARL-3", FM)], c[("IDM driver", FM)]
        base = c[("RL/IDM", "IDM")]
        closed = {s for s, r in rl.items() if float(r[column]) > 0}
        arr = lambda eps, s: float(eps[s]["success"]) > 0
        n = len(rl)
        nc = max(len(closed), 1)
        by_rarl = sum(arr(rarl, s) for s in closed) / nc
        by_drv = sum(arr(drv, s) for s in closed) / nc
        by_any = sum(arr(rarl, s) or arr(drv, s) for s in closed) / nc
        rest = set(rl) - closed
        loss, lh, _ = paired(values(base, keys=rest), values(rl, keys=rest))
        rec, rh, _ = paired(values(rl, keys=rest), values(rarl, keys=rest))
        share = f"{100 * rec / -loss:.0f} %" if loss < 0 else "no loss"
        print(f"| {seed} | {n} | {pct(len(closed) / n)} % | {pct(by_rarl)} / {pct(by_drv)} / {pct(by_any)} % | "
              f"{100 * loss:+.1f} +- {100 * lh:.1f} | {100 * rec:+.1f} +- {100 * rh:.1f} ({share}) |")
    print()


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("episodes", nargs="+", help="blockade/seed-N/episodes.csv, one per seed")
    ap.add_argument("--committed", nargs="*", default=[], help="the alternation's seed-N/results/episodes.csv, in the same order")
    ap.add_argument("--crawl", nargs="*", default=[], help="blockade/crawl-seed-N/episodes.csv, in the same order")
    a = ap.parse_args()
    for name in ("committed", "crawl"):
        if getattr(a, name) and len(getattr(a, name)) != len(a.episodes):
            ap.error(f"--{name} needs one file per episodes file, in the same order")
    main(a.episodes, a.committed, a.crawl)
