"""``train``: rl-zoo3's train with one sub-env per task, the variants' hyperparameters and resumable runs.

Launcher options of ``train`` (besides rl-zoo's): ``--resume [RUN_DIR]``, ``--exp-id N`` (run folder ``<env>_N``),
``--no-progress``, ``--no-tensorboard``, ``--keep-buffers K`` (replay-buffer checkpoints kept, default 1, 0 = all),
``--no-align-checkpoints`` (save at the step reached, not at the next end of episodes). Without ``-conf``, the
hyperparameters of ``--algo`` are its family's file plus its overrides (:mod:`sb3_mtte.experiments.configs`).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import rl_zoo3
import rl_zoo3.train
from huggingface_sb3 import EnvironmentName
from rl_zoo3 import hyperparams_opt
from rl_zoo3.utils import get_latest_run_id

from sb3_mtte.experiments import run_info
from sb3_mtte.experiments.configs import missing_entries_message, zoo_hyperparameters
from sb3_mtte.experiments.env_ids import benchmark_help, register_env_id
from sb3_mtte.experiments.manager import LaunchOptions, MultiTaskExperimentManager
from sb3_mtte.experiments.variants import algo_classes, convert_trial_params, family_of

TRACKED_FLAGS: dict[str, tuple[str, ...]] = {
    "eval_freq": ("--eval-freq",),
    "eval_episodes": ("--eval-episodes",),
    "save_freq": ("--save-freq",),
    "n_timesteps": ("-n", "--n-timesteps"),
    "env_kwargs": ("--env-kwargs",),
    "eval_env_kwargs": ("--eval-env-kwargs",),
    "vec_env": ("--vec-env",),
    "log_interval": ("--log-interval",),
    "save_replay_buffer": ("--save-replay-buffer",),
    "tensorboard_log": ("-tb", "--tensorboard-log"),
}
"""rl-zoo flags whose presence on the command line matters (file defaults, resumed runs' own settings)."""

LAUNCHER_HELP = (
    "sb3_mtte options: --resume [RUN_DIR] (continue the latest checkpoint of RUN_DIR, default the latest "
    "run of --algo/--env in -f), --exp-id N (run folder <env>_N instead of the next free one), "
    "--no-progress, --no-tensorboard, --keep-buffers K (replay-buffer checkpoints kept, 0 = all; "
    "default 1), --no-align-checkpoints.\nrl-zoo options:"
)


def register_algos() -> None:
    """Add every zoo key to ``rl_zoo3.ALGOS`` and its optuna sampler to rl-zoo's tables (idempotent)."""
    for key, cls in algo_classes().items():
        family = family_of(key)
        assert family is not None
        rl_zoo3.ALGOS[key] = cls
        hyperparams_opt.HYPERPARAMS_SAMPLER[key] = family.sample_params
        hyperparams_opt.HYPERPARAMS_CONVERTER[key] = convert_trial_params


def flag_value(argv: Sequence[str], *names: str) -> str | None:
    """Value of the last occurrence of an option (``--x v`` or ``--x=v``) in ``argv``."""
    value = None
    for i, arg in enumerate(argv):
        for name in names:
            if arg == name and i + 1 < len(argv):
                value = argv[i + 1]
            elif arg.startswith(name + "="):
                value = arg.split("=", 1)[1]
    return value


def has_flag(argv: Sequence[str], *names: str) -> bool:
    """Whether one of the options ``names`` is in ``argv``."""
    return any(arg in names or any(arg.startswith(n + "=") for n in names) for arg in argv)


def latest_run_dir(log_folder: str, algo: str, env_id: str) -> Path:
    """The latest run folder ``<log_folder>/<algo>/<env>_<id>``."""
    env_name = EnvironmentName(env_id)
    exp_id = get_latest_run_id(os.path.join(log_folder, algo), env_name)
    if exp_id == 0:
        raise SystemExit(
            f"No run of {algo} on {env_id} in {log_folder}/{algo}/ to resume: give -f of your runs, or --resume "
            "RUN_DIR."
        )
    return Path(log_folder) / algo / f"{env_name}_{exp_id}"


def _launcher_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="sb3-mtte train", add_help=False)
    parser.add_argument("--resume", nargs="?", const="", default=None, metavar="RUN_DIR")
    parser.add_argument("--no-progress", action="store_true")
    parser.add_argument("--no-tensorboard", action="store_true", default=None)
    parser.add_argument("--keep-buffers", type=int, default=None)
    parser.add_argument("--no-align-checkpoints", action="store_true", default=None)
    parser.add_argument("--exp-id", type=int, default=None)
    return parser


