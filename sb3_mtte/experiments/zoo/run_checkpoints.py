"""Resumable checkpoints of a run folder: model, replay buffer and marker, and the env restart at each of them."""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.vec_env import VecEnv

from sb3_mtte.common.checkpoints import read_checkpoint_data
from sb3_mtte.experiments.variants import FAMILIES

CHECKPOINT_PREFIX = "rl_model"
_CHECKPOINT_RE = re.compile(rf"^{CHECKPOINT_PREFIX}_(\d+)_steps\.zip$")


@dataclass
class Checkpoint:
    """A complete checkpoint of a run folder."""

    timesteps: int
    model: Path
    replay_buffer: Path | None
    meta: dict[str, Any] = field(default_factory=dict)


def checkpoint_paths(run_dir: str | os.PathLike, timesteps: int) -> dict[str, Path]:
    """Model, replay-buffer and marker paths of the checkpoint at ``timesteps`` (SB3's CheckpointCallback names)."""
    run_dir = Path(run_dir)
    return {
        "model": run_dir / f"{CHECKPOINT_PREFIX}_{timesteps}_steps.zip",
        "replay_buffer": run_dir / f"{CHECKPOINT_PREFIX}_replay_buffer_{timesteps}_steps.pkl",
        "meta": run_dir / f"{CHECKPOINT_PREFIX}_{timesteps}_steps.json",
    }


def find_checkpoints(run_dir: str | os.PathLike) -> list[Checkpoint]:
    """Complete checkpoints of a run folder, oldest first.

    A checkpoint is complete when its model and its replay buffer exist. The marker (``rl_model_<t>_steps.json``,
    written last) is read when present.
    """
    found = []
    for path in Path(run_dir).glob(f"{CHECKPOINT_PREFIX}_*_steps.zip"):
        match = _CHECKPOINT_RE.match(path.name)
        if match is None:
            continue
        steps = int(match.group(1))
        paths = checkpoint_paths(run_dir, steps)
        if not paths["replay_buffer"].is_file():
            continue
        meta = json.loads(paths["meta"].read_text()) if paths["meta"].is_file() else {}
        found.append(Checkpoint(steps, path, paths["replay_buffer"], meta))
    return sorted(found, key=lambda c: c.timesteps)


def find_latest_checkpoint(run_dir: str | os.PathLike) -> Checkpoint | None:
    """The most recent complete checkpoint of a run folder (see :func:`find_checkpoints`), or None."""
    found = find_checkpoints(run_dir)
    return found[-1] if found else None


def run_folders(log_folder: str | os.PathLike, algo: str, env_name: str) -> list[Path]:
    """The run folders ``<log_folder>/<algo>/<env_name>_<id>`` (rl-zoo's names), latest (highest id) first."""
    found = []
    for path in (Path(log_folder) / algo).glob(f"{env_name}_*"):
        suffix = path.name[len(env_name) + 1 :]
        if suffix.isdigit() and path.is_dir():
            found.append((int(suffix), path))
    return [path for _, path in sorted(found, reverse=True)]


def latest_run_with_model(log_folder: str | os.PathLike, algo: str, env_name: str) -> Path | None:
    """The latest run folder of ``algo`` on ``env_name`` that holds a model (final, best or checkpoint), else the
    latest one that holds a started run (``run_info.json``), else None; newer folders passed over are named in one
    line on stdout."""
    folders = run_folders(log_folder, algo, env_name)
    chosen = next((p for p in folders if any(p.glob("*.zip"))), None)
    chosen = chosen or next((p for p in folders if (p / "run_info.json").is_file()), None)
    passed = [p.name for p in folders[: folders.index(chosen)]] if chosen is not None else []
    if passed:
        print(f"Passing over {', '.join(passed)} (no model): the latest run with one is {chosen}")
    return chosen


def final_checkpoint(run_dir: str | os.PathLike, env_name: str) -> Checkpoint | None:
    """The final model and replay buffer of a run that finished (``--save-replay-buffer``), if any."""
    run_dir = Path(run_dir)
    info_path = run_dir / "run_info.json"
    info = json.loads(info_path.read_text()) if info_path.is_file() else {}
    model, buffer = run_dir / f"{env_name}.zip", run_dir / "replay_buffer.pkl"
    if not (info.get("finished") and model.is_file() and buffer.is_file()):
        return None
    steps = int(read_checkpoint_data(model).get("num_timesteps", 0))
    return Checkpoint(steps, model, buffer, {"timesteps": steps, "final_model": True})


def missing_folders(path: Path) -> list[Path]:
    """``path`` and each folder above it that does not exist yet, deepest first."""
    missing = []
    while not path.exists() and path != path.parent:
        missing.append(path)
        path = path.parent
    return missing


def remove_made_folders(made: list[Path]) -> None:
    """Remove the run folder a failed set-up made (the first of ``made``), then each folder above it that it made
    and that is still empty (another run may have begun there meanwhile)."""
    if made:
        shutil.rmtree(made[0], ignore_errors=True)
    for folder in made[1:]:
        with contextlib.suppress(OSError):
            folder.rmdir()


def restart_seed(seed: int, timesteps: int, stream: int = 0) -> int:
    """Seed of the envs restarted at a checkpoint: a function of the run seed, the step and the env (0: train)."""
    state = np.random.SeedSequence([int(seed) & 0xFFFFFFFF, int(seed) >> 32, int(timesteps), stream])
    return int(state.generate_state(1)[0] % (2**31 - 2**16))


def restart_envs(model: BaseAlgorithm, eval_env: VecEnv | None, seed: int, timesteps: int) -> None:
    """Reseed from (seed, step) and reset the training env, and reseed the evaluation env for its next reset.

    Called at every checkpoint taken at the boundary between episodes, and on resuming from any checkpoint,
    so that both runs continue from the same env states.
    """
    env = model.get_env()
    assert env is not None
    buffer = getattr(model, "replay_buffer", None)
    if hasattr(buffer, "reset_running_episodes"):
        buffer.reset_running_episodes()  # episodes cut by the restart are not offered to the top-K store
    env.seed(restart_seed(seed, timesteps, 0))
    model._last_obs = env.reset()  # type: ignore[assignment]
    model._last_episode_starts = np.ones((env.num_envs,), dtype=bool)
    if eval_env is not None:
        eval_env.seed(restart_seed(seed, timesteps, 1))


def atomic_save(save: Callable[[str], None], path: Path) -> None:
    """Write ``path`` with ``save`` under a temporary name, then rename it: a reader sees the whole file or none. A
    write that fails (a full disk, Ctrl-C) removes its temporary file and leaves ``path`` as it was."""
    tmp = path.with_name(f".tmp_{path.name}")
    try:
        save(str(tmp))
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def load_model(
    path: str | os.PathLike, device: str = "auto", env: VecEnv | None = None, **kwargs: Any
) -> BaseAlgorithm:
    """Load a checkpoint of any algorithm family, picking the class from the zip.

    :param path: the model zip.
    :param device: torch device.
    :param env: the env to attach.
    :param kwargs: attributes to set on the loaded model (SB3's ``load`` keyword arguments).
    """
    classes = {family.algorithm.__name__: family.algorithm for family in FAMILIES.values()}
    name = read_checkpoint_data(path).get("algorithm_name")
    if name not in classes:
        raise ValueError(f"{path} was not saved by {' or '.join(classes)} (algorithm_name={name!r}).")
    return classes[name].load(path, env=env, device=device, **kwargs)
