"""The learning runs on a GPU (scripts/gpu/learning_runs.py and the scripts beside it): the plan of cores
and folders, the commands, the states that decide what is resumed, evaluated and recorded, when a run is stopped
after a checkpoint, what comes back, and the comparison with the CPU runs."""

from __future__ import annotations

import json
import shutil
import tarfile
import zipfile
from pathlib import Path

import numpy as np
import pytest
from script_loader import ROOT, load_script

learning_runs = load_script("scripts/gpu/learning_runs.py")
learning_folders = load_script("scripts/gpu/learning_folders.py")
learning_venv = load_script("scripts/gpu/learning_venv.py")
learning_compare = load_script("scripts/gpu/learning_compare.py")

CPU_RECORDS = ROOT / "docs" / "records" / "MT10-100k"


# ---------------------------------------------------------------------------------------------------- the plan
def test_cores_are_cut_into_contiguous_blocks_one_per_run():
    assert learning_runs.plan_cores(range(16), 2) == [list(range(8)), list(range(8, 16))]
    assert learning_runs.plan_cores(range(16), 4)[3] == [12, 13, 14, 15]
    assert learning_runs.plan_cores([0, 1, 2, 3, 4], 2) == [[0, 1, 2], [3, 4]]
    with pytest.raises(ValueError, match="at most one run per core"):
        learning_runs.plan_cores(range(2), 3)


def test_core_lists_take_tasksets_form():
    assert learning_folders.core_list([3, 0, 1, 2, 8]) == "0-3,8"
    assert learning_folders.core_list([5]) == "5"
    assert learning_folders.core_list([0, 2, 4]) == "0,2,4"


def test_run_folders_and_records_are_named_by_algorithm_and_seed():
    assert learning_folders.run_dir_of(Path("/r"), "mtsac_mt", "MT10-100k", 0) == Path("/r/mtsac_mt/MT10-100k_1")
    assert learning_folders.record_name("MT10-100k", "mtsacte", 3) == "MT10-100k-gpu/mtsacte_seed3.json"


def test_the_arguments_plan_one_group_per_algorithm(tmp_path):
    args = learning_runs.parse_args(["--runs-dir", str(tmp_path), "--out", str(tmp_path / "o"), "--seeds", "0", "1",
                                     "--algos", "mtsac_mt", "mtsacte", "--cores", "2"])  # fmt: skip
    groups = learning_runs.plan_runs(args, args.core_ids)
    assert [[(run.algo, run.seed, run.cores) for run in group] for group in groups] == [
        [("mtsac_mt", 0, [args.core_ids[0]]), ("mtsac_mt", 1, [args.core_ids[1]])],
        [("mtsacte", 0, [args.core_ids[0]]), ("mtsacte", 1, [args.core_ids[1]])],
    ]


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--seeds", "0", "0"], "distinct seeds"),
        (["--seeds", "-1"], "distinct seeds"),
        (["--algos", "mtsac_mt", "mtsac_mt"], "given twice"),
        (["--budget-s", "20"], "more than 30"),
        (["--episodes", "0"], "1 or more"),
        (["--seeds", "0", "1", "--cores", "1"], "--cores 1"),
    ],
)
def test_bad_arguments_end_with_one_line(tmp_path, capsys, extra, message):
    with pytest.raises(SystemExit):
        learning_runs.parse_args(["--runs-dir", str(tmp_path), "--out", str(tmp_path), *extra])
    assert message in capsys.readouterr().err


def test_a_new_run_gets_its_seed_and_a_started_one_is_resumed(tmp_path):
    run = learning_folders.Run("mtsac_mt", 1, "MT10-100k", tmp_path / "mtsac_mt" / "MT10-100k_2", [4, 5, 6, 7])
    new = learning_runs.train_command(run, "new", "python3", "cuda", 1, tmp_path)
    assert new[:3] == ["taskset", "-c", "4-7"]
    assert new[3:6] == ["python3", "-m", "sb3_mtte"]
    assert new[new.index("--seed") + 1] == "1" and new[new.index("--exp-id") + 1] == "2"
    assert new[new.index("--device") + 1] == "cuda" and "--resume" not in new
    resumed = learning_runs.train_command(run, "unfinished", "python3", "cuda", 1, tmp_path)
    assert resumed[resumed.index("--resume") + 1] == str(run.run_dir) and "--seed" not in resumed


