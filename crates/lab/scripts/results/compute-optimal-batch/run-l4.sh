#!/usr/bin/env bash
# The compute-optimal batch on ladder L4 (configs/ladder/jobs/l4-ego-idm-brake.toml, the rung's
# job), batch 128 against 512: 420 s of wall time per run, two runs side by side, seeds 0 and 1.
# As run.sh: samples per transition, warm-up, policy lag and validation spacing equal in samples,
# learning rates by sqrt(batch / 128); held-out validation added (50 cases per scenario, seed 7)
# and the transition budget lifted so that the clock, not the budget, ends each run.
#
#   SOCIALFLOW=target/release/socialflow crates/lab/scripts/results/compute-optimal-batch/run-l4.sh runs/l4batch
set -euo pipefail
cd "$(dirname "$0")/../../../../.."
SF=${SOCIALFLOW:-target/release/socialflow}
out=${1:?usage: run-l4.sh <runs dir>}
mkdir -p "$out"
arm() { # name batch samples_per_insert lr_actor lr_critic lr_alpha bc_updates critic_pretrain lag every seed
  local d="$out/$1-s${11}" rc=0
  rm -rf "$d"; mkdir -p "$d"
  timeout -s INT 420 "$SF" train configs/ladder/jobs/l4-ego-idm-brake.toml --workers 1 --data-dir "$d" \
    --set sac.seed="${11}" --set sac.batch_size="$2" --set train.samples_per_insert="$3" \
    --set sac.lr_actor="$4" --set sac.lr_critic="$5" --set sac.lr_alpha="$6" \
    --set sac.bc_updates="$7" --set sac.critic_pretrain_updates="$8" --set train.max_policy_lag="$9" \
    --set train.env_steps=240000 --set validation.every_updates="${10}" --set validation.episodes=50 \
    --set validation.seed=7 --set validation.envs=25 > "$d.log" 2>&1 || rc=$?
  echo "$1-s${11} ended rc=$rc at $(date -u +%T)"
}
for seed in 0 1; do
  arm b128 128 0.25 0.0001 0.0005 0.0001 500 1500 100 1000 "$seed" &
  arm b512 512 0.0625 0.0002 0.001 0.0002 125 375 25 250 "$seed" &
  wait
done
