#!/usr/bin/env bash
# The wheels benchmarks/gpu_check.sh installs on a GPU machine without a package registry: the package's runtime
# dependencies that a PyTorch image for Python 3.12 lacks (46 MB), into .whl/ (ignored by git).
#   bash benchmarks/gpu_wheels.sh [PYTHON_VERSION]   # default 3.12
set -euo pipefail
cd "$(dirname "$0")/.."
python -m pip download -q --no-deps --only-binary=:all: --python-version "${1:-3.12}" --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 -d .whl \
    stable-baselines3==2.9.2 gymnasium==1.4.0 farama-notifications metaworld==3.1.1 mujoco==3.3.0 glfw==2.11.0 \
    pyopengl==3.1.10
du -sh .whl