# ------------------------------------------------------------------------------------------------ a run's state
def write_run(run_dir: Path, finished: bool, model: bool = True, evaluated: bool = False) -> None:
    run_dir.mkdir(parents=True, exist_ok=True)
    info = {"finished": finished, "final_model": "MT10-100k.zip", "timesteps": 1000 if finished else 400}
    (run_dir / "run_info.json").write_text(json.dumps(info))
    if model:
        (run_dir / "MT10-100k.zip").write_bytes(b"")
    if evaluated:
        (run_dir / "success.json").write_text(json.dumps({"mean": 0.3}))


def test_the_state_decides_what_is_resumed_evaluated_and_recorded(tmp_path):
    assert learning_folders.run_state(tmp_path / "none") == "new"
    write_run(tmp_path / "a", finished=False)
    assert learning_folders.run_state(tmp_path / "a") == "unfinished"
    write_run(tmp_path / "b", finished=True)
    assert learning_folders.run_state(tmp_path / "b") == "trained"
    write_run(tmp_path / "c", finished=True, evaluated=True)
    assert learning_folders.run_state(tmp_path / "c") == "evaluated"
    write_run(tmp_path / "d", finished=True, model=False)
    assert learning_folders.run_state(tmp_path / "d") == "unfinished"


def test_an_unfinished_run_is_never_evaluated_or_recorded_even_with_a_final_evaluation(tmp_path):
    write_run(tmp_path / "r", finished=False, evaluated=True)
    assert learning_folders.run_state(tmp_path / "r") == "unfinished"


def test_a_run_resumes_from_its_last_checkpoint(tmp_path):
    write_run(tmp_path, finished=False)
    assert learning_folders.steps_reached(tmp_path) == 0
    for steps in (50000, 100000):
        (tmp_path / f"rl_model_{steps}_steps.json").write_text("{}")
    (tmp_path / "rl_model_replay_buffer_100000_steps.pkl").write_bytes(b"")
    assert [steps for steps, _ in learning_folders.checkpoint_markers(tmp_path)] == [50000, 100000]
    assert learning_folders.steps_reached(tmp_path) == 100000


# ------------------------------------------------------------------------------------------- stopping in time
def test_a_run_is_stopped_after_a_checkpoint_only_when_neither_its_end_nor_its_next_checkpoint_fits():
    markers = [(50000, 100.0), (100000, 120.0)]  # 2,500 env steps/s
    stop = learning_runs.should_stop
    assert not stop(120.0, 400.0, markers, 0.0, 50000, 1_000_000)  # the next checkpoint fits
    assert stop(120.0, 140.0, markers, 0.0, 50000, 1_000_000)  # 20 s left: neither fits
    near_the_end = [(900000, 100.0), (950000, 120.0)]
    assert not stop(120.0, 180.0, near_the_end, 0.0, 50000, 1_000_000)  # its end fits (50 s forecast)
    assert stop(120.0, 160.0, near_the_end, 0.0, 50000, 1_000_000)
    assert not stop(120.0, 121.0, [(950000, 100.0), (1000000, 120.0)], 0.0, 50000, 1_000_000)  # it is ending
    assert not stop(120.0, 140.0, markers[1:], 0.0, 50000, 1_000_000)  # one checkpoint: no pace to go by
    assert not stop(120.0, 140.0, [], 0.0, 50000, 1_000_000)


