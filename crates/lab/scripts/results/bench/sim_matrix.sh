#!/usr/bin/env bash
# Simulator throughput matrix: 4 scenarios x {20, 40} vehicles x {1, 2} threads x both layouts.
# Usage: crates/lab/scripts/results/bench/sim_matrix.sh [seconds] > docs/bench/sim.jsonl
set -euo pipefail
secs=${1:-5}
bin=${SOCIALFLOW:-target/release/socialflow}
for s in intersection bottleneck merge roundabout; do
  for v in 20 40; do
    for t in 1 2; do
      for l in query-centric ego-frame; do
        "$bin" bench sim --scenario "$s" --vehicles "$v" --threads "$t" --seconds "$secs" --layout "$l" --json
      done
    done
  done
done
