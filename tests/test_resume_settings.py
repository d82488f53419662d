"""``train --resume <folder>`` restores every setting the run was started with; a flag given again overrides it
and the command says so in one line.

One tiny toy run is started with a value other than the default for every setting and stopped by Ctrl-C. Two
resumes of copies of it are watched up to the start of training: one with no flag, one with a new value for every
setting that has a flag to change it.
"""

from __future__ import annotations

import contextlib
import io
import os
import shutil
import signal
from pathlib import Path
from typing import Any

import pytest
import torch as th
from conftest import ENV
from stable_baselines3.common.callbacks import BaseCallback

from sb3_mtte.experiments.cli import main
from sb3_mtte.experiments.zoo.manager import MultiTaskExperimentManager
from sb3_mtte.experiments.zoo.run_settings import RUN_SETTINGS

ALGO = "mtsac_mt"
THREADS = th.get_num_threads()


class SigintAt(BaseCallback):
    """Stands for a Ctrl-C: send SIGINT to this process once ``timesteps`` env steps are reached."""

    def __init__(self, timesteps: int) -> None:
        super().__init__()
        self.timesteps, self.sent = timesteps, False

    def _on_step(self) -> bool:
        if not self.sent and self.num_timesteps >= self.timesteps:
            self.sent = True
            os.kill(os.getpid(), signal.SIGINT)
        return True


class Captured(Exception):
    """Ends a resumed run at the start of its training, with what it was about to train with."""

    def __init__(self, settings: dict[str, Any]) -> None:
        super().__init__("captured")
        self.settings = settings


def settings_at_learn(manager: MultiTaskExperimentManager, model: Any) -> dict[str, Any]:
    """What the resumed run trains with, read where it takes effect, by setting of ``RUN_SETTINGS``."""
    env = model.get_env()
    checkpoints, evaluation = manager.checkpoint_callback, manager.eval_callback
    return {
        "seed": manager.seed,
        "n_timesteps": manager.n_timesteps,
        "num_threads": th.get_num_threads(),
        "device": manager.device,
        "verbose": manager.verbose,
        "env_kwargs": env.get_attr("_max_episode_steps")[0],
        "eval_env_kwargs": evaluation.eval_env.get_attr("_max_episode_steps")[0],
        "eval_freq": evaluation.eval_freq * manager.n_tasks,
        "eval_episodes": evaluation.episodes_per_task,
        "n_eval_envs": manager.n_eval_envs,
        "truncate_last_trajectory": manager.truncate_last_trajectory,
        "save_freq": checkpoints.save_freq,
        "vec_env": type(env).__name__,
        "log_interval": manager.log_interval,
        "save_replay_buffer": manager.save_replay_buffer,
        "tensorboard_log": manager.tensorboard_dir,
        "gym_packages": manager.args.gym_packages,
        "progress": manager.show_progress,
        "keep_buffers": checkpoints.keep_buffers,
        "align_checkpoints": checkpoints.align_to_episodes,
        "tensorboard": manager.launch.tensorboard,
        "hyperparams": model.batch_size,
    }


def started_flags(tb: Path) -> list[str]:
    return [
        *("--seed", "3", "-n", "800", "--num-threads", str(THREADS + 1), "--device", "cpu", "--verbose", "0"),
        *("--env-kwargs", "max_episode_steps:25", "--eval-env-kwargs", "max_episode_steps:10"),
        *("--eval-freq", "100", "--eval-episodes", "2", "--save-freq", "400", "--vec-env", "dummy"),
        *("--n-eval-envs", "2", "--truncate-last-trajectory", ""),  # rl-zoo's type=bool: only "" is False
        *("--log-interval", "2", "--save-replay-buffer", "-tb", str(tb / "started"), "--gym-packages", "sb3_mtte.envs"),
        *("--no-progress", "--keep-buffers", "2", "--no-align-checkpoints", "--no-tensorboard"),
        *("-params", "batch_size:16"),
    ]


