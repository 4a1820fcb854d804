#!/usr/bin/env bash
# Developer build: compiles the extension (and generated protobuf code) in place, so that
# `PYTHONPATH=python python3 -m pytest tests` runs against this work tree without pip.
set -euo pipefail
cd "$(dirname "$0")/.."
build=build/dev
cmake -S . -B "$build" -G Ninja -DCMAKE_BUILD_TYPE=Release \
  -Dpybind11_DIR="$(python3 -m pybind11 --cmakedir)" -DPython_EXECUTABLE="$(command -v python3)" >/dev/null
cmake --build "$build" -j2
# A new file renamed over the old one: processes that loaded the old library keep its inode
# (copying over it in place kills them with SIGBUS, e.g. a test run in progress).
for so in "$build"/_core*.so; do
  cp "$so" "python/bubble_rt/.$(basename "$so").new"
  mv -f "python/bubble_rt/.$(basename "$so").new" "python/bubble_rt/$(basename "$so")"
done
if [ -d "$build/proto_gen" ]; then
  rm -rf python/bubble_rt/proto_gen && cp -r "$build/proto_gen" python/bubble_rt/proto_gen
fi
