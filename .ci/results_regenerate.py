"""Result pages regenerate from their committed inputs: a spot check run by CI.

Each check runs one result script of crates/lab/scripts/ on the committed per-episode or
validation files it was run on, and compares what it prints and the JSON it writes, byte for
byte, with the committed files a page cites. The report (`docs/report/`) and the README's ladder
table are checked by their own CI steps; these cover the Stage-1 results (the plateau table, F1
at 120k and at the plateau, L5 against the noise-matched IDM flow, the companion run), the
paper-style FailMaker's cost to the egos and the compute-optimal batch tables. A difference names
the file: regenerate it with the command the check shows (its page gives the same one), or find
what changed the script.

    python .ci/results_regenerate.py        # needs scipy (CI's report venv has it)
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile

REPO = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
STAGE1 = "docs/curves/stage1"
F1_120K = f"{STAGE1}/f1-120k/episodes.csv.gz"
PLATEAU = f"{STAGE1}/f1-plateau/episodes.csv.gz"

# (script, its arguments, committed stdout, committed --json output)
FAILMAKER = "docs/results/failmaker-paper"
LEVER = "docs/results/probes/constant-message-lateral"
BATCH = "docs/results/compute-optimal-batch"

CHECKS = [
    ("failmaker_cost.py", [f"{FAILMAKER}/episodes.csv.gz", f"{FAILMAKER}/episodes-s10.csv.gz",
                           "--runs", "9,10", "--flows",
                           "FailMaker-paper,FailMaker-paper r2,FailMaker-paper r1,FailMaker"],
     f"{FAILMAKER}/cost.md", f"{FAILMAKER}/cost.json"),
    ("failmaker_cost.py", [f"{LEVER}/episodes-s9.csv.gz", f"{LEVER}/episodes-s10.csv.gz", "--runs", "9,10",
                           "--flows", "SocialComm told0,SocialComm told90", "--no-gate"],
     f"{LEVER}/lever.md", f"{LEVER}/lever.json"),
    ("batch_sweep.py", ["table", f"{BATCH}/points.csv", "--level", "0.75", "--at", "240,480,720"],
     f"{BATCH}/table.md", f"{BATCH}/table.json"),
    ("batch_sweep.py", ["table", f"{BATCH}/points-l4.csv", "--level", "0.8", "--at", "120,240,420"],
     f"{BATCH}/table-l4.md", f"{BATCH}/table-l4.json"),
    ("plateau.py",
     [f"{STAGE1}/macad-s{seed}" for seed in (11, 12, 13, 14)]
     + [f"{STAGE1}/socialcomm-s{seed}" for seed in (11, 12, 13, 14, 15)]
     + [f"{STAGE1}/copo-s11"],
     f"{STAGE1}/plateau.md", f"{STAGE1}/plateau.json"),
    ("f1_stage1.py", [F1_120K, "--mark", "120k"],
     f"{STAGE1}/f1-120k/f1.md", f"{STAGE1}/f1-120k/f1.json"),
    ("l5_noise.py", [F1_120K, "--run", "stage 1, seeds 11 and 12, kept actors at 120k, against IDM+noise"],
     f"{STAGE1}/f1-120k/vs-idm-noise.md", f"{STAGE1}/f1-120k/vs-idm-noise.json"),
    ("l5_noise.py", [f"{STAGE1}/copo-s11-eval/episodes.csv.gz", "--run", "stage 1 CoPO, seed 11, kept actors and the job against IDM+noise"],
     f"{STAGE1}/copo-s11-eval/vs-idm-noise.md", f"{STAGE1}/copo-s11-eval/vs-idm-noise.json"),
    ("f1_stage1.py", [PLATEAU, "--mark", "end", "--pairs", "13:13,13:14,15:13,15:14"],
     f"{STAGE1}/f1-plateau/f1-end.md", f"{STAGE1}/f1-plateau/f1-end.json"),
    ("l5_noise.py", [PLATEAU, "--run", "stage 1 at the plateau: the last actors, SocialComm seed 15's kept actors, the companion and its control, against IDM+noise"],
     f"{STAGE1}/f1-plateau/vs-idm-noise.md", f"{STAGE1}/f1-plateau/vs-idm-noise.json"),
    ("told_ego.py", [f"{STAGE1}/told-ego-s15/episodes.csv.gz"],
     f"{STAGE1}/told-ego-s15/told-ego.md", f"{STAGE1}/told-ego-s15/told-ego.json"),
    ("l5_noise.py", [PLATEAU, "--baseline", "Control-s13@24k", "--min-gain", "0", "--run", "the companion (SocialComm warm-started from MACAD seed 13) against its control (MACAD warm-started the same way)"],
     f"{STAGE1}/f1-plateau/vs-control.md", f"{STAGE1}/f1-plateau/vs-control.json"),
]


def read(path: str) -> bytes:
    with open(path, "rb") as f:
        return f.read()


def main() -> int:
    failed = []
    with tempfile.TemporaryDirectory() as tmp:
        for script, args, md, js in CHECKS:
            out_json = os.path.join(tmp, os.path.basename(js))
            cmd = [sys.executable, os.path.join("crates/lab/scripts", script), *args, "--json", out_json]
            run = subprocess.run(cmd, cwd=REPO, capture_output=True, check=False)
            shown = " ".join(cmd[1:-2]) + f" --json {js} > {md}"
            if run.returncode != 0:
                failed.append(f"{shown}: exited {run.returncode}: {run.stderr.decode(errors='replace').strip()}")
                continue
            for committed, made in ((md, run.stdout), (js, read(out_json))):
                if made != read(os.path.join(REPO, committed)):
                    failed.append(f"{committed} is not what `{shown}` makes of the committed inputs")
            print(f"regenerates: {md}, {js}")
    for f in failed:
        print(f"results_regenerate: {f}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
