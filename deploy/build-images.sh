#!/usr/bin/env bash
# Builds socialflow:local (and socialflow-prometheus:local) from scratch: binaries + the shared
# libraries ldd lists + configs. Usage: deploy/build-images.sh [BIN_DIR] (default target/release).
set -euo pipefail
cd "$(dirname "$0")"
bin_dir="${1:-../target/release}"
[ -x "$bin_dir/socialflow" ] || { echo "no socialflow binary in $bin_dir: build it first (cargo build --release -p socialflow-cli)" >&2; exit 1; }

# Copies a binary and every library it links (with the loader) into a root directory.
add_with_libs() {
  local root="$1" bin="$2" dest="$3"
  mkdir -p "$root$(dirname "$dest")"
  cp -L "$bin" "$root$dest"
  ldd "$bin" | grep -oE '/[^ ]+' | while read -r lib; do
    mkdir -p "$root$(dirname "$lib")"
    cp -L "$lib" "$root$lib"
  done
}

rm -rf rootfs && mkdir -p rootfs/app/configs rootfs/tmp rootfs/data
add_with_libs rootfs "$bin_dir/socialflow" /app/socialflow
# Debug info is most of a dev build's size; the image does not need it.
if command -v strip >/dev/null; then strip --strip-debug rootfs/app/socialflow; fi
cp -r ../configs/scenarios ../configs/cases ../configs/learner.toml ../configs/quickstart.toml rootfs/app/configs/
chmod 1777 rootfs/tmp
docker build -q -t socialflow:local -f Dockerfile . >/dev/null
echo "built socialflow:local"

if ! docker image inspect socialflow-prometheus:local >/dev/null 2>&1; then
  tmp=$(mktemp -d)
  fetch() { (cd "$tmp" && apt-get download prometheus >/dev/null 2>&1 && dpkg -x prometheus_*.deb x); }
  if ! fetch && ! { apt-get update >/dev/null 2>&1 && fetch; }; then
    echo "WARNING: could not fetch Debian's prometheus package; socialflow-prometheus:local not built" >&2
    rm -rf "$tmp"
    exit 0
  fi
  rm -rf rootfs-prometheus && mkdir -p rootfs-prometheus/prometheus rootfs-prometheus/etc/prometheus rootfs-prometheus/tmp
  add_with_libs rootfs-prometheus "$tmp/x/usr/bin/prometheus" /usr/bin/prometheus
  cp prometheus.yml rootfs-prometheus/etc/prometheus/prometheus.yml
  chmod 1777 rootfs-prometheus/tmp rootfs-prometheus/prometheus
  docker build -q -t socialflow-prometheus:local -f Dockerfile.prometheus . >/dev/null
  rm -rf "$tmp"
  echo "built socialflow-prometheus:local"
fi
