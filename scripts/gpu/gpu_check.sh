#!/usr/bin/env bash
# The device check of the fast path (the update as a CUDA graph, the replay buffer on the GPU: the default on CUDA
# since this passed on an H200) on one CUDA GPU, downloading nothing, in parts that each fit well inside one 9-minute
# call (on one H200: updates 67 s, end_to_end 193 s, profile about 3 min):
#   updates     the CUDA tests (the graph gives the eager path's parameters, entropy coefficients, mu and w for every
#               variant it holds; the device and pinned storages give the host's batches; every algorithm trains,
#               saves and loads on CUDA, on the eager path and on the fast path; their outcome goes into the
#               report), then benchmarks/bench_gpu.py's updates/s of every variant at N = 10, 20, 50, eager against
#               fast;
#   end_to_end  MT10, then MT50, end to end for MTSAC and MTSACTE, eager against fast, and the hours the paper's
#               budget takes;
#   profile     where the fast path's time goes in learn() (benchmarks/profile_gpu.py: each stage of a vector step,
#               the device's busy share, the top ops by device and host time, env stepping alone per VecEnv class),
#               into gpu_profile.json (docs/results/gpu_profile.json).
# With no argument, updates and end_to_end (a user with a GPU). Writes ${OUT:-gpu_check}/: tests.log (updates) and
# gpu_check.json, after every part; a gpu_check.json already there from the same device and torch keeps the other
# part's figures, so copy the first call's file there before the second. It goes to docs/results/gpu_check.json.
# Exits non-zero when a test or a measurement fails.
#
# The machine needs PyTorch with CUDA and the wheels in .whl/ (ignored by git): the package's runtime dependencies
# that its image lacks (scripts/gpu/gpu_wheels.txt; the image's packages are scripts/gpu/device_packages.txt) and the
# package's own wheel, installed into /tmp/site first. Nothing renders: MUJOCO_GL=disable.
#   bash scripts/gpu/gpu_wheels.sh             # with a package registry, into .whl/
#   bash scripts/gpu/gpu_check.sh updates      # on the GPU machine, from the repository root: the first call
#   bash scripts/gpu/gpu_check.sh end_to_end   # the second call
#   bash scripts/gpu/gpu_check.sh profile      # a third, where a target is missed
# DRY_RUN=1 runs every step on the CPU at toy sizes in a venv made from nothing but the GPU machine's packages and
# the carried wheels (scripts/gpu/device_venv.py; DRY_RUN_PYTHON and DRY_RUN_TORCH stand in for the machine's Python
# and torch, default python3.11 and torch==2.13.0; DRY_RUN_VENV is its folder), so that an import the machine
# cannot satisfy fails here too.
set -uo pipefail
cd "$(dirname "$0")/../.."
parts=("$@")
[ ${#parts[@]} -gt 0 ] || parts=(updates end_to_end)
for part in "${parts[@]}"; do
    case "$part" in
        updates | end_to_end | profile) ;;
        *) echo "gpu_check.sh: unknown part '$part': give updates, end_to_end, profile or nothing (the first two)." >&2
           exit 2 ;;
    esac
done
out="${OUT:-gpu_check}"
mkdir -p "$out"
out="$(cd "$out" && pwd)"
export MUJOCO_GL="${MUJOCO_GL:-disable}" PYTHONUNBUFFERED=1 PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
if [ "${DRY_RUN:-0}" = 1 ]; then
    export PYTHONPATH="$PWD"  # the checkout and the venv, nothing of this machine's
    python="$(python3 scripts/gpu/device_venv.py "${DRY_RUN_VENV:-/tmp/sb3_mtte_device_venv}" \
        --python "${DRY_RUN_PYTHON:-python3.11}" --torch "${DRY_RUN_TORCH:-torch==2.13.0}" | tail -1)" || exit 1
    tests=(-k "not cuda")
    updates=(--n-tasks 10 --repeats 3 --device cpu)
    end_to_end=(--benchmarks MT10 --vector-steps 20 --device cpu)
    profile=(--benchmarks MT10 --vector-steps 5 --device cpu)
else
    python=python3
    if compgen -G ".whl/*.whl" > /dev/null; then
        python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site \
            .whl/*.whl || exit 1
        export PYTHONPATH="$PYTHONPATH:/tmp/site"
    fi
    nvidia-smi -L
    python3 -c "import torch as th; assert th.cuda.is_available(), 'no CUDA device'" || exit 1
    tests=(-k cuda)
    updates=(--n-tasks 10 20 50 --repeats 11 --device cuda)
    end_to_end=(--benchmarks MT10 MT50 --vector-steps 300 --device cuda)
    profile=(--benchmarks MT10 MT50 --vector-steps 100 --device cuda)
fi
bench() {
    (cd benchmarks && "$python" bench_gpu.py --out "$out/gpu_check.json" "$@") > /dev/null
}
status=0
for part in "${parts[@]}"; do
    if [ "$part" = updates ]; then
        "$python" -m pytest -q -rs -p no:cacheprovider "${tests[@]}" tests/test_update_path.py tests/test_buffers.py \
            tests/test_device.py 2>&1 | tee "$out/tests.log" | tail -6
        tests_rc="${PIPESTATUS[0]}"
        [ "$tests_rc" = 0 ] || status=1
        bench --parts updates "${updates[@]}" --tests-log "$out/tests.log" --tests-rc "$tests_rc" || exit 1
    elif [ "$part" = end_to_end ]; then
        bench --parts end_to_end "${end_to_end[@]}" || exit 1
    else
        (cd benchmarks && "$python" profile_gpu.py --out "$out/gpu_profile.json" "${profile[@]}") > /dev/null || exit 1
        echo "wrote $out/gpu_profile.json"
    fi
done
[ -f "$out/gpu_check.json" ] && "$python" - "$out/gpu_check.json" <<'PY'
import json, sys
report = json.load(open(sys.argv[1]))
print(report["device_name"], report["torch"], "update speedup at N = 10:", report.get("update_speedup_n10"))
for entry in report.get("updates", []):
    print(entry["n_tasks"], entry["speedup"])
for label in ("MTSAC", "MTSACTE"):
    print(label, report.get(label))
PY
exit "$status"
