#!/usr/bin/env bash
# SAC updates on a lent accelerator: our learner on the GPU (wgpu; CUDA where it links) beside
# the same binary on that machine's CPU and the PyTorch reference, for the compact, paper-small
# and paper networks. One script, two halves, because the device machine reaches no registry:
#
#   build (here, where crates download):
#     crates/lab/scripts/results/bench/gpu_sac.sh build [dir]   # default dir: target/gpu-bench
#   run (on the lent machine, the dir carried with the working tree):
#     crates/lab/scripts/results/bench/gpu_sac.sh run [dir] [out]   # out default: $OUT or dir/out
#
# `build` makes `socialflow` with the `wgpu` feature and tries the `cuda` feature (burn 0.22's
# CUDA backend needs cubecl-llvm, whose build script downloads an LLVM bundle: on a machine that
# reaches only package registries it does not link, and the script says so and goes on).
# `run` writes one JSON per measurement into `out` (bench sac's --json, PyTorch's own JSON) and a
# summary line per measurement on stdout. A missing Vulkan driver or CUDA build is reported, not
# fatal: the CPU rows are still measured. Nothing here asserts a time.
set -euo pipefail
cd "$(dirname "$0")/../../../../.."
mode=${1:-}
dir=${2:-target/gpu-bench}
case "$mode" in
build)
  mkdir -p "$dir"
  target="${CARGO_TARGET_DIR:-${HOME}/.cache/socialflow/target}"
  cargo build --release --locked -p socialflow-cli --features wgpu
  cp "$target/release/socialflow" "$dir/socialflow-wgpu"
  if cargo build --release --locked -p socialflow-cli --features cuda 2>"$dir/cuda-build.log"; then
    cp "$target/release/socialflow" "$dir/socialflow-cuda"
    echo "built: $dir/socialflow-wgpu, $dir/socialflow-cuda"
  else
    echo "built: $dir/socialflow-wgpu; the cuda feature did not build (tail of $dir/cuda-build.log):"
    tail -n 5 "$dir/cuda-build.log"
  fi
  ;;
run)
  out=${3:-${OUT:-$dir/out}}
  mkdir -p "$out"
  { nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader || echo "no nvidia-smi"
    nproc; uptime; } > "$out/machine.txt" 2>&1
  cat "$out/machine.txt"
  # name: what to pass to `bench sac`; seconds: timing budget per measurement.
  nets=("compact:--size compact:20" "paper-small:--job configs/paper-small/flow-socialcomm.toml:10"
        "paper:--size paper:40")
  one() { # binary device net-name args seconds
    local bin=$1 dev=$2 name=$3 args=$4 secs=$5 f="$out/sf-$2-$(basename "$1")-$3.json"
    # shellcheck disable=SC2086
    if "$bin" bench sac --device "$dev" $args --seconds "$secs" --json > "$f" 2> "$f.err"; then
      python3 -c "import json,sys; d=json.load(open(sys.argv[1])); print(sys.argv[2], round(d['updates_per_s'], 3), 'updates/s')" \
        "$f" "$(basename "$bin") $dev $name"
    else
      echo "$(basename "$bin") $dev $name: failed ($(tail -n 1 "$f.err"))"
    fi
  }
  for spec in "${nets[@]}"; do
    IFS=: read -r name args secs <<< "$spec"
    one "$dir/socialflow-wgpu" cpu "$name" "$args" "$secs"
    one "$dir/socialflow-wgpu" wgpu "$name" "$args" "$secs"
    [ -x "$dir/socialflow-cuda" ] && one "$dir/socialflow-cuda" cuda "$name" "$args" "$secs"
  done
  # The PyTorch reference on the same machine, GPU and CPU, where torch is installed.
  if python3 -c 'import torch' 2>/dev/null; then
    PYTHONPATH=../shared/bench python3 crates/lab/scripts/results/bench/sac_torch_cuda.py paper:50 compact:100 small:100 \
      > "$out/torch_cuda.json" 2> "$out/torch_cuda.err" || echo "torch on cuda: failed ($(tail -n 1 "$out/torch_cuda.err"))"
    for size in compact paper; do
      python3 ../shared/bench/sac_torch.py --mode sac --size "$size" --iters 10 --warmup 2 --threads "$(nproc)" \
        > "$out/torch_cpu_$size.json" 2>&1 || echo "torch on cpu ($size): failed"
    done
  else
    echo "no torch here: the PyTorch rows are not measured"
  fi
  ;;
*)
  echo "usage: $0 build [dir] | run [dir] [out]" >&2
  exit 2
  ;;
esac
