"""``train``: rl-zoo3's train with one sub-env per task, the variants' hyperparameters and resumable runs.

Launcher options of ``train`` (besides rl-zoo's): :func:`~sb3_mtte.experiments.zoo.parsers.add_launcher_options`.
Without ``-conf``, the hyperparameters of ``--algo`` are its family's file plus its overrides
(:mod:`sb3_mtte.experiments.zoo.configs`). ``--algo`` takes the package's zoo keys only.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import rl_zoo3
from huggingface_sb3 import EnvironmentName
from rl_zoo3 import hyperparams_opt

from sb3_mtte.common.utils import did_you_mean
from sb3_mtte.experiments import run_info
from sb3_mtte.experiments.cli import command_prog, device_error
from sb3_mtte.experiments.env_ids import benchmark_help, default_vec_env, register_env_id
from sb3_mtte.experiments.variants import algo_classes, convert_trial_params, family_of
from sb3_mtte.experiments.zoo import adapter
from sb3_mtte.experiments.zoo.configs import missing_entries_message, zoo_hyperparameters
from sb3_mtte.experiments.zoo.manager import LaunchOptions, MultiTaskExperimentManager
from sb3_mtte.experiments.zoo.parsers import TRAIN_DESCRIPTION, add_launcher_options, zoo_parser
from sb3_mtte.experiments.zoo.run_checkpoints import latest_run_with_model

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
    """The latest run folder ``<log_folder>/<algo>/<env>_<id>`` that holds a model or checkpoint (else a started
    run: :func:`~sb3_mtte.experiments.zoo.run_checkpoints.latest_run_with_model`)."""
    run_dir = latest_run_with_model(log_folder, algo, str(EnvironmentName(env_id)))
    if run_dir is None:
        raise SystemExit(
            f"No run of {algo} on {env_id} in {log_folder}/{algo}/ to resume: give -f of your runs, or --resume "
            "RUN_DIR."
        )
    return run_dir


def _launcher_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="sb3-mtte train", add_help=False)
    add_launcher_options(parser)
    return parser


def check_algo(algo: str | None) -> str:
    """``algo``; a missing ``--algo`` or one that is no zoo key of the package ends with one line naming the keys."""
    keys = list(algo_classes())
    if algo is None:
        raise SystemExit(f"--algo is required: one of {' '.join(keys)}.")
    if algo not in keys:
        hint = did_you_mean(algo, keys)
        raise SystemExit(
            f"--algo {algo} is not an algorithm of sb3_mtte: {hint + ' ' if hint else ''}one of {' '.join(keys)}."
        )
    return algo


def check_budget(zoo_argv: Sequence[str]) -> None:
    """Refuse ``-n`` of no env step (rl-zoo reads ``-n 0`` or below as the file's ``n_timesteps``)."""
    value = flag_value(zoo_argv, "-n", "--n-timesteps")
    if value is not None and value.lstrip("-").isdigit() and int(value) <= 0:
        raise SystemExit(
            f"-n {value}: n must be a positive number of env steps (over all tasks), e.g. -n 10000; without -n the "
            "hyperparameters' n_timesteps is trained."
        )


def check_conf_file(zoo_argv: Sequence[str]) -> None:
    """Refuse a ``-conf`` that is neither a file nor an importable module (rl-zoo's two kinds)."""
    conf = flag_value(zoo_argv, "-conf", "--conf-file")
    if conf is None or Path(conf).is_file():
        return
    if not conf.endswith((".yml", ".yaml", ".py")):
        with contextlib.suppress(ImportError, ValueError):
            if importlib.util.find_spec(conf) is not None:
                return
    raise SystemExit(
        f"-conf {conf}: no such file; give a hyperparameter file (.yml with one entry per env id, as rl-zoo's) or "
        "a Python module with a hyperparams dict."
    )


def _resume_run(resume: str, zoo_argv: list[str], algo: str, env_id: str | None) -> tuple[str, dict[str, Any]]:
    """The run folder to resume and its saved launcher options (progress bar included); adds the run's seed and log
    folder to ``zoo_argv``."""
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
    saved = dict(info.get("launcher") or {})
    saved["progress"] = (info.get("zoo_args") or {}).get("progress", True)
    return str(resume_dir), saved


def _launch_options(
    ours: argparse.Namespace, zoo_argv: list[str], algo: str, env_id: str, saved: dict[str, Any]
) -> LaunchOptions:
    """Launcher options from the command line, else the resumed run's, else the defaults."""

    def choose(given: Any, key: str, default: Any) -> Any:
        return given if given is not None else saved.get(key, default)

    no_align, no_tensorboard = ours.no_align_checkpoints, ours.no_tensorboard
    uses_conf = has_flag(zoo_argv, "-conf", "--conf-file")
    return LaunchOptions(
        exp_id=ours.exp_id,
        flags_given=frozenset(dest for dest, names in TRACKED_FLAGS.items() if has_flag(zoo_argv, *names)),
        keep_buffers=choose(ours.keep_buffers, "keep_buffers", 1),
        align_checkpoints=choose(None if no_align is None else not no_align, "align_checkpoints", True),
        tensorboard=choose(None if no_tensorboard is None else not no_tensorboard, "tensorboard", True),
        hyperparams=None if uses_conf else zoo_hyperparameters(algo, [env_id]),
    )


def train(argv: Sequence[str]) -> None:
    """``train``: rl-zoo's train with the launcher's additions (see the module docstring)."""
    ours, zoo_argv = _launcher_parser().parse_known_args(list(argv))
    if has_flag(zoo_argv, "-h", "--help"):  # rl-zoo's parser prints the help and exits
        run_zoo_train(zoo_argv, LaunchOptions())
        return
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
    env_id = flag_value(zoo_argv, "--env")
    if env_id is None:
        raise SystemExit(f"--env is required: {benchmark_help()}")
    if not register_env_id(env_id):
        raise SystemExit(f"{env_id!r} is not a benchmark of sb3_mtte: {benchmark_help(env_id)}")
    algo = check_algo(flag_value(zoo_argv, "--algo"))
    check_budget(zoo_argv)
    check_conf_file(zoo_argv)
    problem = device_error("--device", flag_value(zoo_argv, "--device"))
    if problem:
        raise SystemExit(problem)
    register_algos()
    resume_dir, saved = (None, {}) if ours.resume is None else _resume_run(ours.resume, zoo_argv, algo, env_id)
    if ours.resume is None and not has_flag(zoo_argv, "--vec-env"):  # a resumed run keeps its own (args.yml)
        zoo_argv += ["--vec-env", default_vec_env(env_id)]
    if not ours.no_progress and saved.get("progress", True) and not has_flag(zoo_argv, "-P", "--progress"):
        zoo_argv.append("-P")  # a resumed run keeps its own setting
    launch = _launch_options(ours, zoo_argv, algo, env_id, saved)
    missing = None if resume_dir or launch.hyperparams is None else missing_entries_message(algo, [env_id])
    if missing:
        raise SystemExit(missing)
    launch.resume_dir = resume_dir
    run_zoo_train(zoo_argv, launch)


def run_zoo_train(zoo_argv: list[str], launch: LaunchOptions) -> None:
    """Run rl-zoo's ``train()`` on ``zoo_argv``, with :class:`MultiTaskExperimentManager` as its manager and the
    package's parser (:func:`~sb3_mtte.experiments.zoo.adapter.run_train`)."""

    def make_manager(*args: Any, **kwargs: Any) -> MultiTaskExperimentManager:
        return MultiTaskExperimentManager(*args, launch=launch, **kwargs)

    parser = zoo_parser(TRAIN_DESCRIPTION, launcher_options=True, prog=command_prog("train"))
    adapter.run_train(zoo_argv, make_manager, parser)


__all__ = [
    "check_algo",
    "check_budget",
    "check_conf_file",
    "flag_value",
    "has_flag",
    "latest_run_dir",
    "register_algos",
    "run_zoo_train",
    "train",
]
