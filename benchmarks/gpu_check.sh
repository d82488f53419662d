#!/usr/bin/env bash
# The GPU check of the fast path, in one run of under 8 minutes on one H100 that downloads nothing: the CUDA tests
# (the CUDA graph gives the eager parameters for every variant it holds, the device and pinned replay storages give
# the host's batches), then benchmarks/bench_gpu.py (eager against fast: updates/s of every variant at N = 10, 20, 50;
# MT10 and MT50 end to end for MTSAC and MTSACTE; the hours of the paper's budget). Writes ${OUT:-gpu_check}/:
# tests.log and gpu_check.json (to be copied to docs/results/gpu_check.json).
#
# The machine needs PyTorch with CUDA and the package's other runtime dependencies. Wheels found in .whl/ (ignored by
# git; 46 MB for Python 3.12) are installed into /tmp/site first, for a machine without a package registry.
# Nothing renders: MUJOCO_GL=disable, so no EGL library is needed.
#   bash benchmarks/gpu_wheels.sh          # with a package registry, into .whl/
#   bash benchmarks/gpu_check.sh           # on the GPU machine, from the repository root
# DRY_RUN=1 runs every step on the CPU at toy sizes (a machine without a GPU can check the script).
set -uo pipefail
cd "$(dirname "$0")/.."
out="${OUT:-gpu_check}"
mkdir -p "$out"
out="$(cd "$out" && pwd)"
export MUJOCO_GL="${MUJOCO_GL:-disable}" PYTHONUNBUFFERED=1 PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
if compgen -G ".whl/*.whl" > /dev/null; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
        || exit 1
    export PYTHONPATH="$PYTHONPATH:/tmp/site"
fi
if [ "${DRY_RUN:-0}" = 1 ]; then
    sizes=(--n-tasks 10 --benchmarks MT10 --vector-steps 20 --repeats 3 --device cpu)
    tests=(-k "not cuda")
else
    tests=(-k cuda)
    nvidia-smi -L
    python3 -c "import torch as th; assert th.cuda.is_available(), 'no CUDA device'" || exit 1
    sizes=(--n-tasks 10 20 50 --benchmarks MT10 MT50 --vector-steps 300 --repeats 11 --device cuda)
fi
python3 -m pytest -q -rs -p no:cacheprovider "${tests[@]}" tests/test_update_path.py tests/test_buffers.py \
    tests/test_device.py 2>&1 | tee "$out/tests.log" | tail -6
tests_status=${PIPESTATUS[0]}
(cd benchmarks && python3 bench_gpu.py "${sizes[@]}" --out "$out/gpu_check.json") > /dev/null || exit 1
python3 - "$out/gpu_check.json" <<'EOF'
import json, sys
report = json.load(open(sys.argv[1]))
print(report["device_name"], report["torch"], "update speedup at N = 10:", report.get("update_speedup_n10"))
for entry in report["updates"]:
    print(entry["n_tasks"], entry["speedup"])
for label in ("MTSAC", "MTSACTE"):
    print(label, report[label])
EOF
exit "$tests_status"
