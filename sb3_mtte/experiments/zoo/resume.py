"""What the multi-task manager does with a run folder that already holds a run, before any env is built.

- ``--resume``: every setting the run was started with comes back from its folder
  (:mod:`~sb3_mtte.experiments.zoo.run_settings`); a flag given again overrides one and is named in one line. A
  finished run has nothing to resume unless ``-n`` is larger than its steps.
- ``--exp-id`` of a folder that holds a run: a finished run given the same settings has nothing to do (a second
  identical command exits 0); one with other settings, or a stopped run, is refused naming the way out.
"""

from __future__ import annotations

import importlib
import os
from typing import Any

import torch as th
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

from sb3_mtte.experiments import run_info
from sb3_mtte.experiments.cli import device_error
from sb3_mtte.experiments.zoo.run_settings import (
    HYPERPARAMETERS,
    RUN_SETTINGS,
    SETTINGS,
    hyperparameter_notice,
    override_notice,
    recorded_hyperparameters,
    recorded_settings,
    same_value,
    shown,
)


class NothingToDo(Exception):
    """The run folder already holds what the command asks for; the message says so (the command exits 0)."""


ATTRIBUTES = {
    "seed": "seed",
    "n_timesteps": "n_timesteps",
    "device": "device",
    "verbose": "verbose",
    "eval_freq": "eval_freq",
    "eval_episodes": "n_eval_episodes",
    "n_eval_envs": "n_eval_envs",
    "truncate_last_trajectory": "truncate_last_trajectory",
    "save_freq": "save_freq",
    "log_interval": "log_interval",
    "save_replay_buffer": "save_replay_buffer",
    "progress": "show_progress",
}
"""Settings that are one attribute of the manager, and that attribute."""

ARGUMENTS = ("num_threads", "vec_env", "tensorboard_log", "gym_packages")
"""Settings read from the parsed arguments."""

SWITCH_FLAGS = {
    "progress": ("--no-progress", "-P"),
    "save_replay_buffer": (None, "--save-replay-buffer"),
    "align_checkpoints": ("--no-align-checkpoints", None),
    "tensorboard": ("--no-tensorboard", None),
}
"""On/off settings: the flag that turns each off, and the one that turns it on."""


