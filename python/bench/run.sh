#!/usr/bin/env bash
# The Python speed benchmark in its own venv: socialflow's wheel (release build) beside
# highway-env (and MetaDrive if it installs) from the Python registry. Writes
# docs/bench/python.json. Usage: python/bench/run.sh [seconds per measurement]
set -euo pipefail
cd "$(dirname "$0")/../.."
venv="${SOCIALFLOW_BENCH_VENV:-${HOME}/.cache/socialflow/bench-venv}"
[ -x "$venv/bin/python" ] || python3 -m venv "$venv"
"$venv/bin/pip" install -q --disable-pip-version-check highway-env
"$venv/bin/pip" install -q --disable-pip-version-check metadrive-simulator || echo "metadrive-simulator did not install; reported as such"
"$venv/bin/pip" install -q --disable-pip-version-check ./python
"$venv/bin/python" python/bench/bench_speed.py --seconds "${1:-10}" | tee docs/bench/python.json
