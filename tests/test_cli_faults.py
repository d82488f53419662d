"""What a user hits on the command line, each ending in one line before any work: Ctrl-C, a CUDA device the machine
lacks, an output path that cannot be written, a misspelled benchmark, a model outside its run folder, evaluate's
counts and header, enjoy's -n, and the tests run from a checkout that is not installed editable."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch as th
from conftest import ENV, tiny_train
from test_cli_input import one_line_error

from sb3_mtte.experiments.cli import main as cli_main
from sb3_mtte.experiments.env_ids import benchmark_help
from sb3_mtte.experiments.playback import evaluate_model as evaluate
from sb3_mtte.experiments.results import plot

ROOT = Path(__file__).resolve().parent.parent
NO_PROC = pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs Linux's /proc")


@pytest.fixture(scope="module")
def model(tmp_path_factory) -> Path:
    """The final model of a tiny toy-conflict run of SAC-MT."""
    run = tiny_train(tmp_path_factory.mktemp("zoo"), "mtsac_mt", steps=200)
    return run / f"{ENV}.zip"


@pytest.fixture
def no_evaluation(monkeypatch):
    """evaluate's episodes: any call fails the test (a refusal must come before them)."""

    def refuse(*args, **kwargs):
        raise AssertionError("the evaluation started")

    monkeypatch.setattr(evaluate, "evaluate_success", refuse)


# ========================================================================================================= Ctrl-C
INTERRUPTED_EVALUATE = """
import sys
from sb3_mtte import evaluation
real = evaluation.evaluate_success

def announced(*args, **kwargs):
    print("evaluating", flush=True)
    return real(*args, **kwargs)

evaluation.evaluate_success = announced  # before the command imports it
from sb3_mtte.experiments import cli
sys.argv = ["sb3-mtte", "evaluate", sys.argv[1], "--episodes", "1000000", "--no-progress"]
cli.console_main()
"""

INTERRUPTED_SUB_ENVS = """
import functools, sys
import numpy as np
from stable_baselines3.common.vec_env import SubprocVecEnv
from sb3_mtte.experiments import cli
from sb3_mtte.experiments.env_ids import MultiTaskVecEnvFactory, make_task_env

def step_forever(argv):
    make = functools.partial(make_task_env, "toy-conflict")
    env = MultiTaskVecEnvFactory(4, vec_env_cls=SubprocVecEnv)([make] * 4)
    env.reset()
    print("stepping", flush=True)
    while True:
        env.step(np.zeros((4, 2), dtype=np.float32))

cli.COMMANDS["evaluate"] = step_forever
sys.argv = ["sb3-mtte", "evaluate"]
cli.console_main()
"""


