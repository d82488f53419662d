"""Mistakes on the commands after training (evaluate, record, plot, sweep, record_video) end with one line naming
the fix, before any work is done."""

from __future__ import annotations

import json
import sys
from types import SimpleNamespace

import numpy as np
import pytest
from conftest import ENV

from sb3_mtte.evaluation import MultiTaskEvalCallback
from sb3_mtte.envs import make_mt_env
from sb3_mtte.experiments.cli import main as zoo_main
from sb3_mtte.experiments.playback import evaluate_model as evaluate
from sb3_mtte.experiments.results import plot, records
from sb3_mtte.experiments.zoo import sweep


def one_line_error(capsys, command, argv: list[str]) -> str:
    """The error line a command exits with (status 2, on stderr, no traceback)."""
    with pytest.raises(SystemExit) as exit_info:
        command(argv)
    assert exit_info.value.code == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and "Traceback" not in error, error
    return error.split("error: ", 1)[1].strip()


def a_run_folder(root, **files: bytes):
    """A run folder with a run_info.json and the given files."""
    run = root / "mtsac_mt" / f"{ENV}_1"
    run.mkdir(parents=True)
    info = {"algo": "mtsac_mt", "env_id": ENV, "seed": 0, "task_names": ["a", "b", "c", "d"], "n_tasks": 4}
    (run / "run_info.json").write_text(json.dumps(info))
    for name, content in files.items():
        (run / name.replace("_json", ".json").replace("_npz", ".npz")).write_bytes(content)
    return run


def test_evaluate_refuses_a_folder_as_its_output_file(tmp_path, capsys):
    (tmp_path / "results").mkdir()
    for out in (str(tmp_path / "results"), str(tmp_path / "new") + "/"):
        message = one_line_error(capsys, evaluate.main, ["no_model.zip", "--out", out])
        assert message.startswith(f"--out {out} is a folder: give a file path (e.g. ")


def test_plot_names_a_source_that_is_not_a_folder_and_an_output_that_is_a_file(tmp_path, capsys):
    a_run_folder(tmp_path / "runs")
    message = one_line_error(capsys, plot.main, [str(tmp_path / "runs"), str(tmp_path / "recrods")])
    assert message == f"{tmp_path / 'recrods'}: no such folder; give folders of runs (train's -f) or records"
    (tmp_path / "figures").write_text("")
    message = one_line_error(capsys, plot.main, [str(tmp_path / "runs"), "--out", str(tmp_path / "figures")])
    assert message == f"--out {tmp_path / 'figures'} is a file: give a folder."


def test_record_names_a_missing_runs_folder_and_an_output_that_is_a_file(tmp_path, capsys):
    message = one_line_error(capsys, records.main, [str(tmp_path / "nope"), "--out", str(tmp_path / "records")])
    assert message == f"{tmp_path / 'nope'}: no such folder; give train's -f"
    (tmp_path / "records").write_text("")
    message = one_line_error(capsys, records.main, [str(tmp_path), "--out", str(tmp_path / "records")])
    assert message == f"--out {tmp_path / 'records'} is a file: give a folder."


@pytest.mark.parametrize(
    ("files", "expected"),
    [
        ({"evaluations_npz": b"PK\x03\x04 cut short"}, r"evaluations\.npz is not a valid \.npz file \(.*\): fix or"),
        ({"success_json": b'{"mean": 0.'}, r"success\.json is not valid JSON \(.*\): fix or remove it"),
    ],
)
def test_a_damaged_file_in_a_run_folder_is_named(tmp_path, files, expected):
    a_run_folder(tmp_path, **files)
    with pytest.raises(SystemExit, match=expected):
        plot.main([str(tmp_path), "--out", str(tmp_path / "figures")])


def test_plot_refuses_a_negative_seed_with_one_line(tmp_path, capsys):
    message = one_line_error(capsys, plot.main, [str(tmp_path), "--seed", "-1"])
    assert message == "--seed -1: the bootstrap seed is an int from 0 to 2**32 - 1, e.g. --seed 0"


def test_a_device_torch_does_not_know_ends_with_one_line(tmp_path, capsys):
    expected = "--device gpu: not a torch device; give auto, cpu, cuda or cuda:<index>."
    assert one_line_error(capsys, evaluate.main, [str(tmp_path / "m.zip"), "--device", "gpu"]) == expected
    for command in ("train", "enjoy", "record_video"):
        with pytest.raises(SystemExit) as exit_info:
            zoo_main([command, "--algo", "mtsac_mt", "--env", ENV, "-f", str(tmp_path), "--device", "gpu"])
        assert exit_info.value.code == expected, command
    assert not (tmp_path / "mtsac_mt").exists()


def test_sweep_refuses_a_seed_given_twice(tmp_path, capsys):
    with pytest.raises(SystemExit):
        sweep.main(["--algos", "mtsac_mt", "--envs", ENV, "--seeds", "0", "0", "--out", str(tmp_path)])
    assert (
        capsys.readouterr()
        .err.strip()
        .endswith(
            "error: --seeds 0 0: 0 is given twice: each value once (a repeated one would run the same trials twice)"
        )
    )


def test_sweep_imports_ray_once(tmp_path, monkeypatch):
    calls = []

    class Stop(Exception):
        pass

    def fake_import_ray():
        calls.append(1)
        return SimpleNamespace(tune=None, init=lambda **kwargs: (_ for _ in ()).throw(Stop()))

    monkeypatch.setattr(sweep, "import_ray", fake_import_ray)
    with pytest.raises(Stop):
        sweep.main(["--algos", "mtsac_mt", "--envs", ENV, "--out", str(tmp_path)])
    assert calls == [1]