class RunFolderSettings:
    """The part of :class:`~sb3_mtte.experiments.zoo.manager.MultiTaskExperimentManager` that reads a run folder's
    own settings (it relies on the manager's attributes)."""

    args: Any
    launch: Any
    save_path: str
    env_name: Any
    env_kwargs: dict[str, Any]
    eval_env_kwargs: dict[str, Any]
    eval_env_kwargs_given: dict[str, Any] | None
    custom_hyperparams: dict[str, Any] | None
    vec_env_class: Any
    tensorboard_dir: str | None
    n_timesteps: int

    # ---- the values of a setting
    def setting_value(self, dest: str) -> Any:
        """The value the command sets for ``dest``: given, or its default."""
        if dest in ATTRIBUTES:
            return getattr(self, ATTRIBUTES[dest])
        if dest in ARGUMENTS:
            return getattr(self.args, dest, None)
        if dest == "env_kwargs":
            return self.env_kwargs
        if dest == "eval_env_kwargs":
            return self.eval_env_kwargs_given
        return getattr(self.launch, dest)

    def restore_setting(self, dest: str, value: Any) -> None:
        """Take the run's own value of ``dest``."""
        problem = device_error("--device", value) if dest == "device" else None
        if problem:
            raise SystemExit(f"The run's own device: {problem}")
        if dest in ATTRIBUTES:
            setattr(self, ATTRIBUTES[dest], value)
        elif dest == "num_threads" and int(value) > 0:
            th.set_num_threads(int(value))
        elif dest == "env_kwargs":
            self.env_kwargs = dict(value or {})
        elif dest == "eval_env_kwargs":  # after env_kwargs: none given means the training env's
            self.eval_env_kwargs_given = value
            self.eval_env_kwargs = dict(value or self.env_kwargs)
        elif dest == "vec_env":
            self.vec_env_class.vec_env_cls = SubprocVecEnv if value == "subproc" else DummyVecEnv
        elif dest == "tensorboard_log":
            self.tensorboard_dir = os.path.join(value, self.env_name) if value else None
        elif dest == "gym_packages":
            for module in value or ():
                importlib.import_module(module)
        elif dest in ("keep_buffers", "align_checkpoints", "tensorboard"):
            setattr(self.launch, dest, value)
        if dest in ARGUMENTS:
            setattr(self.args, dest, value)

    def _flag_of(self, dest: str, value: Any) -> str:
        switch = SWITCH_FLAGS.get(dest)
        flag = None if switch is None else switch[bool(value)]
        return flag or SETTINGS[dest].flags[0]

    # ---- --resume
    def restore_run_settings(self) -> None:
        """Resuming: take every setting of the run folder that is not given again; name each one that is, in one
        line, where it differs."""
        recorded = recorded_settings(self.save_path, self.env_name)
        given = self.launch.flags_given
        for setting in RUN_SETTINGS:
            if setting.dest not in recorded:
                continue
            if setting.dest not in given:
                self.restore_setting(setting.dest, recorded[setting.dest])
                continue
            value = self.setting_value(setting.dest)
            notice = override_notice(setting.dest, value, recorded[setting.dest], self._flag_of(setting.dest, value))
            if notice:
                print(notice)

    def hyperparameter_overrides(self, recorded: dict[str, Any]) -> None:
        """Resuming: name each ``-params`` value that differs from the run's ``config.yml``, in one line each."""
        for key, value in (self.custom_hyperparams or {}).items():
            notice = hyperparameter_notice(key, value, recorded.get(key))
            if notice:
                print(notice)

    def refuse_a_finished_resume(self) -> None:
        """Resuming a finished run does nothing, unless ``-n`` is larger than its steps."""
        info = run_info.read_run_info(self.save_path) or {}
        done = int(info.get("timesteps", 0))
        if info.get("finished") and self.n_timesteps <= done:
            raise NothingToDo(
                f"{self.save_path} is finished ({done:,} of {int(info.get('n_timesteps', done)):,} env steps): "
                f"nothing to do; -n above {done} trains it further."
            )

    # ---- --exp-id of a folder that holds a run
    def check_the_run_folder(self) -> None:
        """A new run into a folder that holds a run: nothing to do if that run is finished with the same settings,
        else one line naming the way out."""
        info = run_info.read_run_info(self.save_path)
        if info is None:
            return
        done = int(info.get("timesteps", 0))
        if not info.get("finished"):
            raise SystemExit(
                f"{self.save_path} already holds a run: use --resume {self.save_path}. It is not finished; another "
                "--exp-id, or none, starts a new run."
            )
        difference = self.first_difference()
        if difference:
            raise SystemExit(
                f"{self.save_path} holds a finished run with other settings ({difference}): give another --exp-id, "
                "or none for the next free one."
            )
        raise NothingToDo(
            f"{self.save_path} holds this run, finished at {done:,} env steps: nothing to do (another --exp-id, or "
            "none, starts a new run)."
        )

    def first_difference(self) -> str | None:
        """The first setting given now that changes results and differs from the run's, in words, or None."""
        recorded = recorded_settings(self.save_path, self.env_name)
        given = self.launch.flags_given
        for setting in RUN_SETTINGS:
            if not (setting.changes_results and setting.dest in given and setting.dest in recorded):
                continue
            value, theirs = self.setting_value(setting.dest), recorded[setting.dest]
            if not same_value(value, theirs):
                if setting.switch is not None:
                    return f"{setting.switch}: {'on' if theirs else 'off'} there, {'on' if value else 'off'} here"
                return f"{self._flag_of(setting.dest, value)}: {shown(theirs)} there, {shown(value)} here"
        if HYPERPARAMETERS in given:
            config = recorded_hyperparameters(self.save_path, self.env_name)
            for key, value in (self.custom_hyperparams or {}).items():
                if not same_value(value, config.get(key)):
                    return f"-params {key}: {config.get(key)!r} there, {value!r} here"
        return None


__all__ = ["NothingToDo", "RunFolderSettings"]
