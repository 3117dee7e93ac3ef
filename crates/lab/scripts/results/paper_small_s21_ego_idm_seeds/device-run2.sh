#!/bin/bash
# Device call 2: wait for the jobs (at most $1 s), stop any still running (they checkpoint on
# shutdown), then evaluate every run's last actor and each [validation] run's kept actor among
# IDM cars on the stored cases, beside the IDM ego. Run from the repository root after device-run1.sh:
# bash crates/lab/scripts/results/paper_small_s21_ego_idm_seeds/device-run2.sh [seconds]
set -u
B=$PWD/.dev/socialflow
T=${1:-150}; t=0
while [ $t -lt $T ] && pgrep -f "socialflow train" >/dev/null; do sleep 10; t=$((t+10)); done
bash "$(dirname "$0")/device-progress.sh" | tee $OUT/progress2.txt
pkill -TERM -f "socialflow train"; for i in $(seq 30); do pgrep -f "socialflow train" >/dev/null || break; sleep 1; done
mkdir -p /tmp/e/jobs
egos='{ name = "IDM-ego", job = "idm" }'
for s in 4 5 6 7; do for v in val noval; do
  j=$(ls -d /tmp/r/$v-$s/jobs/*-ego-idm | head -1)
  [ -f $j/checkpoint/actor.bpk ] || continue
  o=$([ $v = val ] && echo 20 || echo 30)
  d=/tmp/e/jobs/$((o+s))-ego-idm; mkdir -p $d; cp $j/config.toml $d/; cp $j/checkpoint/actor.bpk $d/policy.bpk
  egos="$egos, { name = \"$v$s-last\", job = \"ego-idm\", job_id = $((o+s)) }"
  if [ $v = val ] && [ -f $j/best_policy.bpk ]; then
    d=/tmp/e/jobs/$((10+s))-ego-idm; mkdir -p $d; cp $j/config.toml $d/; cp $j/best_policy.bpk $d/policy.bpk
    egos="$egos, { name = \"val$s-kept\", job = \"ego-idm\", job_id = $((10+s)) }"
  fi
done; done
cat > /tmp/e/grid.toml <<G
kind = "eval"
name = "val-vs-noval"
runs = "/tmp/e"
out = "/tmp/e/eval"
scenarios = ["intersection", "bottleneck", "merge", "roundabout"]
cases = 50
seeds = 1
envs = 25
flows = [{ name = "IDM", job = "idm" }]
egos = [$egos]
[experiments]
cross_validation = ["IDM"]
G
cat /tmp/e/grid.toml
( time $B eval /tmp/e/grid.toml ) 2>&1 | tail -20
mkdir -p /tmp/pack
for d in /tmp/r/*/; do n=$(basename $d); j=$(ls -d $d/jobs/*-ego-idm | head -1); mkdir -p /tmp/pack/$n; cp $j/curve.csv $j/validation.csv $j/policy.json $j/best_policy.json $j/state.json /tmp/pack/$n/ 2>/dev/null; tail -5 /tmp/r/$n.log > /tmp/pack/$n/log-tail.txt; done
cp -r /tmp/e/grid.toml /tmp/e/eval /tmp/pack/ 2>/dev/null
tar czf $OUT/results.tar.gz -C /tmp/pack .
ls -la $OUT