def _resume_run(resume: str, zoo_argv: list[str], algo: str, env_id: str | None) -> tuple[str, dict[str, Any]]:
    """The run folder to resume and its saved launcher options; adds the run's seed and log folder to ``zoo_argv``."""
    if env_id is None:
        raise SystemExit("--resume needs --algo and --env (or a run folder: --resume RUN_DIR).")
    log_folder = flag_value(zoo_argv, "-f", "--log-folder") or "logs"
    resume_dir = Path(resume) if resume else latest_run_dir(log_folder, algo, env_id)
    info = run_info.read_run_info(resume_dir) or {}
    if info and (info.get("algo"), info.get("env_id")) != (algo, env_id):
        raise SystemExit(
            f"{resume_dir} is a run of --algo {info.get('algo')} --env {info.get('env_id')}, "
            f"not --algo {algo} --env {env_id}."
        )
    if not has_flag(zoo_argv, "--seed") and "seed" in info:
        zoo_argv += ["--seed", str(info["seed"])]
    if resume and not has_flag(zoo_argv, "-f", "--log-folder"):
        zoo_argv += ["-f", str(resume_dir.parent.parent)]
    return str(resume_dir), dict(info.get("launcher") or {})


def _launch_options(ours: argparse.Namespace, zoo_argv: list[str], algo: str, saved: dict[str, Any]) -> LaunchOptions:
    """Launcher options from the command line, else the resumed run's, else the defaults."""

    def choose(given: Any, key: str, default: Any) -> Any:
        return given if given is not None else saved.get(key, default)

    no_align, no_tensorboard = ours.no_align_checkpoints, ours.no_tensorboard
    uses_conf = has_flag(zoo_argv, "-conf", "--conf-file", "-h", "--help")
    return LaunchOptions(
        exp_id=ours.exp_id,
        flags_given=frozenset(dest for dest, names in TRACKED_FLAGS.items() if has_flag(zoo_argv, *names)),
        keep_buffers=choose(ours.keep_buffers, "keep_buffers", 1),
        align_checkpoints=choose(None if no_align is None else not no_align, "align_checkpoints", True),
        tensorboard=choose(None if no_tensorboard is None else not no_tensorboard, "tensorboard", True),
        hyperparams=None if uses_conf else zoo_hyperparameters(algo),
    )


def train(argv: Sequence[str]) -> None:
    """``train``: rl-zoo's train with the launcher's additions (see the module docstring)."""
    ours, zoo_argv = _launcher_parser().parse_known_args(list(argv))
    asks_help = has_flag(zoo_argv, "-h", "--help")
    if asks_help:
        print(LAUNCHER_HELP)
    if ours.resume:  # --resume RUN_DIR: the run's own algorithm and env unless given
        info = run_info.read_run_info(ours.resume) or {}
        if not info:
            raise SystemExit(
                f"--resume {ours.resume}: not a run folder (no {run_info.RUN_INFO_FILE}); give <log folder>/<algo>/"
                "<env>_<id>, or --algo and --env without a folder to resume the latest run in -f."
            )
        for flag, key in (("--algo", "algo"), ("--env", "env_id")):
            if not has_flag(zoo_argv, flag) and key in info:
                zoo_argv += [flag, str(info[key])]
    algo = flag_value(zoo_argv, "--algo") or "ppo"
    env_id = flag_value(zoo_argv, "--env")
    if env_id is None and not asks_help:
        raise SystemExit(f"--env is required: {benchmark_help()}")
    if env_id is not None and not register_env_id(env_id):
        raise SystemExit(f"{env_id!r} is not a benchmark of sb3_mtte: {benchmark_help()}")
    register_algos()
    resume_dir, saved = (None, {}) if ours.resume is None else _resume_run(ours.resume, zoo_argv, algo, env_id)
    if not ours.no_progress and not has_flag(zoo_argv, "-P", "--progress"):
        zoo_argv.append("-P")
    launch = _launch_options(ours, zoo_argv, algo, saved)
    missing = None if resume_dir or launch.hyperparams is None else missing_entries_message(algo, [env_id])
    if missing and not asks_help:
        raise SystemExit(missing)
    launch.resume_dir = resume_dir
    run_zoo_train(zoo_argv, launch)


def run_zoo_train(zoo_argv: list[str], launch: LaunchOptions) -> None:
    """Run rl-zoo's ``train()`` on ``zoo_argv`` with :class:`MultiTaskExperimentManager` as its manager.

    rl-zoo's ``train()`` parses ``sys.argv`` and builds its ``ExperimentManager`` itself; both are swapped for
    the time of the call.
    """

    def make_manager(*args: Any, **kwargs: Any) -> MultiTaskExperimentManager:
        return MultiTaskExperimentManager(*args, launch=launch, **kwargs)

    with (
        patched(sys, "argv", [f"{sys.argv[0]} train", *zoo_argv]),
        patched(rl_zoo3.train, "ExperimentManager", make_manager),
    ):
        rl_zoo3.train.train()


@contextlib.contextmanager
def patched(obj: Any, name: str, value: Any) -> Iterator[None]:
    """Set ``obj.name`` to ``value`` for the time of a ``with`` block."""
    old = getattr(obj, name)
    setattr(obj, name, value)
    try:
        yield
    finally:
        setattr(obj, name, old)


__all__ = ["flag_value", "has_flag", "latest_run_dir", "patched", "register_algos", "run_zoo_train", "train"]
