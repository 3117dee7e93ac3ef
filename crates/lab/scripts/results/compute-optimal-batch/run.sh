#!/usr/bin/env bash
# The compute-optimal batch on lateral MACAD (configs/stage1/flow-macad.toml): each arm trains for
# the same wall time (720 s), two runs side by side on the 2 cores, then
# `crates/lab/scripts/batch_sweep.py` reads the runs' validation lines against wall time.
# Arms keep equal in samples what the recipe fixes in updates: replay samples per transition (32),
# the cloning and critic-only warm-up (64k and 192k samples), the policy lag (12.8k samples) and
# the validation spacing (256k samples); learning rates scale by sqrt(batch / 128).
#
#   SOCIALFLOW=target/release/socialflow crates/lab/scripts/results/compute-optimal-batch/run.sh runs/batch
set -euo pipefail
cd "$(dirname "$0")/../../../../.."
SF=${SOCIALFLOW:-target/release/socialflow}
out=${1:?usage: run.sh <runs dir>}
mkdir -p "$out"
arm() { # name batch samples_per_insert lr_actor lr_critic lr_alpha bc_updates critic_pretrain lag every seed
  local d="$out/$1-s${11}" rc=0
  rm -rf "$d"; mkdir -p "$d"
  timeout -s INT 720 "$SF" train configs/stage1/flow-macad.toml --workers 1 --data-dir "$d" \
    --set sac.seed="${11}" --set sac.batch_size="$2" --set train.samples_per_insert="$3" \
    --set sac.lr_actor="$4" --set sac.lr_critic="$5" --set sac.lr_alpha="$6" \
    --set sac.bc_updates="$7" --set sac.critic_pretrain_updates="$8" --set train.max_policy_lag="$9" \
    --set validation.every_updates="${10}" --set 'train.keep_actors_at=[]' > "$d.log" 2>&1 || rc=$?
  # 124: stopped by the timeout, as planned (the job checkpoints on SIGINT).
  echo "$1-s${11} ended rc=$rc at $(date -u +%T)"
}
b128() { arm b128 128 0.25 0.0001 0.0005 0.0001 500 1500 100 2000 "$1"; }
b512() { arm b512 512 0.0625 0.0002 0.001 0.0002 125 375 25 500 "$1"; }
b64() { arm b64 64 0.5 0.0000707 0.000354 0.0000707 1000 3000 200 4000 "$1"; }
# Pairs mix arms so that no arm meets a quieter machine than another.
b128 11 & b512 11 & wait
b64 11 & b512 12 & wait
b128 12 & b64 12 & wait
