#!/usr/bin/env bash
# The wheels scripts/gpu/gpu_check.sh installs on a GPU machine without a package registry: those of
# scripts/gpu/gpu_wheels.txt (the package's runtime dependencies that the machine's image lacks; 46 MB for Python
# 3.12) and the package's own wheel (built from this checkout, without dependencies), into DIR (default .whl/,
# ignored by git).
#   bash scripts/gpu/gpu_wheels.sh [PYTHON_VERSION [DIR]]   # default 3.12 .whl
set -euo pipefail
cd "$(dirname "$0")/../.."
dir="${2:-.whl}"
mkdir -p "$dir"
rm -f "$dir"/sb3_mtte-*.whl
mapfile -t wheels < <(grep -v '^#' scripts/gpu/gpu_wheels.txt)
python -m pip download -q --no-deps --only-binary=:all: --python-version "${1:-3.12}" --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 -d "$dir" \
    "${wheels[@]}"
python -m pip wheel -q --no-deps --wheel-dir "$dir" .
du -sh "$dir"
