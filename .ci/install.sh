#!/usr/bin/env bash
# Installs what bubble_rt needs on a fresh Debian bookworm machine (root for apt-get), then
# the package itself. Idempotent: re-running skips what is already there.
set -euo pipefail
cd "$(dirname "$0")/.."
extras="${1:-}"
need=()
for p in libeigen3-dev libopencv-dev clang-format; do
  dpkg -s "$p" >/dev/null 2>&1 || need+=("$p")
done
# OpenBLAS: any of Debian's variants builds and runs (the module sets one BLAS thread itself);
# the serial one is installed when none is there.
dpkg -s libopenblas-serial-dev >/dev/null 2>&1 || dpkg -s libopenblas-pthread-dev >/dev/null 2>&1 ||
  dpkg -s libopenblas-openmp-dev >/dev/null 2>&1 || need+=(libopenblas-serial-dev)
if [ ${#need[@]} -gt 0 ]; then
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${need[@]}" >/dev/null
fi
python3 -m pip install -q --upgrade pip >/dev/null 2>&1 || true
python3 -m pip install -q ".${extras:+[$extras]}"
