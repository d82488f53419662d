"""The settings a run was started with, as its folder records them, and what a later command makes of them.

``train --resume`` takes every setting below from the run folder. A flag given again overrides its setting, and the
command says so in one line (``--num-threads 2 overrides the run's 1.``). The hyperparameters come from the run's
``config.yml``; ``-params`` given at resume overrides them key by key, each named likewise.

========================  ======================================  ==================================================
setting                   flags                                   recorded in
========================  ======================================  ==================================================
seed                      ``--seed``                              ``run_info.json``
n_timesteps               ``-n``                                  ``run_info.json``
num_threads               ``--num-threads``                       ``<env>/args.yml``
device                    ``--device``                            ``<env>/args.yml``
verbose                   ``--verbose``                           ``<env>/args.yml``
env_kwargs                ``--env-kwargs``                        ``<env>/args.yml``
eval_env_kwargs           ``--eval-env-kwargs``                   ``<env>/args.yml``
eval_freq                 ``--eval-freq``                         ``<env>/config.yml``
eval_episodes             ``--eval-episodes``                     ``<env>/config.yml``
n_eval_envs               ``--n-eval-envs``                       ``<env>/args.yml``
save_freq                 ``--save-freq``                         ``<env>/config.yml``
vec_env                   ``--vec-env``                           ``<env>/args.yml``
log_interval              ``--log-interval``                      ``<env>/args.yml``
save_replay_buffer        ``--save-replay-buffer``                ``<env>/args.yml``
truncate_last_trajectory  ``--truncate-last-trajectory``          ``<env>/args.yml``
tensorboard_log           ``-tb``                                 ``<env>/args.yml``
gym_packages              ``--gym-packages``                      ``<env>/args.yml``
progress                  ``-P``, ``--no-progress``               ``<env>/args.yml``
keep_buffers              ``--keep-buffers``                      ``run_info.json`` (``launcher``)
align_checkpoints         ``--no-align-checkpoints``              ``run_info.json`` (``launcher``)
tensorboard               ``--no-tensorboard``                    ``run_info.json`` (``launcher``)
========================  ======================================  ==================================================

``--resume`` refuses the flags of a new start in one line (:data:`REFUSED_AT_RESUME`): optuna's (``-optimize``,
``--n-trials``, ...), ``-i`` (a resumed run continues from its own checkpoint) and ``--track`` (rl-zoo starts
wandb before the run folder is read). ``-conf`` and ``-uuid`` change nothing at resume.

A second run into a folder that holds a finished run (``--exp-id``) compares the settings that change its results
(:attr:`RunSetting.changes_results`): when every one given equals the run's, there is nothing to do.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from sb3_mtte.experiments import run_info
from sb3_mtte.experiments.zoo.configs import LAUNCHER_YAML_KEYS


@dataclass(frozen=True)
class RunSetting:
    """One setting of a run that a later command restores or overrides."""

    dest: str
    """Its name in rl-zoo's parsed arguments (and in ``args.yml``)."""
    flags: tuple[str, ...]
    """The flags that set it."""
    changes_results: bool = True
    """Whether it changes what the run computes (a thread count or a progress bar does not)."""
    switch: str | None = None
    """For an on/off setting, what it switches (``"progress bar"``)."""
    unset: str | None = None
    """What -1, the flag's default, stands for (``"torch's default"``)."""


RUN_SETTINGS: tuple[RunSetting, ...] = (
    RunSetting("seed", ("--seed",)),
    RunSetting("n_timesteps", ("-n", "--n-timesteps")),
    RunSetting("num_threads", ("--num-threads",), changes_results=False, unset="torch's default"),
    RunSetting("device", ("--device",), changes_results=False),
    RunSetting("verbose", ("--verbose",), changes_results=False),
    RunSetting("env_kwargs", ("--env-kwargs",)),
    RunSetting("eval_env_kwargs", ("--eval-env-kwargs",)),
    RunSetting("eval_freq", ("--eval-freq",)),
    RunSetting("eval_episodes", ("--eval-episodes",)),
    RunSetting("n_eval_envs", ("--n-eval-envs",), changes_results=False),
    RunSetting("save_freq", ("--save-freq",)),
    RunSetting("vec_env", ("--vec-env",), changes_results=False),
    RunSetting("log_interval", ("--log-interval",), changes_results=False, unset="the model's default"),
    RunSetting("save_replay_buffer", ("--save-replay-buffer",), changes_results=False, switch="replay-buffer saving"),
    RunSetting("truncate_last_trajectory", ("--truncate-last-trajectory",)),
    RunSetting("tensorboard_log", ("-tb", "--tensorboard-log"), changes_results=False),
    RunSetting("gym_packages", ("--gym-packages",), changes_results=False),
    RunSetting("progress", ("-P", "--progress", "--no-progress"), changes_results=False, switch="progress bar"),
    RunSetting("keep_buffers", ("--keep-buffers",), changes_results=False),
    RunSetting("align_checkpoints", ("--no-align-checkpoints",), switch="checkpoints at the end of episodes"),
    RunSetting("tensorboard", ("--no-tensorboard",), changes_results=False, switch="tensorboard events"),
)
"""Every setting a resumed run takes from its folder (see the module docstring)."""

