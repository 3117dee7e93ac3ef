#!/usr/bin/env bash
# The wgpu learner's test (`sac.device = "wgpu"`, the `wgpu` feature): the same seed and batches
# on wgpu (Vulkan) and on the CPU give the same losses and weights. Runs on Mesa's software
# Vulkan driver (lavapipe) where no GPU is present, installed from Debian's registry when this
# runs as root; otherwise a missing driver skips the test with a message, unless
# SOCIALFLOW_REQUIRE_VULKAN is set. `.ci/run` calls it after clippy.
set -euo pipefail
cd "$(dirname "$0")/.."
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-${HOME}/.cache/socialflow/target}"
has_driver() { compgen -G "/usr/share/vulkan/icd.d/*.json" >/dev/null && compgen -G "/usr/lib/*/libvulkan.so.1" >/dev/null; }
if ! has_driver && [ "$(id -u)" = 0 ]; then
  export DEBIAN_FRONTEND=noninteractive
  install() { apt-get install -y --no-install-recommends mesa-vulkan-drivers libvulkan1 >/dev/null; }
  install || { apt-get update >/dev/null && install; } || { echo "cannot install Debian's mesa-vulkan-drivers (lavapipe)" >&2; exit 1; }
fi
if ! has_driver; then
  if [ -n "${SOCIALFLOW_REQUIRE_VULKAN:-}" ]; then
    echo "no Vulkan driver (install mesa-vulkan-drivers and libvulkan1)" >&2
    exit 1
  fi
  echo "no Vulkan driver and not root: skipping the wgpu learner's test"
  exit 0
fi
cargo test --locked -p socialflow-sac --features wgpu --test sac wgpu -- --nocapture
