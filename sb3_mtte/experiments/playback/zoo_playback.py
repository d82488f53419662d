"""``enjoy`` (rl-zoo's, one sub-env per task, every episode printed) and ``record_video`` (one video per task)."""

from __future__ import annotations

import argparse
import functools
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import yaml
from huggingface_sb3 import EnvironmentName
from rl_zoo3.utils import get_model_path

from sb3_mtte.common.checkpoints import incomplete_checkpoint_error
from sb3_mtte.envs import check_env_kwargs, make_env_fns, make_mt_env
from sb3_mtte.experiments import run_info
from sb3_mtte.experiments.cli import CommandParser, command_prog, device_error, output_folder_error
from sb3_mtte.experiments.env_ids import (
    MultiTaskVecEnvFactory,
    benchmark_help,
    env_id_n_tasks,
    register_env_id,
    split_env_id,
)
from sb3_mtte.experiments.playback.episode_reporter import EpisodeReporter
from sb3_mtte.experiments.playback.video import record_task_videos, record_tiled_video
from sb3_mtte.experiments.zoo.adapter import run_enjoy
from sb3_mtte.experiments.zoo.launcher import flag_value, has_flag, register_algos
from sb3_mtte.experiments.zoo.parsers import ENJOY_DESCRIPTION, CheckedStoreDict, ZooParser
from sb3_mtte.experiments.zoo.run_checkpoints import latest_run_with_model, load_model


def _latest_run_id(args: argparse.Namespace) -> int:
    """The id of the latest run of ``args.algo`` on ``args.env`` under ``args.folder`` that holds a model, announced
    as rl-zoo does; exits with one line when there is none."""
    env_name = EnvironmentName(args.env)
    run_dir = latest_run_with_model(args.folder, args.algo, str(env_name))
    exp_id = 0 if run_dir is None else int(run_dir.name.rsplit("_", 1)[1])
    if exp_id == 0:
        raise SystemExit(
            f"No run folder {os.path.join(args.folder, args.algo, f'{env_name}_<id>')}: give -f, --algo, --env "
            "(and --exp-id) of a trained run."
        )
    print(f"Loading latest experiment, id={exp_id}")
    return exp_id


def locate_model(args: argparse.Namespace) -> tuple[str, str, str]:
    """(name_prefix, model_path, log_path) of the model an enjoy/record_video command names (rl-zoo's rules, with
    ``args.exp_id`` 0 set to the latest run's id); a missing run or model exits with one line."""
    if args.exp_id == 0:
        args.exp_id = _latest_run_id(args)
    located = _model_path(args)
    problem = incomplete_checkpoint_error(located[1])
    if problem is not None:
        raise SystemExit(problem)
    return located


def _model_path(args: argparse.Namespace) -> tuple[str, str, str]:
    try:
        return get_model_path(
            args.exp_id,
            args.folder,
            args.algo,
            EnvironmentName(args.env),
            args.load_best,
            args.load_checkpoint,
            args.load_last_checkpoint,
        )
    except AssertionError as error:  # rl-zoo's report of a missing run folder
        raise SystemExit(f"{error}: give -f, --algo, --env (and --exp-id) of a trained run.") from None
    except ValueError as error:  # the run folder exists, the model asked for does not
        run_dir = Path(args.folder) / args.algo / f"{EnvironmentName(args.env)}_{args.exp_id}"
        models = " ".join(sorted(path.name for path in run_dir.glob("*.zip"))) or "none"
        raise SystemExit(
            f"{error}: load one of the models of {run_dir} ({models}) with --load-best, --load-checkpoint STEPS or "
            "--load-last-checkpoint, or none of them for the final model."
        ) from None


def _model_parser(prog: str) -> argparse.ArgumentParser:
    """The options that name a trained model (rl-zoo's names)."""
    parser = CommandParser(prog=prog, add_help=False)
    parser.add_argument("--env", required=True, help="env id of the run (MT10, MT10-smoke, toy-conflict, ...)")
    parser.add_argument("-f", "--folder", default="logs", help="log folder")
    parser.add_argument("--algo", default="mtsacte", help="zoo algorithm key")
    parser.add_argument("--exp-id", type=int, default=0, help="run id (0: latest)")
    parser.add_argument("--load-best", action="store_true", help="load best_model.zip (highest mean success)")
    parser.add_argument(
        "--load-checkpoint",
        type=int,
        default=None,
        metavar="STEPS",
        help="load the checkpoint taken at STEPS env steps (rl_model_STEPS_steps.zip)",
    )
    parser.add_argument("--load-last-checkpoint", action="store_true", help="load the run's latest checkpoint")
    return parser