SETTINGS = {setting.dest: setting for setting in RUN_SETTINGS}
LAUNCHER_SETTINGS = ("keep_buffers", "align_checkpoints", "tensorboard")
"""Settings of the launcher, recorded in ``run_info.json``'s ``launcher``."""
HYPERPARAMETERS = "hyperparams"
"""The key of ``-params`` in :func:`given_settings`."""
OPTUNA_FLAGS = (
    ("-optimize", "--optimize-hyperparameters"),
    ("--n-trials",),
    ("--max-total-trials",),
    ("--n-jobs",),
    ("--sampler",),
    ("--pruner",),
    ("--n-startup-trials",),
    ("--n-evaluations",),
    ("--storage",),
    ("--study-name",),
    ("--trial-id",),
    ("--optimization-log-path",),
    ("--no-optim-plots",),
)
"""rl-zoo's optuna flags (a hyperparameter search, not a run to resume)."""
REFUSED_AT_RESUME = (*OPTUNA_FLAGS, ("-i", "--trained-agent"), ("--track",))
"""The flags of a new start that ``--resume`` refuses, each with its other spellings."""


def has_flag(argv: Sequence[str], *names: str) -> bool:
    """Whether one of the options ``names`` is in ``argv`` (``--x v`` or ``--x=v``)."""
    return any(arg in names or any(arg.startswith(n + "=") for n in names) for arg in argv)


def given_settings(argv: Sequence[str]) -> frozenset[str]:
    """The settings of :data:`RUN_SETTINGS` (and :data:`HYPERPARAMETERS`) that ``argv`` gives."""
    given = {setting.dest for setting in RUN_SETTINGS if has_flag(argv, *setting.flags)}
    if has_flag(argv, "-params", "--hyperparams"):
        given.add(HYPERPARAMETERS)
    return frozenset(given)


def resume_refusal(argv: Sequence[str]) -> str | None:
    """The line that refuses a flag of :data:`REFUSED_AT_RESUME` in ``argv`` given with ``--resume``, or None."""
    for names in REFUSED_AT_RESUME:
        if has_flag(argv, *names):
            if names in OPTUNA_FLAGS:
                return f"{names[0]} is a hyperparameter search: run it without --resume."
            if names[0] == "-i":
                return "-i with --resume: a resumed run continues from its own checkpoint; leave -i out."
            return "--track with --resume: tracking starts with a new run only; leave --track out."
    return None


def _read_yaml(path: Path) -> dict[str, Any]:
    if not path.is_file():
        return {}
    with open(path) as file:
        return dict(yaml.load(file, Loader=yaml.UnsafeLoader) or {})


def recorded_settings(run_dir: str | os.PathLike, env_name: str) -> dict[str, Any]:
    """The settings of :data:`RUN_SETTINGS` that the run folder records (its command-line arguments, the launcher
    keys of its ``config.yml``, its seed and budget), by setting."""
    run_dir = Path(run_dir)
    info = run_info.read_run_info(run_dir) or {}
    args = _read_yaml(run_dir / env_name / "args.yml") or dict(info.get("zoo_args") or {})
    recorded = {dest: args[dest] for dest in SETTINGS if dest in args}
    config = _read_yaml(run_dir / env_name / "config.yml")
    recorded.update({key: config[key] for key in LAUNCHER_YAML_KEYS if key in config})
    recorded.update({key: info[key] for key in ("seed", "n_timesteps") if key in info})
    launcher = info.get("launcher") or {}
    recorded.update({key: launcher[key] for key in LAUNCHER_SETTINGS if key in launcher})
    return recorded


def recorded_hyperparameters(run_dir: str | os.PathLike, env_name: str) -> dict[str, Any]:
    """The hyperparameters of the run folder (its ``config.yml``), empty when it has none."""
    return _read_yaml(Path(run_dir) / env_name / "config.yml")


def shown(value: Any) -> str:
    """A setting's value as a flag takes it: ``key:value`` pairs for keyword arguments, ``none`` for none."""
    if value is None or value == "" or value == {} or value == []:
        return "none"
    if isinstance(value, Mapping):
        return " ".join(f"{key}:{item!r}" for key, item in value.items())
    if isinstance(value, (list, tuple)):
        return " ".join(str(item) for item in value)
    return str(value)


def same_value(given: Any, recorded: Any) -> bool:
    """Whether a value given now is the one recorded (``None`` and an empty value are the same)."""
    if shown(given) == "none" and shown(recorded) == "none":
        return True
    return bool(given == recorded)


def override_notice(dest: str, given: Any, recorded: Any, flag: str | None = None) -> str | None:
    """The line that says a flag given now overrides the run's own setting, or None when both are the same."""
    if same_value(given, recorded):
        return None
    setting = SETTINGS[dest]
    flag = flag or setting.flags[0]
    if setting.switch is not None:
        return f"{flag} overrides the run's setting ({setting.switch} {'on' if recorded else 'off'})."
    theirs = setting.unset if setting.unset is not None and recorded == -1 else shown(recorded)
    return f"{flag} {shown(given)} overrides the run's {theirs}."


def hyperparameter_notice(key: str, given: Any, recorded: Any) -> str | None:
    """The line that says ``-params key:value`` overrides the run's value of ``key``, or None when it is the same."""
    if same_value(given, recorded):
        return None
    return f"-params {key}:{given!r} overrides the run's {'none' if recorded is None else repr(recorded)}."


__all__ = [
    "HYPERPARAMETERS",
    "REFUSED_AT_RESUME",
    "RUN_SETTINGS",
    "RunSetting",
    "given_settings",
    "has_flag",
    "hyperparameter_notice",
    "override_notice",
    "recorded_hyperparameters",
    "recorded_settings",
    "resume_refusal",
    "same_value",
    "shown",
]