def test_sweep_without_ray_names_the_extra(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray raises ImportError
    argv = ["--algos", "mtsac_mt", "--envs", "toy-conflict", "--out", str(tmp_path / "sweep")]
    message = one_line_error(capsys, sweep.main, argv)
    assert message == 'sb3-mtte sweep needs Ray Tune: pip install "sb3-mtte[ray]" (or pip install "ray[tune]").'


@pytest.mark.parametrize(
    "flags", [["--episodes", "0"], ["-n", "-1"], ["--width", "0"], ["--fps", "0"], ["--fps", "-5"]]
)
def test_record_video_refuses_no_episode_or_no_step(tmp_path, flags):
    with pytest.raises(SystemExit) as exit_info:
        zoo_main(["record_video", "--algo", "mtsac_mt", "--env", ENV, "-f", str(tmp_path), *flags])
    expected = "give at least 1 (episodes per task, steps per video, pixels, frames per second)."
    assert exit_info.value.code == f"{' '.join(flags)}: {expected}"


@pytest.mark.parametrize("episodes", [0, 2.5])
def test_an_evaluation_callback_of_no_episode_is_refused(episodes):
    expected = r"^episodes_per_task \(the zoo's --eval-episodes\) must be a positive int such as 10, got "
    with pytest.raises(ValueError, match=expected):
        MultiTaskEvalCallback(make_mt_env(ENV), episodes_per_task=episodes)


def test_the_evaluations_file_is_replaced_whole(tmp_path):
    """Written beside and moved over the old file: no partial file, no temporary file left."""
    callback = MultiTaskEvalCallback(make_mt_env(ENV), episodes_per_task=1, log_path=tmp_path)
    callback.evaluations_timesteps, callback.evaluations_success = [100], [np.array([0.0, 1.0, 0.5, 0.0])]
    callback.save_evaluations()
    callback.evaluations_timesteps.append(200)
    callback.evaluations_success.append(np.ones(4))
    callback.save_evaluations()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["evaluations.npz"]
    with np.load(tmp_path / "evaluations.npz") as data:
        assert data["timesteps"].tolist() == [100, 200] and data["success_rate"].shape == (2, 4)


@pytest.mark.parametrize(
    ("flags", "expected"),
    [
        (["--exp-id", "-5"], "argument --exp-id: -5 is negative: give 0 or more"),
        (["--keep-buffers", "-1"], "argument --keep-buffers: -1 is negative: give 0 or more"),
        (["--num-threads", "0"], "argument --num-threads: 0 threads: give 1 or more, or -1 for PyTorch's default"),
        (["-n", "1e5"], "argument -n/--n-timesteps: invalid int value: '1e5'"),
        (["--seed", str(10**20)], f"argument --seed: {10**20} is out of range: give 0 to 2**32 - 1, or -1 for a random"
         " seed"),
    ],
)
def test_train_refuses_a_flag_out_of_range_in_one_line(tmp_path, capsys, flags, expected):
    command = lambda argv: zoo_main(["train", "--algo", "mtsac_mt", "--env", ENV, "-f", str(tmp_path), *argv])  # noqa: E731
    assert one_line_error(capsys, command, flags) == expected
    assert not (tmp_path / "mtsac_mt").exists()


@pytest.mark.parametrize("command", [plot.main, records.main, evaluate.main])
def test_a_parser_error_is_one_line_without_the_usage_block(tmp_path, capsys, command):
    message = one_line_error(capsys, command, [str(tmp_path), "--no-such-flag"])
    assert message == "unrecognized arguments: --no-such-flag"


@pytest.mark.parametrize(
    ("flags", "expected"),
    [
        (["--dpi", "0"], "--dpi 0: give a positive int"),
        (["--dpi", "-5"], "--dpi -5: give a positive int"),
        (["--smooth", "0"], "--smooth 0: give a positive int (1: no smoothing)"),
        (["--smooth", "-3"], "--smooth -3: give a positive int (1: no smoothing)"),
    ],
)
def test_plot_refuses_a_resolution_or_window_below_one_before_any_work(tmp_path, capsys, flags, expected):
    out = tmp_path / "figures"
    assert one_line_error(capsys, plot.main, [str(tmp_path), "--out", str(out), *flags]) == expected
    assert not out.exists()


def test_version(capsys):
    assert zoo_main(["--version"]) == capsys.readouterr().out.split()[-1]


def test_a_name_equal_but_for_case_is_suggested_first():
    from sb3_mtte.common.utils import did_you_mean
    from sb3_mtte.experiments.zoo.configs import missing_entries_message

    assert did_you_mean("mtsacTE", ["mtsac", "mtsacte"]) == "did you mean mtsacte?"
    assert did_you_mean("mt10-smoke", ["MT10", "MT10-smoke", "MT20-smoke"]) == "did you mean MT10-smoke?"
    assert ": did you mean MT10-smoke? (its entries: " in missing_entries_message("mtsacte", ["mt10-smoke"])


@pytest.mark.parametrize("steps", ["0", "-4"])
def test_enjoy_refuses_no_step_before_loading_the_model(tmp_path, steps):
    with pytest.raises(SystemExit) as exit_info:
        zoo_main(["enjoy", "--algo", "mtsac_mt", "--env", ENV, "-f", str(tmp_path), "--no-render", "-n", steps])
    assert exit_info.value.code == f"-n {steps}: give 1 or more vector steps (each steps every task once)."

