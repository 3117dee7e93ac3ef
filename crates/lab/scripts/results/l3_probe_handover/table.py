#!/usr/bin/env python3
"""Markdown tables of `socialflow probe --kind handover` points (JSON lines), one file per run.

    python3 crates/lab/scripts/results/l3_probe_handover/table.py \
        docs/ladder/l3-roundabout-direct/probe-handover/seed-{0,1}.jsonl

Action components are (speed reference, steer), in action units ([-1, 1]: 0.1 is 0.3 m/s of
reference speed or 4.5 degrees of steer)."""
import json
import sys

f = lambda v: "/".join(f"{x:+.3f}" for x in v)
g = lambda v: "/".join(f"{x:.3f}" for x in v)


def loop(s):
    if not s:
        return "-"
    return f"{s['success']:.2f} ({1 - s['safety']:.2f})"


print(
    "| run | updates after hand-over | gap to IDM: actor | gap: averaged actor | bias (actor) "
    "| dQ/da | share of dQ/da pointing away from IDM | critic's best offset along the axis "
    "| its Q gain | IDM rated at least as high | closed loop, averaged: success (failed) "
    "| closed loop, actor: success (failed) |"
)
print("|" + "---|" * 12)
for path in sys.argv[1:]:
    name = path.rsplit("/", 1)[-1].split(".")[0]
    with open(path) as fh:
        points = [json.loads(line)["point"] for line in fh if line.startswith("{")]
    for p in points:
        if "averaged" in p:
            av, ac = loop(p["averaged"]), loop(p["actor"])
        else:  # the first runs: the averaged actor only, and its collision rate
            av, ac = f"{p['success']:.2f} (collision {p['collision']:.2f})", "-"
        print(
            f"| {name} | {p['since_handover']} | {g(p['gap'])} | {g(p['gap_averaged'])} "
            f"| {f(p['bias'])} | {f(p['grad'])} | {g(p['grad_away'])} | {f(p['axis_best'])} "
            f"| {g(p['axis_gain'])} | {p['idm_rated_higher']:.2f} | {av} | {ac} |"
        )
