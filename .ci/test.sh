#!/usr/bin/env bash
# The README's test command: install everything (Debian packages, the package with its test and
# docs extras), check formatting, lint and types, build the docs site with warnings as errors,
# then run the whole test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
export OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1
bash .ci/install.sh test,docs
echo "== ruff";          python3 -m ruff check python tests bench
echo "== ruff format";   python3 -m ruff format --check python tests bench
echo "== clang-format";  find cpp \( -name '*.cpp' -o -name '*.h' \) -print0 | xargs -0 clang-format --dry-run --Werror
echo "== mypy";          python3 -m mypy
echo "== import-linter"; (cd python && lint-imports --config ../pyproject.toml)
echo "== mkdocs";        NO_MKDOCS_2_WARNING=1 python3 -m mkdocs build --strict --site-dir "$(mktemp -d)"
echo "== pytest"
# Run from tests/ so the installed package (not the source tree) is what gets imported. Two
# workers: the suite is CPU-bound and single-threaded for most of its length (11 -> 7.5 min
# on a 2-core machine); tests bind any free port and use their own temporary folders.
cd tests && python3 -m pytest -q -p no:cacheprovider -n 2 .
