#!/usr/bin/env bash
# Smoke test of the compose deployment: builds the images from scratch, starts the learner,
# two workers and Prometheus, submits a small job, waits for SAC updates to rise, checks the
# metrics endpoints and Prometheus' targets, and tears everything down.
# Usage: deploy/smoke.sh [BIN_DIR]   (default target/release; CI passes its debug build)
set -euo pipefail
cd "$(dirname "$0")"
bin_dir="$(cd "${1:-../target/release}" && pwd)"
sf="$bin_dir/socialflow"
compose() { if command -v docker-compose >/dev/null; then docker-compose "$@"; else docker compose "$@"; fi; }
free_port() { python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])'; }
get() { python3 -c 'import sys,urllib.request; print(urllib.request.urlopen(sys.argv[1], timeout=5).read().decode())' "$1"; }

./build-images.sh "$bin_dir"
export SOCIALFLOW_TOKEN="smoke-$(od -An -N12 -tx1 /dev/urandom | tr -d ' \n')"
export SOCIALFLOW_GRPC_PORT=$(free_port) SOCIALFLOW_ADMIN_PORT=$(free_port) SOCIALFLOW_PROMETHEUS_PORT=$(free_port)
project="sfsmoke$$"
cleanup() { compose -p "$project" logs --no-color > "${TMPDIR:-/tmp}/socialflow-smoke-$project.log" 2>&1 || true; compose -p "$project" down -v --remove-orphans >/dev/null 2>&1 || true; }
trap cleanup EXIT
services="learner worker prometheus"
have_prom=1
if ! docker image inspect socialflow-prometheus:local >/dev/null 2>&1; then
  echo "WARNING: no Prometheus image; running without it and skipping the scrape check" >&2
  services="learner worker"; have_prom=0
fi
compose -p "$project" up -d --scale worker=2 $services
echo "waiting for the learner"
for _ in $(seq 1 120); do get "http://127.0.0.1:$SOCIALFLOW_ADMIN_PORT/readyz" >/dev/null 2>&1 && break; sleep 1; done
get "http://127.0.0.1:$SOCIALFLOW_ADMIN_PORT/readyz"
url="http://127.0.0.1:$SOCIALFLOW_GRPC_PORT"
job=$("$sf" submit smoke-job.toml --learner "$url" | python3 -c 'import json,sys; print(json.load(sys.stdin)["job_id"])')
echo "submitted job $job"
updates_of() { "$sf" status "$job" --learner "$url" --json | python3 -c 'import json,sys; print(json.load(sys.stdin)["progress"]["updates"])'; }
first=""
for _ in $(seq 1 300); do
  u=$(updates_of)
  if [ "$u" -gt 0 ] && [ -z "$first" ]; then first=$u; echo "updates: $u"; fi
  if [ -n "$first" ] && [ "$u" -gt "$first" ]; then echo "updates rose: $first -> $u"; break; fi
  sleep 1
done
[ -n "$first" ] && [ "$(updates_of)" -gt "$first" ] || { echo "FAIL: updates did not rise" >&2; exit 1; }
metrics=$(get "http://127.0.0.1:$SOCIALFLOW_ADMIN_PORT/metrics")
echo "$metrics" | grep -E '^socialflow_learner_(updates_total|transitions_received_total|workers|policy_version) '
echo "$metrics" | grep -q '^socialflow_learner_updates_total [1-9]' || { echo "FAIL: learner metrics" >&2; exit 1; }
if [ "$have_prom" = 1 ]; then
echo "waiting for Prometheus to scrape learner and workers"
for _ in $(seq 1 60); do
  up=$(get "http://127.0.0.1:$SOCIALFLOW_PROMETHEUS_PORT/api/v1/targets" 2>/dev/null | python3 -c 'import json,sys; t=json.load(sys.stdin)["data"]["activeTargets"]; print(sum(1 for x in t if x["health"]=="up"))' 2>/dev/null || echo 0)
  [ "$up" -ge 3 ] && break; sleep 2
done
echo "prometheus targets up: $up (learner + 2 workers expected)"
[ "$up" -ge 3 ] || { echo "FAIL: prometheus targets" >&2; exit 1; }
fi
"$sf" cancel "$job" --learner "$url" >/dev/null
echo "smoke OK"
