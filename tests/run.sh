#!/usr/bin/env bash
# The test command: sets up what the tests read back with, then builds and runs every test.
# Without it, `cargo test` alone skips the Python package's tests and the TensorBoard, ONNX and
# promtool checks (each prints why); with it they run, and a missing tool fails them. Needs only
# the Rust toolchain, gcc, python3 and network access to the Debian and Python registries (the
# tools are cached under ~/.cache/socialflow). `.ci/run` calls this after fmt and clippy.
set -euo pipefail
cd "$(dirname "$0")/.."
step() { echo "== tests: $* (at ${SECONDS} s, $(date -u +%H:%M:%S))"; }
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-${HOME}/.cache/socialflow/target}"
cache="${HOME}/.cache/socialflow"
# promtool (Debian's prometheus package, unpacked, no root needed) checks the /metrics text in
# the e2e tests; with SOCIALFLOW_REQUIRE_PROMTOOL a missing one fails them instead of skipping.
step "promtool"
tools="$cache/tools"
if [ ! -x "$tools/usr/bin/promtool" ]; then
  mkdir -p "$tools/deb"
  fetch_prom() { (cd "$tools/deb" && rm -f prometheus_*.deb && apt-get download prometheus >/dev/null 2>&1); }
  fetch_prom || { apt-get update >/dev/null 2>&1 || true; fetch_prom; } || { echo "cannot fetch Debian's prometheus package (promtool)" >&2; exit 1; }
  dpkg -x "$tools"/deb/prometheus_*.deb "$tools"
fi
export PROMTOOL="$tools/usr/bin/promtool" SOCIALFLOW_REQUIRE_PROMTOOL=1
# The full-disk test mounts a small tmpfs and the network test makes namespaces, links and
# iptables rules of its own: as root they must run, not skip.
if [ "$(id -u)" = 0 ]; then export SOCIALFLOW_REQUIRE_TMPFS=1 SOCIALFLOW_REQUIRE_NETNS=1; fi
"$PROMTOOL" check rules deploy/alerts.yml
# A headless Chromium (Debian's) for the episode viewer's browser test (tests/viewer.rs); as root
# it is installed if missing and the test must run, not skip. Its screenshot is kept in
# ~/.cache/socialflow/artifacts/viewer.png.
step "chromium"
if [ "$(id -u)" = 0 ]; then
  if ! command -v chromium >/dev/null 2>&1; then
    apt_chromium() { DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends chromium >/dev/null; }
    apt_chromium || { apt-get update >/dev/null 2>&1 || true; apt_chromium; } || { echo "cannot install Debian's chromium (the viewer's browser test)" >&2; exit 1; }
  fi
  export SOCIALFLOW_REQUIRE_BROWSER=1
fi
export SOCIALFLOW_ARTIFACTS="$cache/artifacts"
# One cached venv for the Python sides of the tests: the official tensorboard package reads a
# job's event files, onnxruntime runs an exported policy, and the socialflow Python package
# (built from this tree below) runs its pytest suite with Gymnasium's and PettingZoo's checkers;
# scipy, statsmodels and pandas check the report's statistics (`.ci/run`).
step "python venv"
pyvenv="$cache/pyvenv"
if ! "$pyvenv/bin/python" -c 'import tensorboard, onnxruntime, numpy, pytest, gymnasium, pettingzoo, scipy, statsmodels, pandas' 2>/dev/null; then
  python3 -m venv "$pyvenv"
  "$pyvenv/bin/pip" install -q --disable-pip-version-check "tensorboard==2.21.0" "onnxruntime>=1.17" "numpy>=1.22" "pytest>=7" "gymnasium>=1.1" "pettingzoo>=1.24" "scipy>=1.11" "statsmodels>=0.14" "pandas>=2"
fi
export SOCIALFLOW_TB_PYTHON="$pyvenv/bin/python" SOCIALFLOW_ONNX_PYTHON="$pyvenv/bin/python"
# The Python package from this tree (maturin from the Python registry builds it; the dev profile
# reuses the debug build's optimised dependencies); its tests run inside `cargo test`
# (tests/python_pkg.rs) with this interpreter.
# A wheel is built once; the test venv installs it, and a fresh venv installs it with its
# dependencies from the Python registry and imports it, as a user's `pip install <wheel>` would.
step "python package (maturin wheel)"
wheels="$cache/wheels"
rm -rf "$wheels"
MATURIN_PEP517_ARGS="--profile dev" "$pyvenv/bin/pip" wheel -q --disable-pip-version-check --no-deps ./python -w "$wheels"
wheel=$(ls "$wheels"/socialflow-*.whl)
"$pyvenv/bin/pip" install -q --disable-pip-version-check --force-reinstall --no-deps "$wheel"
step "the wheel in a fresh venv"
fresh="$cache/fresh-venv"
python3 -m venv --clear "$fresh"
"$fresh/bin/pip" install -q --disable-pip-version-check "$wheel"
(cd / && "$fresh/bin/python" -m socialflow --help >/dev/null && "$fresh/bin/python" -c '
import socialflow
env = socialflow.make_ego(scenario="merge", flow="idm")
obs, info = env.reset(seed=0)
obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
print("fresh venv: socialflow", socialflow.__version__, "imports and steps")')
export SOCIALFLOW_PKG_PYTHON="$pyvenv/bin/python"
step "build and test"
cargo build --workspace --bins --locked && cargo test --workspace --locked
