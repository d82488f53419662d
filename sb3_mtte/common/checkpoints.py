"""Checks run before loading a checkpoint, so a wrong file fails with a clear error instead of a shape mismatch."""

from __future__ import annotations

import io
import json
import pathlib
import random
import zipfile

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.save_util import open_path


def read_checkpoint_data(path: str | pathlib.Path | io.BufferedIOBase) -> dict:
    """The JSON ``data`` entry of an SB3 zip checkpoint, without deserialising its objects or tensors."""
    file = open_path(path, "r", verbose=0, suffix="zip")
    try:
        with zipfile.ZipFile(file) as archive:
            data = json.loads(archive.read("data").decode())
    finally:
        if isinstance(file, io.BufferedIOBase) and not isinstance(path, io.BufferedIOBase):
            file.close()
        else:
            file.seek(0)
    return data


def incomplete_checkpoint_error(path) -> str | None:
    """The one-line error for a file that is not a whole SB3 zip checkpoint (a truncated copy, say), else None."""
    try:
        read_checkpoint_data(path)
    except (zipfile.BadZipFile, KeyError, json.JSONDecodeError, UnicodeDecodeError) as error:
        return (
            f"{getattr(path, 'name', path)} is not a complete SB3 checkpoint ({error}): it may be truncated; save "
            "the model again or load another file."
        )
    return None


def check_checkpoint(path, algorithm_name: str, n_tasks: int | None) -> None:
    """Raise ValueError when ``path`` was saved by another algorithm or for another task count.

    :param path: checkpoint path or file object.
    :param algorithm_name: class name of the algorithm loading it.
    :param n_tasks: task count of the env it is loaded with, or None when loaded without an env.
    """
    data = read_checkpoint_data(path)
    saved_name = data.get("algorithm_name")
    if saved_name != algorithm_name:
        raise ValueError(
            f"This checkpoint was saved by {saved_name or 'another algorithm (not sb3_mtte)'}, "
            f"not {algorithm_name}: load it with that class."
        )
    saved_tasks = data.get("n_tasks")
    if n_tasks is not None and saved_tasks != n_tasks:
        raise ValueError(f"This checkpoint was trained on {saved_tasks} tasks; the env given has {n_tasks} tasks.")


def capture_rng_state(action_space: spaces.Space) -> dict:
    """The RNG states that training draws from: python, numpy, torch CPU and CUDA, and ``action_space``'s own
    generator, from which SB3 draws the random actions before ``learning_starts``."""
    state = {"python": random.getstate(), "numpy": np.random.get_state(), "torch": th.get_rng_state()}
    if th.cuda.is_available():
        state["cuda"] = th.cuda.get_rng_state_all()
    state["action_space"] = action_space.np_random.bit_generator.state
    return state


def restore_rng_state(state: dict, action_space: spaces.Space) -> None:
    """Restore what :func:`capture_rng_state` captured (loading re-seeds ``action_space``; this undoes it)."""
    random.setstate(state["python"])
    np.random.set_state(state["numpy"])
    th.set_rng_state(state["torch"])
    if "cuda" in state and th.cuda.is_available():
        th.cuda.set_rng_state_all(state["cuda"])
    if "action_space" in state:
        action_space.np_random.bit_generator.state = state["action_space"]
