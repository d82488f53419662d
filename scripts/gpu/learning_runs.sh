#!/usr/bin/env bash
# Learning runs of the fast path (the CUDA defaults) on one CUDA GPU: MT10-100k runs of mtsac_mt, seeds 0 and 1 side
# by side, each on its own cores, then their final evaluation (50 episodes per task) on the GPU and their records
# (scripts/gpu/learning_runs.py). A call ends within --budget-s (default here 450 s, plus about 20 s of install). A
# run that cannot finish in time stops after its last checkpoint that fits; the same command in a second call, on the
# same warm machine, resumes it from RUNS_DIR (default /tmp/sb3_mtte_learning_runs, outside the checkout) and
# finishes, evaluates and records it. Writes ${OUT:-learning_runs}/: learning_runs.json (each run's state, wall time
# and env steps/s), run_files.tar.gz (each run folder's small files) and records/MT10-100k-gpu/<algo>_seed<k>.json.
# Options after the command go to learning_runs.py: --seeds 0 1 2 3, --algos mtsac_mt mtsacte, --budget-s 300, and
# --commit SHA, the checkout's commit for the records (the runs import the carried wheel, which is no git tree).
#
# The machine has no package registry. Carry .whl/ (ignored by git), made here with one:
#   bash scripts/gpu/gpu_wheels.sh && bash scripts/gpu/learning_runs.sh wheels   # gpu_wheels.txt's, the package's
#                                                                                # and learning_wheels.txt's
#   bash scripts/gpu/learning_runs.sh                  # on the GPU machine, from the repository root; twice
# DRY_RUN=1 runs it twice on the CPU at MT10-smoke (a first call cut short, then its resumption), in a venv holding
# only the GPU machine's packages and the carried wheels (device_venv.py, then learning_venv.py; DRY_RUN_PYTHON and
# DRY_RUN_TORCH stand in for the machine's Python and torch, default python3.11 and torch==2.13.0; DRY_RUN_VENV is
# its folder, rebuilt unless DRY_RUN_KEEP_VENV=1; DRY_RUN_BUDGET_S is the first call's budget, default 150 s).
set -uo pipefail
cd "$(dirname "$0")/../.."
if [ "${1:-}" = wheels ]; then  # wheels [DIR [PYTHON_VERSION]]: learning_wheels.txt's, into DIR (default .whl)
    dir="${2:-.whl}"
    mkdir -p "$dir"
    while read -r wheel; do
        python -m pip download -q --no-deps --only-binary=:all: --python-version "${3:-3.12}" --implementation cp \
            --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
            -d "$dir" "$wheel" 2> /dev/null \
            || python -m pip wheel -q --no-deps --wheel-dir "$dir" "$wheel" || exit 1  # no wheel: built from source
    done < <(grep -v '^#' scripts/gpu/learning_wheels.txt)
    du -sh "$dir"
    exit 0
fi
out="${OUT:-learning_runs}"
runs="${RUNS_DIR:-/tmp/sb3_mtte_learning_runs}"
# The runs import the installed package (the carried wheel, built from this checkout by gpu_wheels.sh), not the
# checkout itself: the hyperparameter files are sb3_mtte.zoo_configs only once installed.
export MUJOCO_GL="${MUJOCO_GL:-disable}" PYTHONUNBUFFERED=1
if [ "${DRY_RUN:-0}" = 1 ]; then
    export PYTHONPATH=""  # the venv alone, nothing of this machine's
    venv="${DRY_RUN_VENV:-/tmp/sb3_mtte_learning_venv}"
    base="${DRY_RUN_PYTHON:-python3.11}"
    python="$venv/bin/python"
    if [ "${DRY_RUN_KEEP_VENV:-0}" != 1 ] || [ ! -x "$python" ]; then
        version="$("$base" -c "import sys; print('%d.%d' % sys.version_info[:2])")" || exit 1
        python3 scripts/gpu/device_venv.py "$venv" --python "$base" --torch "${DRY_RUN_TORCH:-torch==2.13.0}" \
            > /dev/null || exit 1
        bash "$0" wheels "$venv-wheels" "$version" > /dev/null || exit 1
        python3 scripts/gpu/learning_venv.py "$venv" "$venv-wheels" > /dev/null || exit 1
    fi
    rm -rf "$runs"
    dry=(--env MT10-smoke --device cpu --episodes 1)
    "$python" scripts/gpu/learning_runs.py --runs-dir "$runs" --out "$out" --python "$python" "${dry[@]}" \
        --budget-s "${DRY_RUN_BUDGET_S:-150}" "$@" || exit 1
    mv "$out/learning_runs.json" "$out/learning_runs_call1.json"
    exec "$python" scripts/gpu/learning_runs.py --runs-dir "$runs" --out "$out" --python "$python" "${dry[@]}" \
        --budget-s 400 "$@"
fi
if compgen -G ".whl/*.whl" > /dev/null; then
    stamp="$(ls -l .whl | md5sum)"
    if [ "$(cat /tmp/site/.carried 2> /dev/null)" != "$stamp" ]; then  # a second call on the same machine skips it
        python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site \
            .whl/*.whl || exit 1
        echo "$stamp" > /tmp/site/.carried
    fi
    export PYTHONPATH="/tmp/site${PYTHONPATH:+:$PYTHONPATH}"
fi
nvidia-smi -L
python3 -c "import torch as th; assert th.cuda.is_available(), 'no CUDA device'" || exit 1
exec python3 scripts/gpu/learning_runs.py --runs-dir "$runs" --out "$out" --budget-s 450 "$@"
