#!/usr/bin/env bash
# Installs what bubble_rt needs on a fresh Debian bookworm machine (root for apt-get), then
# the package itself. Idempotent: re-running skips what is already there.
set -euo pipefail
cd "$(dirname "$0")/.."
extras="${1:-}"
need=()
for p in libeigen3-dev libopencv-dev libopenblas-serial-dev clang-format; do
  dpkg -s "$p" >/dev/null 2>&1 || need+=("$p")
done
if [ ${#need[@]} -gt 0 ]; then
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${need[@]}" >/dev/null
fi
python3 -m pip install -q --upgrade pip >/dev/null 2>&1 || true
python3 -m pip install -q ".${extras:+[$extras]}"
