#!/usr/bin/env python3
"""Lay out a run's kept actors as finished jobs that `socialflow eval` can name.

An evaluation grid names learned flows by job (`job = "macad-s13-at-240000"`) and finds them in
a learner data directory's `jobs/<id>-<name>/` (a `config.toml` and a `policy.bpk`). A Stage-1
run keeps its actors at fixed update counts (`train.keep_actors_at`: `kept/actor-<N>.bpk`), and its
last actor is its checkpoint's (`checkpoint/actor.bpk`, with the update count in
`checkpoint/state.json`; a job with `[validation]` finishes with its best validated actor as
`policy.bpk`, not its last). This writes,
for each `RUN:N` given, `OUT/jobs/<i>-<label>-at-<N>/` with the run's `config.toml` (its `name`
changed to `<label>-at-<N>`) and that actor as `policy.bpk`; `<label>` is the run directory's
name (`macad-s13`). `N` is a kept count, or `last` for the run's last actor (its update count
read from the checkpoint). `last` is for a run's own data directory (`runs/stage1/macad-s13`,
checkpoint included); the committed runs under docs/curves/stage1/ carry no checkpoint (removed
2026-12-07), and seed 13's last actors are kept there as `kept/actor-240128.bpk`:

    python3 crates/lab/scripts/kept_runs.py --out runs/stage1/kept240 \\
        docs/curves/stage1/macad-s13:240128 docs/curves/stage1/socialcomm-s13:240128

Refuses (exit 2, naming the file) an actor or config that is not there, and an OUT whose
`jobs/` already holds a directory of the same name with other weights.
"""

import argparse
import json
import os
import re
import shutil
import sys


def last_actor(run):
    """The run's last actor (its checkpoint's) and the update count the checkpoint records."""
    state = os.path.join(run, "checkpoint", "state.json")
    with open(state, encoding="utf-8") as f:
        updates = json.load(f).get("updates")
    if not isinstance(updates, int):
        raise TypeError(f"{state}: no whole-number `updates`")
    return os.path.join(run, "checkpoint", "actor.bpk"), updates


def lay_out(out, spec, index):
    run, _, at = spec.rpartition(":")
    if not run or not at:
        raise ValueError(f"`{spec}`: expected RUN:N or RUN:last")
    run = run.rstrip("/")
    label = os.path.basename(run)
    if at == "last":
        actor, updates = last_actor(run)
    elif at.isdigit():
        updates = int(at)
        actor = os.path.join(run, "kept", f"actor-{updates}.bpk")
    else:
        raise ValueError(f"`{spec}`: N must be a whole number of updates or `last`")
    if not os.path.isfile(actor):
        raise FileNotFoundError(f"{actor}: no such actor (kept counts: {kept_counts(run)})")
    name = f"{label}-at-{updates}"
    with open(os.path.join(run, "config.toml"), encoding="utf-8") as f:
        config = f.read()
    config, n = re.subn(r'(?m)^name\s*=\s*"[^"]*"', f'name = "{name}"', config, count=1)
    if n != 1:
        raise ValueError(f"{run}/config.toml: no top-level `name = \"...\"` line to rename")
    dest = os.path.join(out, "jobs", f"{index}-{name}")
    if os.path.isdir(dest):
        with open(os.path.join(dest, "policy.bpk"), "rb") as a, open(actor, "rb") as b:
            if a.read() != b.read():
                raise FileExistsError(f"{dest}: holds other weights; choose another --out")
    os.makedirs(dest, exist_ok=True)
    with open(os.path.join(dest, "config.toml"), "w", encoding="utf-8") as f:
        f.write(config)
    shutil.copyfile(actor, os.path.join(dest, "policy.bpk"))
    return dest, actor


def kept_counts(run):
    kept = os.path.join(run, "kept")
    if not os.path.isdir(kept):
        return "none"
    found = sorted(int(m.group(1)) for n in os.listdir(kept) if (m := re.match(r"actor-(\d+)\.bpk$", n)))
    return ", ".join(map(str, found)) or "none"


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True, help="the data directory to write jobs/ into")
    ap.add_argument("runs", nargs="+", metavar="RUN:N", help="a run directory and a kept update count, or `last`")
    a = ap.parse_args()
    try:
        for i, spec in enumerate(a.runs, 1):
            dest, actor = lay_out(a.out, spec, i)
            print(f"{dest}: {actor}")
    except (OSError, ValueError, TypeError) as e:
        print(f"kept_runs: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
