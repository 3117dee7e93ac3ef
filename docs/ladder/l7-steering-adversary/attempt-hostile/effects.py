"""FailMaker's effect on each ego per training seed, from the evaluation's episodes: success among
FailMaker minus among IDM, paired on the same (scenario, case, seed) starts, with a 95 % t
interval and a paired t-test's p; and how the episodes among FailMaker end.

    python3 docs/ladder/l7-steering-adversary/attempt-hostile/effects.py docs/ladder/l7-steering-adversary/attempt-hostile/seed-*/results/episodes.csv
"""

import csv
import math
import sys

from scipy import stats


def load(path):
    with open(path) as f:
        return list(csv.DictReader(f))


def main(paths):
    print("| seed | ego | among IDM | among FailMaker | effect (points) | 95 % CI | paired p | FailMaker episodes: collision / other failure / not arrived safely |")
    print("|---|---|---|---|---|---|---|---|")
    for path in paths:
        seed = path.split("seed-")[1].split("/")[0]
        rows = load(path)
        for ego in sorted({r["ego"] for r in rows}, reverse=True):
            by = {}
            for r in rows:
                if r["ego"] == ego:
                    by.setdefault(r["flow"], {})[(r["scenario"], r["case"], r["seed"])] = r
            idm, fm = by["IDM"], by["FailMaker"]
            keys = sorted(idm.keys() & fm.keys())
            d = [float(fm[k]["success"]) - float(idm[k]["success"]) for k in keys]
            n = len(d)
            mean = sum(d) / n
            sd = math.sqrt(sum((x - mean) ** 2 for x in d) / (n - 1))
            half = stats.t.ppf(0.975, n - 1) * sd / math.sqrt(n)
            p = stats.ttest_rel([float(fm[k]["success"]) for k in keys], [float(idm[k]["success"]) for k in keys]).pvalue
            a = sum(float(idm[k]["success"]) for k in keys) / n
            b = sum(float(fm[k]["success"]) for k in keys) / n
            col = sum(float(fm[k]["collision"]) for k in keys) / n
            unsafe = sum(1 - float(fm[k]["safety"]) for k in keys) / n
            stuck = sum(float(fm[k]["safety"]) * (1 - float(fm[k]["success"])) for k in keys) / n
            print(f"| {seed} | {ego} | {a:.3f} | {b:.3f} | {100 * mean:+.1f} | +-{100 * half:.1f} | {p:.1e} | {col:.3f} / {unsafe - col:.3f} / {stuck:.3f} |")


if __name__ == "__main__":
    main(sys.argv[1:])