# ------------------------------------------------------------------------------------------- what comes back
def test_more_records_than_can_come_back_stay_in_the_archive_alone(tmp_path):
    runs_dir, out = tmp_path / "runs", tmp_path / "out"
    run = learning_folders.Run("mtsac_mt", 0, "MT10-100k", runs_dir / "mtsac_mt" / "MT10-100k_1", [0])
    write_run(run.run_dir, finished=True, evaluated=True)
    (runs_dir / "logs").mkdir(parents=True)
    (runs_dir / "logs" / "mtsac_mt_seed0.log").write_text("log")
    records = out / "records" / "MT10-100k-gpu"
    records.mkdir(parents=True)
    ctx = learning_runs.argparse.Namespace(out=out, runs_dir=runs_dir, budget_s=60.0, device="cuda", software={})
    for seed in range(6):
        (records / f"mtsac_mt_seed{seed}.json").write_text("{}")
    learning_folders.write_output([[run]], ctx, 0.0, final=True)
    assert len(list(records.glob("*.json"))) == 6  # 6 + 2 files can come back
    (out / "call.log").write_text("the call's output")
    learning_folders.write_output([[run]], ctx, 0.0, final=True)  # 6 + 3 would not
    assert not list(records.glob("*.json"))
    with tarfile.open(out / learning_folders.RUN_FILES) as archive:
        names = archive.getnames()
    assert "records/MT10-100k-gpu/mtsac_mt_seed5.json" in names
    assert "mtsac_mt/MT10-100k_1/run_info.json" in names and "logs/mtsac_mt_seed0.log" in names
    assert not any(name.endswith(".zip") for name in names)
    summary = json.loads((out / learning_folders.SUMMARY_FILE).read_text())
    assert summary["runs"][0]["state_after"] == "evaluated" and summary["runs"][0]["finished"]


# ---------------------------------------------------------------------------------------------- the venv
def fake_wheel(folder: Path, name: str, requires: list[str]) -> Path:
    path = folder / f"{name.replace('-', '_')}-1.0-py3-none-any.whl"
    lines = ["Metadata-Version: 2.1", f"Name: {name}", "Version: 1.0", *(f"Requires-Dist: {r}" for r in requires)]
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr(f"{name.replace('-', '_')}-1.0.dist-info/METADATA", "\n".join(lines) + "\n")
    return path


def test_the_venv_takes_the_extras_requirements_from_the_image_and_names_what_is_left_out(tmp_path):
    package = fake_wheel(tmp_path, "sb3-mtte", ["numpy", 'rl-zoo3; extra == "zoo"', 'scipy; extra == "plots"',
                                                'moviepy; extra == "video"'])  # fmt: skip
    zoo = fake_wheel(tmp_path, "rl-zoo3", ["optuna", "shimmy~=2.0", "pyyaml"])
    assert learning_venv.extra_requirements(package) == {"rl-zoo3", "scipy"}
    install, left_out = learning_venv.needed(
        [package, zoo], on_device={"numpy", "scipy", "pyyaml"}, carried={"rl-zoo3", "optuna", "sb3-mtte"}
    )
    assert install == ["numpy", "pyyaml", "scipy"]
    assert left_out == ["shimmy"]


# -------------------------------------------------------------------------------------------- the comparison
def test_chances_under_one_distribution():
    assert learning_compare.chance_all_inside(8, 2) == pytest.approx(56 / 90)
    assert learning_compare.chance_all_inside(8, 4) == pytest.approx(56 / 132)
    assert learning_compare.chance_all_beyond_one_side(8, 2) == pytest.approx(2 / 45)
    assert learning_compare.chance_all_beyond_one_side(8, 4) == pytest.approx(2 / 495)


def gpu_folder(tmp_path: Path, names: list[str], final_scale: float = 1.0) -> Path:
    folder = tmp_path / "gpu"
    folder.mkdir()
    for name in names:
        record = json.loads((CPU_RECORDS / name).read_text())
        record["final"]["per_task"] = {task: final_scale * v for task, v in record["final"]["per_task"].items()}
        record["started"] = "gpu-" + str(record["started"])
        (folder / name).write_text(json.dumps(record))
    return folder


