#!/usr/bin/env bash
# Validates the Kubernetes manifests offline: renders every overlay with render.py (no kubectl),
# validates each object against the Kubernetes schemas (kubernetes-validate, pinned below), and
# checks them against the code with check.py (flags and env vars against the binary's --help,
# ports against learner.toml, probe paths, image name, metric names, config keys).
# Usage: deploy/k8s/validate.sh BIN_DIR [CACHE_DIR]
#   BIN_DIR holds the `socialflow` binary (e.g. target/release); CACHE_DIR keeps the venv
#   (default ${TMPDIR:-/tmp}/socialflow-k8s-validate). Needs python3 >= 3.11 and PyPI once.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
repo="$(cd "$here/../.." && pwd)"
[ $# -ge 1 ] || { echo "usage: $0 BIN_DIR [CACHE_DIR]" >&2; exit 2; }
bin="$(cd "$1" && pwd)/socialflow"
[ -x "$bin" ] || { echo "no socialflow binary in $1 (cargo build --release -p socialflow-cli)" >&2; exit 2; }
cache="${2:-${TMPDIR:-/tmp}/socialflow-k8s-validate}"
k8s_version=1.30
pins=("kubernetes-validate==1.37.0" "PyYAML==6.0.3")

venv="$cache/venv"
if ! "$venv/bin/python" -c 'import kubernetes_validate, yaml' 2>/dev/null; then
  echo "creating $venv (${pins[*]})"
  mkdir -p "$cache"
  python3 -m venv "$venv"
  "$venv/bin/pip" install -q --disable-pip-version-check "${pins[@]}"
fi
py="$venv/bin/python"

out="$(mktemp -d "${TMPDIR:-/tmp}/socialflow-k8s.XXXXXX")"
trap 'rm -rf "$out"' EXIT
overlays=()
for o in cpu gpu cpu-tls; do
  "$py" "$here/render.py" "$here/overlays/$o" > "$out/$o.yaml"
  echo "rendered overlays/$o: $(grep -c '^kind:' "$out/$o.yaml") objects"
  # examples/submit-job.yaml speaks plaintext gRPC: it belongs with the non-TLS overlays.
  case "$o" in *tls*) overlays+=("$o=$out/$o.yaml") ;; *) overlays+=("$o=$out/$o.yaml:$here/examples/submit-job.yaml") ;; esac
done
"$py" "$here/render.py" "$here/monitoring" > "$out/monitoring.yaml"
echo "rendered monitoring: $(grep -c '^kind:' "$out/monitoring.yaml") objects"

# render.py implements a subset of kustomize: where kubectl is installed, it must agree with it.
if command -v kubectl >/dev/null 2>&1; then
  for d in overlays/cpu overlays/gpu overlays/cpu-tls monitoring; do
    kubectl kustomize "$here/$d" > "$out/kustomize.yaml"
    if "$py" "$here/render.py" --same-as "$out/kustomize.yaml" "$here/$d"; then
      echo "  ok    $d: render.py = kubectl kustomize ($(kubectl version --client 2>/dev/null | sed -n 's/^Kustomize Version: //p'))"
    else
      echo "  FAIL  $d: render.py differs from kubectl kustomize" >&2; exit 1
    fi
  done
else
  echo "  (no kubectl: render.py not compared with kustomize)"
fi

"$py" "$here/check.py" --bin "$bin" --repo "$repo" --k8s-version "$k8s_version" \
  --extra "$out/monitoring.yaml" "${overlays[@]}"
