#!/bin/bash
# Device call 1: eight paper-small RL/IDM jobs (seeds 4-7, with and without [validation]) at once.
# Run from the repository root: bash crates/lab/scripts/results/paper_small_s21_ego_idm_seeds/device-run1.sh [seconds]
# .dev/ holds the carried release binary (socialflow) and the jobs' configs (cfg/<val|noval>-<seed>.toml:
# docs/curves/paper-small-s21-ego-idm-seeds/<val|noval>-<seed>/config.toml).
set -u
B=$PWD/.dev/socialflow
export RAYON_NUM_THREADS=2
mkdir -p /tmp/r
{ date -u; nproc; lscpu | grep -i 'model name'; nvidia-smi --query-gpu=name,driver_version --format=csv,noheader; } > $OUT/machine.txt 2>&1
cat $OUT/machine.txt
$B --help >/dev/null || { echo "binary does not run"; ldd $B; exit 3; }
for s in 4 5 6 7; do for v in val noval; do
  setsid nohup $B train .dev/cfg/$v-$s.toml --workers 2 --quiet --data-dir /tmp/r/$v-$s > /tmp/r/$v-$s.log 2>&1 < /dev/null &
done; done
T=${1:-480}; t=0
while [ $t -lt $T ]; do sleep 30; t=$((t+30)); echo "--- $t s"; uptime; done
bash "$(dirname "$0")/device-progress.sh" | tee $OUT/progress1.txt
