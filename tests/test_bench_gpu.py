"""The device check's benchmark (``benchmarks/bench_gpu.py``) run one part a call: two runs make one report, and a
report of another machine is not mixed in. The measurements are stubbed: their code runs in the check's dry run."""

from __future__ import annotations

import json
from pathlib import Path

from script_loader import load_script

from sb3_mtte.common import gpu_defaults

bench_gpu = load_script("benchmarks/bench_gpu.py")


def stub_measurements(monkeypatch) -> list[bool]:
    """Cheap stand-ins for the two parts; returns what ``FAST_PATH_BY_DEFAULT`` was when each ran."""
    fast_by_default = []

    def updates(n_tasks, device, repeats):
        fast_by_default.append(gpu_defaults.FAST_PATH_BY_DEFAULT)
        return {"n_tasks": n_tasks, "speedup": {"MTSAC-MT": 2.0}}

    def end_to_end(benchmark, device, vector_steps):
        fast_by_default.append(gpu_defaults.FAST_PATH_BY_DEFAULT)
        return {"env_steps_per_s": {"MTSAC": {"eager": 1.0, "fast": 2.0}, "MTSACTE": {"eager": 1.0, "fast": 3.0}}}

    monkeypatch.setattr(bench_gpu, "bench_updates", updates)
    monkeypatch.setattr(bench_gpu, "bench_end_to_end", end_to_end)
    monkeypatch.setattr(gpu_defaults, "FAST_PATH_BY_DEFAULT", False)  # main() sets it; restored after the test
    return fast_by_default


def test_one_part_a_run_makes_one_report(tmp_path, monkeypatch):
    fast_by_default = stub_measurements(monkeypatch)
    out = str(tmp_path / "gpu_check.json")
    common = ["--device", "cpu", "--out", out, "--benchmarks", "MT10", "MT50", "--n-tasks", "10", "20"]
    bench_gpu.main([*common, "--parts", "updates"])
    first = json.loads(Path(out).read_text())
    assert "updates" in first and "end_to_end_MT10" not in first
    bench_gpu.main([*common, "--parts", "end_to_end"])
    report = json.loads(Path(out).read_text())
    assert [entry["n_tasks"] for entry in report["updates"]] == [10, 20] and report["update_speedup_n10"] == 2.0
    rates = {"eager": 1.0, "fast": 2.0}
    assert report["MTSAC"] == {"mt10_env_steps_per_s": rates, "mt50_env_steps_per_s": rates}
    assert {"end_to_end_MT10", "end_to_end_MT50"} <= report.keys()
    assert fast_by_default == [True] * 4  # "fast" is what "auto" picks with the fast path as the default


def test_a_report_of_another_machine_is_replaced(tmp_path, monkeypatch):
    stub_measurements(monkeypatch)
    out = tmp_path / "gpu_check.json"
    out.write_text(json.dumps({"device": "cuda", "device_name": "another GPU", "torch": "2.11", "updates": ["old"]}))
    report = bench_gpu.main(["--device", "cpu", "--out", str(out), "--parts", "end_to_end", "--benchmarks", "MT10"])
    assert "updates" not in report and report["device"] == "cpu"
    assert json.loads(out.read_text()) == report


def test_the_cuda_tests_outcome_goes_into_the_report_and_stays_for_the_second_part(tmp_path, monkeypatch):
    stub_measurements(monkeypatch)
    out, log = str(tmp_path / "gpu_check.json"), tmp_path / "tests.log"
    log.write_text("......\n\n1 failed, 21 passed, 36 deselected in 22.40s\n")
    bench_gpu.main(["--device", "cpu", "--out", out, "--parts", "updates", "--n-tasks", "10",
                    "--tests-log", str(log), "--tests-rc", "1"])  # fmt: skip
    report = bench_gpu.main(["--device", "cpu", "--out", out, "--parts", "end_to_end", "--benchmarks", "MT10"])
    assert report["cuda_tests"] == {"summary": "1 failed, 21 passed, 36 deselected in 22.40s", "rc": 1}