def enjoy(argv: Sequence[str]) -> None:
    """``enjoy``: rl-zoo's enjoy with one sub-env per task (``--n-envs`` is set to the task count)."""
    argv = list(argv)
    env_id = flag_value(argv, "--env")
    register_algos()  # before rl-zoo's parser lists its --algo choices
    if has_flag(argv, "-h", "--help"):
        _run_zoo_enjoy(argv, MultiTaskVecEnvFactory(1))
    if env_id is None or not register_env_id(env_id):
        raise SystemExit(f"--env must be a benchmark of sb3_mtte: {benchmark_help(env_id)}")
    problem = device_error("--device", flag_value(argv, "--device"))
    if problem:
        raise SystemExit(problem)
    steps = flag_value(argv, "-n", "--n-timesteps")
    if steps is not None and not (steps.isdigit() and int(steps) >= 1):
        raise SystemExit(f"-n {steps}: give 1 or more vector steps (each steps every task once).")
    if not has_flag(argv, "-f", "--folder"):
        argv += ["-f", "logs"]
    n_tasks = env_id_n_tasks(env_id)
    n_envs = flag_value(argv, "--n-envs")
    if n_envs is not None and n_envs != str(n_tasks):
        raise SystemExit(f"{env_id} has {n_tasks} tasks: --n-envs must be {n_tasks} (one sub-env per task).")
    if n_envs is None:
        argv += ["--n-envs", str(n_tasks)]
    args = _model_parser("enjoy").parse_known_args(argv)[0]
    _, _, log_path = locate_model(args)
    if not has_flag(argv, "--no-render") and sys.platform == "linux" and not os.environ.get("DISPLAY"):
        raise SystemExit(
            "enjoy renders in a window and this machine has no display: add --no-render, or write videos with "
            "sb3-mtte record_video."
        )
    argv += ["--exp-id", str(args.exp_id)]  # resolved, so that rl-zoo's enjoy does not report it a second time
    info = run_info.read_run_info(log_path) or {}
    factory = MultiTaskVecEnvFactory(n_tasks, seed=int(info.get("benchmark_seed", 0)), wrapper=EpisodeReporter)
    _run_zoo_enjoy(argv, factory)


ENJOY_STEPS_HELP = (
    "vector steps: each steps every task once, so N tasks take N env steps (train's -n counts env steps over all "
    "tasks; default 1000)"
)


class EnjoyParser(ZooParser):
    """rl-zoo's enjoy parser as :class:`~sb3_mtte.experiments.zoo.parsers.ZooParser` shows it, its ``-n`` described
    in vector steps (rl-zoo's enjoy loop), apart from ``train``'s env steps over all tasks."""

    def add_argument(self, *names: Any, **kwargs: Any) -> argparse.Action:
        if "-n" in names:
            kwargs["help"] = ENJOY_STEPS_HELP
        return super().add_argument(*names, **kwargs)


def _run_zoo_enjoy(argv: list[str], factory: MultiTaskVecEnvFactory) -> None:
    """Run rl-zoo's ``enjoy()`` with its envs built by ``factory``, and a parser that shows what it does and the
    package's zoo keys."""
    make_parser = functools.partial(EnjoyParser, prog=command_prog("enjoy"), description=ENJOY_DESCRIPTION)
    run_enjoy(argv, factory, make_parser)


