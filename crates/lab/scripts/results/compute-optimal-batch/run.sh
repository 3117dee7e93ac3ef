#!/usr/bin/env bash
# The compute-optimal batch: each arm trains for the same wall time, two runs side by side on the
# 2 cores, then `crates/lab/scripts/batch_sweep.py` reads the runs' validation lines against wall
# time. Two sweeps:
#   macad: lateral MACAD (configs/stage1/flow-macad.toml), batch 64 / 128 / 512, seeds 11 and 12,
#          720 s per run;
#   l4:    ladder L4 (configs/ladder/jobs/l4-ego-idm-brake.toml, the rung's job), batch 128 / 512,
#          seeds 0 and 1, 420 s per run, held-out validation added (50 cases per scenario, seed 7)
#          and the transition budget lifted so that the clock, not the budget, ends each run.
# Arms keep equal in samples what the recipe fixes in updates: replay samples per transition (32),
# the cloning and critic-only warm-up (64k and 192k samples), the policy lag (12.8k samples) and
# the validation spacing (256k samples on MACAD, 128k on L4); learning rates scale by
# sqrt(batch / 128).
#
#   SOCIALFLOW=target/release/socialflow crates/lab/scripts/results/compute-optimal-batch/run.sh macad runs/batch
#   SOCIALFLOW=target/release/socialflow crates/lab/scripts/results/compute-optimal-batch/run.sh l4 runs/l4batch
set -euo pipefail
cd "$(dirname "$0")/../../../../.."
SF=${SOCIALFLOW:-target/release/socialflow}
sweep=${1:?usage: run.sh macad|l4 <runs dir>}
out=${2:?usage: run.sh macad|l4 <runs dir>}
case "$sweep" in
macad)
  config=configs/stage1/flow-macad.toml wall_s=720 every_128=2000
  extra=(--set 'train.keep_actors_at=[]') ;;
l4)
  config=configs/ladder/jobs/l4-ego-idm-brake.toml wall_s=420 every_128=1000
  extra=(--set train.env_steps=240000 --set validation.episodes=50 --set validation.seed=7
         --set validation.envs=25) ;;
*) echo "run.sh: unknown sweep '$sweep' (macad or l4)" >&2; exit 2 ;;
esac
mkdir -p "$out"
arm() { # name batch samples_per_insert lr_actor lr_critic lr_alpha bc_updates critic_pretrain lag every seed
  local d="$out/$1-s${11}" rc=0
  rm -rf "$d"; mkdir -p "$d"
  timeout -s INT "$wall_s" "$SF" train "$config" --workers 1 --data-dir "$d" \
    --set sac.seed="${11}" --set sac.batch_size="$2" --set train.samples_per_insert="$3" \
    --set sac.lr_actor="$4" --set sac.lr_critic="$5" --set sac.lr_alpha="$6" \
    --set sac.bc_updates="$7" --set sac.critic_pretrain_updates="$8" --set train.max_policy_lag="$9" \
    --set validation.every_updates="${10}" "${extra[@]}" > "$d.log" 2>&1 || rc=$?
  # 124: stopped by the timeout, as planned (the job checkpoints on SIGINT).
  echo "$1-s${11} ended rc=$rc at $(date -u +%T)"
}
b128() { arm b128 128 0.25 0.0001 0.0005 0.0001 500 1500 100 "$every_128" "$1"; }
b512() { arm b512 512 0.0625 0.0002 0.001 0.0002 125 375 25 $((every_128 / 4)) "$1"; }
b64() { arm b64 64 0.5 0.0000707 0.000354 0.0000707 1000 3000 200 $((every_128 * 2)) "$1"; }
# Pairs mix arms so that no arm meets a quieter machine than another.
if [ "$sweep" = macad ]; then
  b128 11 & b512 11 & wait
  b64 11 & b512 12 & wait
  b128 12 & b64 12 & wait
else
  for seed in 0 1; do b128 "$seed" & b512 "$seed" & wait; done
fi
