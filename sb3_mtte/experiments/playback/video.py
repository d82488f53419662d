"""The videos of ``record_video``, streamed: one task at a time, every frame written to its file as it is drawn.

Task i's video is complete before task i+1's env is built, so memory does not grow with the number of tasks or
of frames; the tiled video (all tasks side by side) runs every task at once and streams its frames the same way.
Each video shows a progress bar of its frames.
"""

from __future__ import annotations

import argparse
import contextlib
import os
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path

import gymnasium as gym
import numpy as np
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.vec_env import VecEnv
from stable_baselines3.common.vec_env.base_vec_env import tile_images
from tqdm import tqdm

from sb3_mtte.common.utils import short_task_name

DEFAULT_FPS = 30


def _frame(image: np.ndarray | None, flip: bool) -> np.ndarray:
    if image is None:
        raise RuntimeError("The env returned no image: it cannot render in rgb_array mode here.")
    image = np.asarray(image, dtype=np.uint8)
    return image[::-1] if flip else image


def task_frames(model: BaseAlgorithm, env: gym.Env, args: argparse.Namespace) -> Iterator[np.ndarray]:
    """Frames of ``args.episodes`` episodes of one task's env (at most ``args.n_timesteps`` steps), each drawn
    before the action chosen from the same state, with the goal variations in evaluation order."""
    with contextlib.suppress(AttributeError):
        env.get_wrapper_attr("set_eval_mode")(True)
    obs, _ = env.reset()
    episodes = steps = 0
    while episodes < args.episodes and (args.n_timesteps is None or steps < args.n_timesteps):
        yield _frame(env.render(), args.flip)
        action, _ = model.predict(obs, deterministic=not args.stochastic)
        obs, _, terminated, truncated, _ = env.step(action)
        steps += 1
        if terminated or truncated:
            episodes += 1
            obs, _ = env.reset()


def all_task_frames(model: BaseAlgorithm, env: VecEnv, args: argparse.Namespace) -> Iterator[list[np.ndarray]]:
    """The frame of every task at each vector step, until every task has run ``args.episodes`` episodes (at most
    ``args.n_timesteps`` steps)."""
    if env.has_attr("set_eval_mode"):
        env.env_method("set_eval_mode", True)
    episodes = np.zeros(env.num_envs, dtype=int)
    obs = env.reset()
    steps = 0
    while (episodes < args.episodes).any() and (args.n_timesteps is None or steps < args.n_timesteps):
        yield [_frame(image, args.flip) for image in env.get_images()]
        actions, _ = model.predict(obs, deterministic=not args.stochastic)
        obs, _, dones, _ = env.step(actions)
        episodes += dones.astype(int)
        steps += 1


def write_video(frames: Iterable[np.ndarray], path: Path, fps: int, total: int | None = None) -> bool:
    """Write ``frames`` into the mp4 ``path`` one at a time, with a progress bar of ``total`` frames; False (and
    no file) when there is no frame. The video is written under a temporary name (``.partial_<name>``) and renamed
    when complete: a video stopped midway is removed, never left as an mp4 that does not play."""
    from moviepy.video.io.ffmpeg_writer import FFMPEG_VideoWriter  # loads ffmpeg: only when writing videos

    partial = path.with_name(f".partial_{path.name}")
    writer = None
    complete = False
    with tqdm(total=total, desc=path.name, unit="frame") as progress:
        try:
            for frame in frames:
                if writer is None:
                    writer = FFMPEG_VideoWriter(str(partial), (frame.shape[1], frame.shape[0]), fps)
                writer.write_frame(frame)
                progress.update()
            complete = True
        finally:
            if writer is not None:
                writer.close()
                if complete:
                    os.replace(partial, path)
                else:
                    partial.unlink(missing_ok=True)
    return writer is not None


def _frame_count(env: gym.Env, args: argparse.Namespace) -> int | None:
    """Frames of one task's video when every episode runs to the time limit (None when the env has none)."""
    try:
        count = args.episodes * int(env.get_wrapper_attr("_max_episode_steps"))
    except AttributeError:
        return None
    return count if args.n_timesteps is None else min(count, args.n_timesteps)


def _fps(env: gym.Env | VecEnv, fps: int | None) -> int:
    return fps or int((env.metadata or {}).get("render_fps", 0) or DEFAULT_FPS)


def record_task_videos(
    model: BaseAlgorithm,
    env_fns: Sequence[Callable[[], gym.Env]],
    args: argparse.Namespace,
    out_dir: Path,
    prefix: str,
) -> list[Path]:
    """One video per task, ``<prefix>-<i>_<task>.mp4``: task i's env is built, filmed, written and closed before
    task i+1's. Returns the written paths."""
    written = []
    for i, make_env in enumerate(env_fns):
        env = make_env()
        try:
            path = out_dir / f"{prefix}-{i:02d}_{short_task_name(env.get_wrapper_attr('task_name'))}.mp4"
            if write_video(task_frames(model, env, args), path, _fps(env, args.fps), _frame_count(env, args)):
                written.append(path)
                print(f"Saved {path}")
        finally:
            env.close()
    return written


def record_tiled_video(model: BaseAlgorithm, env: VecEnv, args: argparse.Namespace, path: Path) -> list[Path]:
    """One video of every task side by side at each vector step. Returns ``[path]``, or ``[]`` with no frame."""
    frames = (tile_images(images) for images in all_task_frames(model, env, args))
    if not write_video(frames, path, _fps(env, args.fps)):
        return []
    print(f"Saved {path}")
    return [path]


__all__ = ["all_task_frames", "record_task_videos", "record_tiled_video", "task_frames", "write_video"]