def test_cpu_runs_compared_with_themselves_show_no_drift(tmp_path):
    folder = gpu_folder(tmp_path, ["mtsac_mt_seed0.json", "mtsac_mt_seed3.json"])
    report = learning_compare.comparison_report(CPU_RECORDS, folder, "MT10-100k")
    assert "| seed 0 | 29.6 | 22.0-50.8 (8 runs) | inside |" in report
    cpu = learning_compare.final_means(learning_compare.finished_runs(CPU_RECORDS, "MT10-100k")["SAC-MT"])
    gpu = learning_compare.final_means(learning_compare.finished_runs(folder, "MT10-100k")["SAC-MT"])
    diff = learning_compare.mean_difference(gpu, cpu)
    assert f"{100 * diff.value:+.1f} points [{100 * diff.low:.1f}, {100 * diff.high:.1f}]" in report
    assert "| seed 0 | 235.8 | reach-v3 | yes, from window 5 |" in report  # SAC-MT seed 0's reach ran away
    assert "Ran away: GPU 2 of 2, CPU 3 of 8" in report
    assert report.rstrip().endswith("Reading fixed before the runs: no sign of drift.")


def test_gpu_runs_that_learned_nothing_are_flagged(tmp_path):
    folder = gpu_folder(tmp_path, ["mtsac_mt_seed1.json", "mtsac_mt_seed5.json"], final_scale=0.1)
    report = learning_compare.comparison_report(CPU_RECORDS, folder, "MT10-100k")
    assert "every GPU run's final success is below the CPU range" in report
    assert "drift suspected" in report


def test_the_difference_is_read_as_fixed():
    shown = learning_compare.MeanDifference(0.2, 0.1, 0.3, 5.0, 6.0, 0.01)
    assert learning_compare.difference_reading(shown) == "the GPU mean is above the CPU mean"
    wide = learning_compare.MeanDifference(0.2, 0.1, 0.3, 1.5, 1.2, 0.3)  # n = 2: the bootstrap alone is too narrow
    assert learning_compare.difference_reading(wide) == "no difference shown"
    assert learning_compare.difference_reading(None) == "too few runs for the difference"
    assert np.isclose(learning_compare.RUNAWAY_LOSS, 100.0)


def test_a_folder_without_shared_algorithms_ends_with_one_line(tmp_path):
    (tmp_path / "gpu").mkdir()
    with pytest.raises(SystemExit, match="no algorithm with finished runs"):
        learning_compare.comparison_report(CPU_RECORDS, tmp_path / "gpu", "MT10-100k")
    shutil.rmtree(tmp_path / "gpu")


# ------------------------------------------------------------------------------------------------- the imports
def test_the_learning_runs_import_only_what_the_gpu_machine_has_and_carries():
    """``train``, ``evaluate`` and ``record`` import nothing beyond the GPU machine's packages, the device check's
    wheels and the learning runs' own (``learning_wheels.txt``): optuna's sqlalchemy, rl-zoo3's shimmy and
    pytablewriter, and huggingface_sb3's moviepy stay behind."""
    from test_dependencies import (
        GPU_SCRIPTS,
        command_module,
        import_as_on_a_plain_install,
        modules_outside,
        requirement_closure,
    )

    on_device = learning_venv.package_names(GPU_SCRIPTS / "device_packages.txt")
    carried = set().union(
        *(learning_venv.package_names(GPU_SCRIPTS / n) for n in ("gpu_wheels.txt", "learning_wheels.txt"))
    )
    # a package of the machine brings what its release here requires: releases differ (huggingface_hub 2 here needs
    # httpcore2, pandas 2 needs pytz), and the dry run's venv checks the machine's own
    allowed = set().union(*(requirement_closure(name) for name in on_device)) | carried | {"sb3-mtte"}
    blocked = modules_outside(allowed)
    assert {"sqlalchemy", "shimmy", "pytablewriter"} <= set(blocked)
    modules = [command_module(command) for command in ("train", "evaluate", "record")]
    result = import_as_on_a_plain_install(modules, blocked)
    assert result.returncode == 0, f"the learning runs need a package the GPU machine lacks:\n{result.stderr[-2000:]}"
