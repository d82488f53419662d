#!/usr/bin/env bash
# On a machine with a CUDA GPU and the package installed: the CUDA tests, the default suite with CUDA present, and
# bench_updates.py on the GPU (updates/s of every variant as ratios to SB3's SAC in the same run, and real MT10
# learn()). Writes under ${OUT:-cuda_check}/: tests.log, suite.log, bench_cuda.json. Exits non-zero when a test
# fails (pipefail: the status of pytest, not of the tail that shows its end) or the benchmark does.
#   bash scripts/gpu/cuda_check.sh
set -uo pipefail
status=0
cd "$(dirname "$0")/../.."
out="${OUT:-cuda_check}"
mkdir -p "$out"
export MUJOCO_GL="${MUJOCO_GL:-egl}"
nvidia-smi -L
python -c "import torch as th; assert th.cuda.is_available(), 'no CUDA device'; print(th.__version__, th.cuda.get_device_name(0))" || exit 1
python -m pytest -q -rs -p no:cacheprovider tests/test_device.py 2>&1 | tee "$out/tests.log" | tail -8 || status=1
python -m pytest -q -rf -p no:cacheprovider -n "${WORKERS:-8}" 2>&1 | tee "$out/suite.log" | tail -15 || status=1
python benchmarks/bench_updates.py --device cuda --n-tasks 10 20 50 --repeats 11 --env-steps 200 --end-to-end 500 \
    > "$out/bench_cuda.json" || exit 1
python - "$out/bench_cuda.json" <<'EOF'
import json, sys
report = json.load(open(sys.argv[1]))
for entry in report["results"]:
    print(entry["n_tasks"], {k: round(v * 1e3, 2) for k, v in entry["seconds"].items()})
print(report.get("end_to_end_mt10"))
EOF
exit "$status"