def _record_video_parser() -> argparse.ArgumentParser:
    prog = command_prog("record_video")
    parser = CommandParser(prog=prog, parents=[_model_parser("record_video")])
    parser.add_argument("-o", "--output-folder", default=None, help="video folder (default: <run>/videos)")
    parser.add_argument("-n", "--n-timesteps", type=int, default=None, help="max steps per video (default: as needed)")
    parser.add_argument("--episodes", type=int, default=1, help="episodes recorded per task (default 1)")
    parser.add_argument("--width", type=int, default=None, help="frame width in pixels (Meta-World; default 480)")
    parser.add_argument("--height", type=int, default=None, help="frame height in pixels (Meta-World; default 480)")
    parser.add_argument("--stochastic", action="store_true", help="sample actions (default: deterministic)")
    parser.add_argument("--seed", type=int, default=None, help="benchmark seed (default: the run's)")
    parser.add_argument("--env-kwargs", type=str, nargs="+", default=None, help="key:value env keyword arguments")
    parser.add_argument("--device", default="auto", help="torch device of the model: auto, cpu, cuda (default auto)")
    parser.add_argument(
        "--fps", type=int, default=None, help="frames per second of the videos (default: the env's render_fps, else 30)"
    )
    parser.add_argument("--tile", action="store_true", help="also write one video of all tasks side by side")
    parser.add_argument("--flip", action="store_true", help="flip frames vertically (Meta-World's corner cameras)")
    return parser


def record_video(argv: Sequence[str]) -> list[Path]:
    """``record_video``: one video per task (and optionally a tiled one) of a trained model, each task filmed and
    written before the next (:mod:`sb3_mtte.experiments.playback.video`).

    Meta-World renders with MuJoCo: headless machines need ``MUJOCO_GL=egl`` (set by default when there is no
    display) or ``osmesa``.

    :return: the written video paths.
    """
    parser = _record_video_parser()
    args = parser.parse_args(list(argv))
    if not os.environ.get("DISPLAY") and "MUJOCO_GL" not in os.environ:
        os.environ["MUJOCO_GL"] = "egl"
    if not register_env_id(args.env):
        raise SystemExit(f"--env must be a benchmark of sb3_mtte: {benchmark_help(args.env)}")
    problem = device_error("--device", args.device)
    if problem:
        raise SystemExit(problem)
    counts = (
        ("--episodes", args.episodes),
        ("-n", args.n_timesteps),
        ("--width", args.width),
        ("--height", args.height),
        ("--fps", args.fps),
    )
    too_few = [f"{flag} {n}" for flag, n in counts if n is not None and n < 1]
    if too_few:
        raise SystemExit(
            f"{' and '.join(too_few)}: give at least 1 (episodes per task, steps per video, pixels, frames per second)."
        )
    register_algos()
    name_prefix, model_path, log_path = locate_model(args)
    info = run_info.read_run_info(log_path) or {}
    seed = args.seed if args.seed is not None else int(info.get("benchmark_seed", 0))
    env_kwargs = _saved_env_kwargs(log_path, args.env)
    if args.env_kwargs:
        namespace = argparse.Namespace()
        CheckedStoreDict(["--env-kwargs"], "env_kwargs")(parser, namespace, args.env_kwargs, "--env-kwargs")
        env_kwargs.update(namespace.env_kwargs)
    env_kwargs.update({key: getattr(args, key) for key in ("width", "height") if getattr(args, key) is not None})
    env_kwargs["render_mode"] = "rgb_array"
    benchmark = split_env_id(args.env)[0]
    try:
        check_env_kwargs(benchmark, env_kwargs)
    except (TypeError, ValueError) as error:
        raise SystemExit(f"{error} (--width and --height: Meta-World only)") from None
    model = load_model(model_path, device=args.device)
    out_dir = Path(args.output_folder or os.path.join(log_path, "videos"))
    out_error = output_folder_error("-o", out_dir)
    if out_error:
        raise SystemExit(out_error)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = record_task_videos(model, make_env_fns(benchmark, seed=seed, **env_kwargs), args, out_dir, name_prefix)
    if args.tile:
        env = make_mt_env(benchmark, seed=seed, **env_kwargs)
        try:
            written += record_tiled_video(model, env, args, out_dir / f"{name_prefix}-all_tasks.mp4")
        finally:
            env.close()
    return written


def _saved_env_kwargs(log_path: str, env_id: str) -> dict[str, Any]:
    """``env_kwargs`` a run was trained with (its ``args.yml``), as rl-zoo's enjoy reads them."""
    path = Path(log_path) / EnvironmentName(env_id) / "args.yml"
    if not path.is_file():
        return {}
    with open(path) as file:
        loaded = yaml.load(file, Loader=yaml.UnsafeLoader)
    return dict(loaded.get("env_kwargs") or {})


__all__ = ["EnjoyParser", "enjoy", "locate_model", "record_video"]
