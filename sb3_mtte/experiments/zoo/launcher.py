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
from sb3_mtte.experiments.cli import CommandParser, command_prog, device_error, output_folder_error
from sb3_mtte.experiments.env_ids import benchmark_help, default_vec_env, env_id_n_tasks, register_env_id
from sb3_mtte.experiments.variants import algo_classes, convert_trial_params, family_of
from sb3_mtte.experiments.zoo import adapter
from sb3_mtte.experiments.zoo.configs import missing_entries_message, zoo_hyperparameters
from sb3_mtte.experiments.zoo.manager import LaunchOptions, MultiTaskExperimentManager
from sb3_mtte.experiments.zoo.parsers import TRAIN_DESCRIPTION, add_launcher_options, zoo_parser
from sb3_mtte.experiments.zoo.resume import NothingToDo
from sb3_mtte.experiments.zoo.run_checkpoints import latest_run_with_model
from sb3_mtte.experiments.zoo.run_settings import given_settings, has_flag, resume_refusal


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
    parser = CommandParser(prog="sb3-mtte train", add_help=False)
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


def check_task_count(algo: str, env_id: str) -> None:
    """Refuse a benchmark of fewer tasks than ``algo`` compares (MTSACTE's Eq. 7 needs 1 <= M < N), in one line."""
    min_tasks = getattr(algo_classes()[algo], "min_tasks", 1)
    n_tasks = env_id_n_tasks(env_id)
    if n_tasks < min_tasks:
        raise SystemExit(
            f"{algo} needs at least {min_tasks} tasks, and {env_id} has {n_tasks}: give a benchmark of {min_tasks} "
            "tasks or more, or an MTSAC key (mtsac_mt)."
        )


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


def check_output_folders(zoo_argv: Sequence[str], resume_dir: str | None) -> None:
    """Refuse a log folder (``-f``), tensorboard folder (``-tb``) or run folder to resume that cannot be made and
    written (a file on the way, no permission), in one line, before any env is built."""
    folders = [("-f", flag_value(zoo_argv, "-f", "--log-folder") or "logs")]
    folders.append(("-tb", flag_value(zoo_argv, "-tb", "--tensorboard-log") or ""))
    folders.append(("--resume", resume_dir or ""))
    for flag, folder in folders:
        problem = output_folder_error(flag, folder) if folder else None
        if problem:
            raise SystemExit(problem)


def _resume_run(resume: str, zoo_argv: list[str], algo: str, env_id: str | None) -> tuple[str, dict[str, Any]]:
    """The run folder to resume and its progress-bar setting; adds the run's seed and log folder to
    ``zoo_argv``."""
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
    return str(resume_dir), {"progress": (info.get("zoo_args") or {}).get("progress", True)}


def _launch_options(
    ours: argparse.Namespace, zoo_argv: list[str], algo: str, env_id: str, given: frozenset[str]
) -> LaunchOptions:
    """Launcher options from the command line, else the defaults (a resumed run's own:
    :meth:`~sb3_mtte.experiments.zoo.resume.RunFolderSettings.restore_run_settings`)."""
    uses_conf = has_flag(zoo_argv, "-conf", "--conf-file")
    return LaunchOptions(
        exp_id=ours.exp_id,
        flags_given=given,
        keep_buffers=1 if ours.keep_buffers is None else ours.keep_buffers,
        align_checkpoints=not ours.no_align_checkpoints,
        tensorboard=not ours.no_tensorboard,
        hyperparams=None if uses_conf else zoo_hyperparameters(algo, [env_id]),
    )


def train(argv: Sequence[str]) -> None:
    """``train``: rl-zoo's train with the launcher's additions (see the module docstring)."""
    given = given_settings(argv)  # before the launcher adds flags of its own
    ours, zoo_argv = _launcher_parser().parse_known_args(list(argv))
    if has_flag(zoo_argv, "-h", "--help"):  # rl-zoo's parser prints the help and exits
        run_zoo_train(zoo_argv, LaunchOptions())
        return
    refusal = resume_refusal(zoo_argv) if ours.resume is not None else None
    if refusal:
        raise SystemExit(refusal)
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
    check_task_count(algo, env_id)
    check_budget(zoo_argv)
    check_conf_file(zoo_argv)
    problem = device_error("--device", flag_value(zoo_argv, "--device"))
    if problem:
        raise SystemExit(problem)
    register_algos()
    resume_dir, saved = (None, {}) if ours.resume is None else _resume_run(ours.resume, zoo_argv, algo, env_id)
    check_output_folders(zoo_argv, resume_dir)
    if ours.resume is None and not has_flag(zoo_argv, "--vec-env"):  # a resumed run keeps its own (args.yml)
        zoo_argv += ["--vec-env", default_vec_env(env_id)]
    if not ours.no_progress and saved.get("progress", True) and not has_flag(zoo_argv, "-P", "--progress"):
        zoo_argv.append("-P")  # a resumed run keeps its own setting
    launch = _launch_options(ours, zoo_argv, algo, env_id, given)
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
    try:
        adapter.run_train(zoo_argv, make_manager, parser)
    except NothingToDo as done:  # the run folder already holds what the command asks for
        print(done)


__all__ = [
    "check_algo",
    "check_budget",
    "check_conf_file",
    "check_output_folders",
    "check_task_count",
    "flag_value",
    "has_flag",
    "latest_run_dir",
    "register_algos",
    "run_zoo_train",
    "train",
]