STARTED = {
    "seed": 3,
    "n_timesteps": 800,
    "num_threads": THREADS + 1,
    "device": "cpu",
    "verbose": 0,
    "env_kwargs": 25,
    "eval_env_kwargs": 10,
    "eval_freq": 100,
    "eval_episodes": 2,
    "n_eval_envs": 2,
    "truncate_last_trajectory": False,
    "save_freq": 400,
    "vec_env": "DummyVecEnv",
    "log_interval": 2,
    "save_replay_buffer": True,
    "tensorboard_log": "started",
    "gym_packages": ["sb3_mtte.envs"],
    "progress": False,
    "keep_buffers": 2,
    "align_checkpoints": False,
    "tensorboard": False,
    "hyperparams": 16,
}
"""What the run was started with, as :func:`settings_at_learn` reads it (a tensorboard folder: its parent's
name)."""

OVERRIDES: dict[str, tuple[list[str], Any, str]] = {
    "seed": (["--seed", "4"], 4, "--seed 4 overrides the run's 3."),
    "n_timesteps": (["-n", "1000"], 1000, "-n 1000 overrides the run's 800."),
    "num_threads": (["--num-threads", "1"], 1, f"--num-threads 1 overrides the run's {THREADS + 1}."),
    "device": (["--device", "auto"], "auto", "--device auto overrides the run's cpu."),
    "verbose": (["--verbose", "1"], 1, "--verbose 1 overrides the run's 0."),
    "env_kwargs": (
        ["--env-kwargs", "max_episode_steps:20"],
        20,
        "--env-kwargs max_episode_steps:20 overrides the run's max_episode_steps:25.",
    ),
    "eval_env_kwargs": (
        ["--eval-env-kwargs", "max_episode_steps:12"],
        12,
        "--eval-env-kwargs max_episode_steps:12 overrides the run's max_episode_steps:10.",
    ),
    "eval_freq": (["--eval-freq", "300"], 300, "--eval-freq 300 overrides the run's 100."),
    "eval_episodes": (["--eval-episodes", "1"], 1, "--eval-episodes 1 overrides the run's 2."),
    "save_freq": (["--save-freq", "300"], 300, "--save-freq 300 overrides the run's 400."),
    "n_eval_envs": (["--n-eval-envs", "3"], 3, "--n-eval-envs 3 overrides the run's 2."),
    "truncate_last_trajectory": (
        ["--truncate-last-trajectory", "1"],
        True,
        "--truncate-last-trajectory True overrides the run's False.",
    ),
    "vec_env": (["--vec-env", "subproc"], "SubprocVecEnv", "--vec-env subproc overrides the run's dummy."),
    "log_interval": (["--log-interval", "3"], 3, "--log-interval 3 overrides the run's 2."),
    "tensorboard_log": (["-tb", "{tb}/resumed"], "resumed", "-tb {tb}/resumed overrides the run's {tb}/started."),
    "gym_packages": (
        ["--gym-packages", "sb3_mtte"],
        ["sb3_mtte"],
        "--gym-packages sb3_mtte overrides the run's sb3_mtte.envs.",
    ),
    "progress": (["-P"], True, "-P overrides the run's setting (progress bar off)."),
    "keep_buffers": (["--keep-buffers", "3"], 3, "--keep-buffers 3 overrides the run's 2."),
    "hyperparams": (["-params", "batch_size:32"], 32, "-params batch_size:32 overrides the run's 16."),
}
"""Setting -> (flags given at resume, what the resumed run trains with, the line that says so). The on/off
settings without a flag that turns them back on (--save-replay-buffer, --no-align-checkpoints, --no-tensorboard) are
restored only."""


def _readable(settings: dict[str, Any]) -> dict[str, Any]:
    tb = settings["tensorboard_log"]
    return {**settings, "tensorboard_log": None if tb is None else Path(tb).parent.name}


