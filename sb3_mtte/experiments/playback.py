"""``enjoy`` (rl-zoo's, one sub-env per task, every episode printed) and ``record_video`` (one video per task)."""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import rl_zoo3.enjoy
import yaml
from huggingface_sb3 import EnvironmentName
from rl_zoo3.exp_manager import ExperimentManager
from rl_zoo3.utils import StoreDict, get_latest_run_id, get_model_path
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.vec_env import VecEnv
from stable_baselines3.common.vec_env.base_vec_env import tile_images

from sb3_mtte.common.utils import get_task_names, short_task_name
from sb3_mtte.envs import make_mt_env
from sb3_mtte.experiments import run_info
from sb3_mtte.experiments.checkpoints import load_model
from sb3_mtte.experiments.env_ids import (
    MultiTaskVecEnvFactory,
    benchmark_help,
    env_id_n_tasks,
    register_env_id,
    split_env_id,
)
from sb3_mtte.experiments.launcher import flag_value, has_flag, patched, register_algos


def locate_model(args: argparse.Namespace) -> tuple[str, str, str]:
    """(name_prefix, model_path, log_path) of the model an enjoy/record_video command names (rl-zoo's rules); a
    missing run or model exits with one line."""
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
        env_name = EnvironmentName(args.env)
        exp_id = args.exp_id or get_latest_run_id(os.path.join(args.folder, args.algo), env_name)
        run_dir = Path(args.folder) / args.algo / f"{env_name}_{exp_id}"
        models = " ".join(sorted(path.name for path in run_dir.glob("*.zip"))) or "none"
        raise SystemExit(
            f"{error}: load one of the models of {run_dir} ({models}) with --load-best, --load-checkpoint STEPS or "
            "--load-last-checkpoint, or none of them for the final model."
        ) from None


def _model_parser(prog: str) -> argparse.ArgumentParser:
    """The options that name a trained model (rl-zoo's names)."""
    parser = argparse.ArgumentParser(prog=prog, add_help=False)
    parser.add_argument("--env", required=True, help="env id of the run (MT10, MT10-smoke, toy-conflict, ...)")
    parser.add_argument("-f", "--folder", default="logs", help="log folder")
    parser.add_argument("--algo", default="mtsacte", help="zoo algorithm key")
    parser.add_argument("--exp-id", type=int, default=0, help="run id (0: latest)")
    parser.add_argument("--load-best", action="store_true")
    parser.add_argument("--load-checkpoint", type=int, default=None)
    parser.add_argument("--load-last-checkpoint", action="store_true")
    return parser


def enjoy(argv: Sequence[str]) -> None:
    """``enjoy``: rl-zoo's enjoy with one sub-env per task (``--n-envs`` is set to the task count)."""
    argv = list(argv)
    env_id = flag_value(argv, "--env")
    register_algos()  # before rl-zoo's parser lists its --algo choices
    if has_flag(argv, "-h", "--help"):
        _run_zoo_enjoy(argv, MultiTaskVecEnvFactory(1))
    if env_id is None or not register_env_id(env_id):
        raise SystemExit(f"--env must be a benchmark of sb3_mtte: {benchmark_help()}")
    if not has_flag(argv, "-f", "--folder"):
        argv += ["-f", "logs"]
    n_tasks = env_id_n_tasks(env_id)
    n_envs = flag_value(argv, "--n-envs")
    if n_envs is not None and n_envs != str(n_tasks):
        raise SystemExit(f"{env_id} has {n_tasks} tasks: --n-envs must be {n_tasks} (one sub-env per task).")
    if n_envs is None:
        argv += ["--n-envs", str(n_tasks)]
    args = _model_parser("enjoy").parse_known_args(argv)[0]
    if args.exp_id == 0:  # resolved here, so that rl-zoo's enjoy does not report it a second time
        args.exp_id = get_latest_run_id(os.path.join(args.folder, args.algo), EnvironmentName(env_id))
        print(f"Loading latest experiment, id={args.exp_id}")
        argv += ["--exp-id", str(args.exp_id)]
    _, _, log_path = locate_model(args)
    info = run_info.read_run_info(log_path) or {}
    factory = MultiTaskVecEnvFactory(n_tasks, seed=int(info.get("benchmark_seed", 0)), report_episodes=True)
    _run_zoo_enjoy(argv, factory)


def _run_zoo_enjoy(argv: list[str], factory: MultiTaskVecEnvFactory) -> None:
    """Run rl-zoo's ``enjoy()``, which parses ``sys.argv`` and builds its envs with ``default_vec_env_cls``."""
    with (
        patched(sys, "argv", [f"{sys.argv[0]} enjoy", *argv]),
        patched(ExperimentManager, "default_vec_env_cls", factory),
    ):
        rl_zoo3.enjoy.enjoy()