def interrupt(script: str, *args: str, whole_group: bool = False) -> tuple[subprocess.Popen, float, str]:
    """Run ``script``, send Ctrl-C once it prints its first line (to its whole process group, as a terminal does,
    with ``whole_group``); return the process, the seconds it took to exit after Ctrl-C, and its stderr."""
    process = subprocess.Popen(
        [sys.executable, "-c", script, *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    try:
        assert process.stdout is not None and process.stdout.readline(), process.communicate()[1]
        sent = time.monotonic()
        (os.killpg if whole_group else os.kill)(process.pid, signal.SIGINT)
        _, err = process.communicate(timeout=60)
        return process, time.monotonic() - sent, err
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)


def test_ctrl_c_ends_evaluate_at_once_with_one_line(model):
    process, seconds, err = interrupt(INTERRUPTED_EVALUATE, str(model))
    assert err == "sb3-mtte evaluate: interrupted (Ctrl-C)\n"
    assert process.returncode == 130
    assert seconds < 2.0, seconds


def test_ctrl_c_of_a_command_stepping_sub_env_processes_ends_them_all(tmp_path):
    """Ctrl-C from a terminal reaches every process of the command: the sub-env processes leave it to the command,
    which exits at once with one line (no traceback of theirs), and they end with it."""
    process, seconds, err = interrupt(INTERRUPTED_SUB_ENVS, whole_group=True)
    assert err == "sb3-mtte evaluate: interrupted (Ctrl-C)\n"
    assert process.returncode == 130 and seconds < 2.0, seconds
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:
        try:
            os.killpg(process.pid, 0)
        except ProcessLookupError:
            return
        time.sleep(0.1)
    os.killpg(process.pid, signal.SIGKILL)
    pytest.fail("a sub-env process outlived its command")


# ===================================================================================================== --device
def test_cuda_on_a_machine_without_it_is_refused_in_one_line(tmp_path, capsys, monkeypatch):
    """SB3 would run on the CPU without a word: train, enjoy, record_video and evaluate refuse, as torch would,
    before any folder exists."""
    monkeypatch.setattr(th.cuda, "is_available", lambda: False)
    expected = "--device cuda: CUDA is not available on this machine; give --device cpu or --device auto."
    assert one_line_error(capsys, evaluate.main, [str(tmp_path / "m.zip"), "--device", "cuda"]) == expected
    for command in ("train", "enjoy", "record_video"):
        argv = [command, "--algo", "mtsac_mt", "--env", ENV, "-f", str(tmp_path), "-n", "10", "--device", "cuda"]
        with pytest.raises(SystemExit) as exit_info:
            cli_main(argv)
        assert exit_info.value.code == expected, command
    assert not (tmp_path / "mtsac_mt").exists()


def test_a_cuda_index_past_the_machine_s_devices_is_refused(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(th.cuda, "is_available", lambda: True)
    monkeypatch.setattr(th.cuda, "device_count", lambda: 1)
    message = one_line_error(capsys, evaluate.main, [str(tmp_path / "m.zip"), "--device", "cuda:1"])
    assert message == "--device cuda:1: this machine's CUDA devices are cuda:0; give one of them, or --device auto."


# ================================================================================================ output paths
def test_evaluate_refuses_an_output_under_a_file_before_evaluating(model, tmp_path, capsys, no_evaluation):
    copy = tmp_path / "ev" / "toy.zip"
    copy.parent.mkdir()
    shutil.copy(model, copy)
    out = f"{copy}/s.json"
    message = one_line_error(capsys, evaluate.main, [str(model), "--out", out])
    assert message == f"--out {out}: {copy} is a file, not a folder; give a path in a folder."


@NO_PROC
def test_evaluate_and_plot_refuse_an_output_that_cannot_be_written(model, tmp_path, capsys, no_evaluation):
    message = one_line_error(capsys, evaluate.main, [str(model), "--out", "/proc/nope/s.json"])
    assert message.startswith("--out /proc/nope/s.json: nothing can be written in /proc (")
    assert message.endswith("); give a folder you can write to.")
    (tmp_path / "runs").mkdir()
    message = one_line_error(capsys, plot.main, [str(tmp_path / "runs"), "--out", "/proc/figs"])
    assert message.startswith("--out /proc/figs: nothing can be written in /proc (")


def test_the_default_output_beside_the_model_is_checked_too(model, tmp_path, capsys, no_evaluation, monkeypatch):
    """A model whose own folder takes no file (here: its default output is under a file) stops before the work."""
    blocked = tmp_path / "blocked"
    blocked.write_text("")
    monkeypatch.setattr(evaluate, "default_output_path", lambda *args: blocked / "success.json")
    message = one_line_error(capsys, evaluate.main, [str(model)])
    assert message == f"--out {blocked / 'success.json'}: {blocked} is a file, not a folder; give a path in a folder."


# ================================================================================================== benchmarks
@pytest.mark.parametrize(
    ("env_id", "problem"),
    [
        ("MT10-smok", "did you mean MT10-smoke?"),
        ("MT11", "did you mean MT10?"),
        ("toy-conflict-1", "toy-conflict has at least 2 tasks, not 1: give toy-conflict-<N> with N >= 2."),
    ],
)
def test_an_unknown_benchmark_gets_the_nearest_name(tmp_path, env_id, problem):
    forms = benchmark_help()
    assert "toy-conflict-<N> (N >= 2), toy-agree-<N> (N >= 1)" in forms and forms.endswith(".")
    for command in ("train", "enjoy"):
        with pytest.raises(SystemExit) as exit_info:
            cli_main([command, "--algo", "mtsac_mt", "--env", env_id, "-f", str(tmp_path)])
        assert str(exit_info.value.code).endswith(f": {problem} The env ids: {forms}"), command
    assert not (tmp_path / "mtsac_mt").exists()


def test_evaluate_names_the_nearest_benchmark(model, capsys, no_evaluation):
    message = one_line_error(capsys, evaluate.main, [str(model), "--env", "MT11"])
    assert message == f"Unknown benchmark 'MT11': did you mean MT10? The env ids: {benchmark_help()}"


# ================================================================================================== evaluate
def test_a_model_outside_its_run_folder_is_evaluated_on_its_checkpoint_s_tasks(model, tmp_path, capsys):
    alone = tmp_path / "elsewhere" / "model.zip"
    alone.parent.mkdir()
    shutil.copy(model, alone)
    record = evaluate.main([str(alone), "--episodes", "1", "--no-progress"])
    assert record["env_id"] == ENV and record["task_names"] == ["agree-0", "agree-1", "agree-2", "conflict"]
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        f"No run_info.json beside {alone}: evaluating on {ENV}, the tasks of its checkpoint, with benchmark seed 0 "
        "(--env and --seed choose others)."
    ]
    assert (alone.parent / "success_model.json").is_file()


def test_the_header_names_the_run_s_env_id_and_counts_episodes(model, capsys):
    record = {"label": "Ours", "algorithm": "MTSACTE", "env_id": "MT10-smoke", "benchmark": "MT10", "seed": 0}
    title = evaluate.evaluation_title({**record, "timesteps": 10, "episodes_per_task": 1})
    assert title == "Ours on MT10-smoke (seed 0), 10 steps, 1 episode per task"
    assert evaluate.evaluation_title({**record, "timesteps": 10, "episodes_per_task": 2}).endswith(
        "2 episodes per task"
    )
    evaluate.main([str(model), "--episodes", "1", "--no-progress", "--out", str(model.parent / "one.json")])
    assert capsys.readouterr().out.startswith(f"SAC-MT on {ENV} (seed 3), 200 steps, 1 episode per task\n")


@pytest.mark.parametrize(
    ("flags", "expected"),
    [
        (["--episodes", "0"], "--episodes 0: give at least 1 episode per task (e.g. --episodes 50)."),
        (["--seed", "-3"], "--seed -3: the benchmark seed is an int from 0 to 2**32 - 1, e.g. --seed 0."),
    ],
)
def test_no_episode_or_a_negative_seed_is_refused_before_anything_is_drawn(
    model, capsys, no_evaluation, flags, expected
):
    assert one_line_error(capsys, evaluate.main, [str(model), *flags]) == expected
    assert capsys.readouterr().out == ""
    with pytest.raises(ValueError, match=r"^--episodes 0: give at least 1"):
        evaluate.evaluate_model(model, episodes=0)


# ====================================================================================================== enjoy -n
def test_enjoy_s_n_says_it_counts_vector_steps(capsys):
    with pytest.raises(SystemExit):
        cli_main(["enjoy", "--help"])
    help_text = " ".join(capsys.readouterr().out.split())
    assert "-n N_TIMESTEPS, --n-timesteps N_TIMESTEPS vector steps: each steps every task once" in help_text
    assert "train's -n counts env steps over all tasks" in help_text


# ====================================================================================== the checkout's install
def test_tests_from_a_checkout_not_installed_editable_stop_with_one_line(tmp_path):
    """A checkout whose package Python finds without its zoo configs (a plain pip install, then python -m pytest in
    the checkout): collection stops with one line naming pip install -e, before any test runs."""
    checkout = tmp_path / "checkout"
    shutil.copytree(ROOT / "sb3_mtte", checkout / "sb3_mtte", ignore=shutil.ignore_patterns("__pycache__"))
    (checkout / "tests").mkdir()
    shutil.copy(ROOT / "tests" / "conftest.py", checkout / "tests")
    (checkout / "tests" / "test_nothing.py").write_text("def test_nothing():\n    pass\n")
    result = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "tests"],
        cwd=checkout,
        capture_output=True,
        text=True,
        timeout=300,
    )
    lines = [line for line in (result.stdout + result.stderr).splitlines() if line.strip()]
    assert result.returncode == pytest.ExitCode.USAGE_ERROR, lines
    assert len(lines) == 1 and "Traceback" not in lines[0], lines
    assert lines[0].endswith(
        f'Python finds it without its zoo configs: run pip install -e ".[tests]" in {checkout} (pip install -e . at '
        "least), then the tests again."
    )