def _resume(run: Path, copy_root: Path, *extra: str) -> tuple[dict[str, Any], str]:
    """Resume a copy of ``run`` up to the start of its training: (what it trains with, what it printed)."""
    copy = copy_root / ALGO / run.name
    shutil.copytree(run, copy)

    def capture(manager: MultiTaskExperimentManager, model: Any) -> None:
        settings = settings_at_learn(manager, model)
        model.get_env().close()
        manager.eval_callback.eval_env.close()
        raise Captured(settings)

    th.set_num_threads(THREADS)
    out = io.StringIO()
    with (
        pytest.MonkeyPatch.context() as patch,
        pytest.raises(Captured) as captured,
        contextlib.redirect_stdout(out),
    ):
        patch.setattr(MultiTaskExperimentManager, "learn", capture)
        main(["train", "--resume", str(copy), *extra])
    th.set_num_threads(THREADS)
    return _readable(captured.value.settings), out.getvalue()


@pytest.fixture(scope="module")
def started(tmp_path_factory) -> Path:
    """A run started with a value other than the default for every setting, stopped by Ctrl-C at 200 env steps."""
    root = tmp_path_factory.mktemp("started")
    original = MultiTaskExperimentManager.create_callbacks

    def with_ctrl_c(manager: MultiTaskExperimentManager) -> None:
        original(manager)
        manager.callbacks.append(SigintAt(200))

    with pytest.MonkeyPatch.context() as patch, pytest.raises(SystemExit) as stopped:
        patch.setattr(MultiTaskExperimentManager, "create_callbacks", with_ctrl_c)
        main(["train", "--algo", ALGO, "--env", ENV, "-f", str(root), *started_flags(root / "tb")])
    th.set_num_threads(THREADS)
    assert stopped.value.code == 130
    return root / ALGO / f"{ENV}_1"


@pytest.fixture(scope="module")
def resumed_plainly(started, tmp_path_factory) -> tuple[dict[str, Any], str]:
    return _resume(started, tmp_path_factory.mktemp("plain"))


@pytest.fixture(scope="module")
def resumed_with_overrides(started, tmp_path_factory) -> tuple[dict[str, Any], str]:
    tb = started.parent.parent / "tb"
    given = [flag.format(tb=tb) for flags, _, _ in OVERRIDES.values() for flag in flags]
    return _resume(started, tmp_path_factory.mktemp("overridden"), *given)


def test_every_setting_of_the_table_is_checked():
    assert set(STARTED) == {setting.dest for setting in RUN_SETTINGS} | {"hyperparams"}
    assert set(OVERRIDES) <= set(STARTED)


@pytest.mark.parametrize("setting", sorted(STARTED))
def test_a_resume_without_flags_restores_the_setting(resumed_plainly, setting):
    settings, stdout = resumed_plainly
    assert settings[setting] == STARTED[setting]
    assert "overrides" not in stdout


@pytest.mark.parametrize("setting", sorted(OVERRIDES))
def test_a_flag_given_at_resume_overrides_the_setting_in_one_line(resumed_with_overrides, started, setting):
    settings, stdout = resumed_with_overrides
    _, value, notice = OVERRIDES[setting]
    assert settings[setting] == value
    assert notice.format(tb=started.parent.parent / "tb") in stdout.splitlines()


@pytest.mark.parametrize(
    ("flags", "line"),
    [
        (["-optimize"], "-optimize is a hyperparameter search: run it without --resume."),
        (["--n-trials", "3"], "--n-trials is a hyperparameter search: run it without --resume."),
        (["--storage", "x.db"], "--storage is a hyperparameter search: run it without --resume."),
        (["-i", "model.zip"], "-i with --resume: a resumed run continues from its own checkpoint; leave -i out."),
        (["--track"], "--track with --resume: tracking starts with a new run only; leave --track out."),
    ],
)
def test_resume_refuses_the_flags_of_a_new_start_in_one_line(started, flags, line):
    with pytest.raises(SystemExit) as refused:
        main(["train", "--resume", str(started), *flags])
    assert str(refused.value.code) == line