def _record_video_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="sb3-mtte record_video", parents=[_model_parser("record_video")])
    parser.add_argument("-o", "--output-folder", default=None, help="video folder (default: <run>/videos)")
    parser.add_argument("-n", "--n-timesteps", type=int, default=None, help="max vector steps (default: as needed)")
    parser.add_argument("--episodes", type=int, default=1, help="episodes recorded per task")
    parser.add_argument("--stochastic", action="store_true", help="sample actions (default: deterministic)")
    parser.add_argument("--seed", type=int, default=None, help="benchmark seed (default: the run's)")
    parser.add_argument("--env-kwargs", type=str, nargs="+", default=None, help="key:value env keyword arguments")
    parser.add_argument("--device", default="auto")
    parser.add_argument("--fps", type=int, default=None)
    parser.add_argument("--tile", action="store_true", help="also write one video of all tasks side by side")
    parser.add_argument("--flip", action="store_true", help="flip frames vertically (Meta-World's corner cameras)")
    return parser


def record_video(argv: Sequence[str]) -> list[Path]:
    """``record_video``: one video per task (and optionally a tiled one) of a trained model.

    Meta-World renders with MuJoCo: headless machines need ``MUJOCO_GL=egl`` (set by default when there is no
    display) or ``osmesa``.

    :return: the written video paths.
    """
    parser = _record_video_parser()
    args = parser.parse_args(list(argv))
    if not os.environ.get("DISPLAY") and "MUJOCO_GL" not in os.environ:
        os.environ["MUJOCO_GL"] = "egl"
    if not register_env_id(args.env):
        raise SystemExit(f"--env must be a benchmark of sb3_mtte: {benchmark_help()}")
    register_algos()
    name_prefix, model_path, log_path = locate_model(args)
    info = run_info.read_run_info(log_path) or {}
    seed = args.seed if args.seed is not None else int(info.get("benchmark_seed", 0))
    env_kwargs = _saved_env_kwargs(log_path, args.env)
    if args.env_kwargs:
        namespace = argparse.Namespace()
        StoreDict(["--env-kwargs"], "env_kwargs")(parser, namespace, args.env_kwargs)
        env_kwargs.update(namespace.env_kwargs)
    env_kwargs["render_mode"] = "rgb_array"
    env = make_mt_env(split_env_id(args.env)[0], seed=seed, **env_kwargs)
    try:
        model = load_model(model_path, device=args.device)
        frames, tiled = _collect_frames(model, env, args)
        fps = args.fps or int((env.metadata or {}).get("render_fps", 0) or 30)
        out_dir = Path(args.output_folder or os.path.join(log_path, "videos"))
        return _write_videos(frames, tiled, out_dir, name_prefix, get_task_names(env), fps)
    finally:
        env.close()


def _collect_frames(
    model: BaseAlgorithm, env: VecEnv, args: argparse.Namespace
) -> tuple[list[list[np.ndarray]], list[np.ndarray]]:
    """Frames of ``args.episodes`` episodes per task, and the tiled frames of all tasks (``args.tile``)."""
    n_tasks = env.num_envs
    if env.has_attr("set_eval_mode"):
        env.env_method("set_eval_mode", True)
    frames: list[list[np.ndarray]] = [[] for _ in range(n_tasks)]
    tiled: list[np.ndarray] = []
    episodes = np.zeros(n_tasks, dtype=int)
    obs = env.reset()
    steps = 0
    while (episodes < args.episodes).any() and (args.n_timesteps is None or steps < args.n_timesteps):
        images = env.get_images()
        if any(image is None for image in images):
            raise RuntimeError("The env returned no image: it cannot render in rgb_array mode here.")
        if args.flip:
            images = [image[::-1] for image in images]
        for i in np.flatnonzero(episodes < args.episodes):
            frames[i].append(images[i])
        if args.tile:
            tiled.append(tile_images(images))
        actions, _ = model.predict(obs, deterministic=not args.stochastic)
        obs, _, dones, _ = env.step(actions)
        episodes += dones.astype(int)
        steps += 1
    return frames, tiled


def _write_videos(
    frames: list[list[np.ndarray]], tiled: list[np.ndarray], out_dir: Path, prefix: str, names: list[str], fps: int
) -> list[Path]:
    """Write one mp4 per task with frames (and the tiled one) and return their paths."""
    from moviepy.video.io.ImageSequenceClip import ImageSequenceClip  # loads ffmpeg: only when writing videos

    out_dir.mkdir(parents=True, exist_ok=True)
    videos = {out_dir / f"{prefix}-{i:02d}_{short_task_name(names[i])}.mp4": f for i, f in enumerate(frames) if f}
    if tiled:
        videos[out_dir / f"{prefix}-all_tasks.mp4"] = tiled
    for path, clip_frames in videos.items():
        clip = ImageSequenceClip(list(clip_frames), fps=fps)
        clip.write_videofile(str(path), logger=None)
        clip.close()
        print(f"Saved {path}")
    return list(videos)


def _saved_env_kwargs(log_path: str, env_id: str) -> dict[str, Any]:
    """``env_kwargs`` a run was trained with (its ``args.yml``), as rl-zoo's enjoy reads them."""
    path = Path(log_path) / EnvironmentName(env_id) / "args.yml"
    if not path.is_file():
        return {}
    with open(path) as file:
        loaded = yaml.load(file, Loader=yaml.UnsafeLoader)
    return dict(loaded.get("env_kwargs") or {})


__all__ = ["enjoy", "locate_model", "record_video"]
