"""Small helpers shared by every multi-task algorithm: task bookkeeping, log keys, loss checks."""

from __future__ import annotations

import difflib
import sys
from collections.abc import Iterable
from numbers import Integral
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.vec_env import VecEnv

MAKE_ENV_FIX = "build the env with make_mt_env (make_mt_env('MT10'), or a list of task names)"
ONE_TASK_FIX = "or wrap one single-task env in OneHotTaskWrapper (DummyVecEnv([lambda: OneHotTaskWrapper(env)]))"


def env_fix(n_envs: int, min_tasks: int = 1) -> str:
    """How to build the env: make_mt_env, and for one sub-env where one task is enough, the one-hot wrapper."""
    return f"{MAKE_ENV_FIX}, {ONE_TASK_FIX}" if n_envs == 1 and min_tasks == 1 else MAKE_ENV_FIX


def nearest_names(name: str, names: Iterable[str], n: int = 1, cutoff: float = 0.6) -> list[str]:
    """The ``n`` names of ``names`` nearest to a misspelled ``name``, nearest first: what every "did you mean" of the
    package names. A name equal but for case comes first (``mtsacTE``: ``mtsacte``), then difflib's nearest with a
    ratio of at least ``cutoff``."""
    names = list(names)
    same = [candidate for candidate in names if candidate.lower() == name.lower()]
    lowered = [candidate.lower() for candidate in names]
    close = difflib.get_close_matches(name.lower(), lowered, n=max(len(names), 1), cutoff=cutoff)
    by_lower = {candidate.lower(): candidate for candidate in reversed(names)}
    return list(dict.fromkeys([*same, *(by_lower[lower] for lower in close)]))[:n]


def did_you_mean(name: str, names: Iterable[str]) -> str:
    """``"did you mean X?"`` with the name of ``names`` nearest to ``name``, or ``""`` when none is near."""
    close = nearest_names(name, names)
    return f"did you mean {close[0]}?" if close else ""


def short_task_name(name: str) -> str:
    """``"button-press-topdown-v3"`` -> ``"button-press-topdown"``."""
    return name[:-3] if name.endswith(("-v2", "-v3")) else name


def task_log_key(prefix: str, index: int, name: str | None = None) -> str:
    """Logger key for a per-task scalar, unique within its first 36 characters even for MT50.

    The task index comes right after the prefix, so SB3's 36-character stdout truncation never makes
    two keys collide: ``task_log_key("eval/success", 3, "door-open-v3") == "eval/success/03_door-open"``.
    """
    suffix = f"{index:02d}" if name is None else f"{index:02d}_{short_task_name(name)}"
    return f"{prefix}/{suffix}"


def task_ids_from_obs(obs: th.Tensor, n_tasks: int) -> th.Tensor:
    """Task index of each row, read from the one-hot that ends every observation."""
    return obs[..., -n_tasks:].argmax(dim=-1)


def get_task_names(env: VecEnv) -> list[str]:
    """Task names of a multi-task VecEnv (sub-env i is task i); generic names when the env has none."""
    try:
        return list(env.get_attr("task_name"))
    except AttributeError:
        return [f"task{i}" for i in range(env.num_envs)]


def check_multitask_env(env: VecEnv, n_tasks: int | None = None, min_tasks: int = 1) -> int:
    """Validate the multi-task layout and return the task count N.

    The layout is: one sub-env per task, a flat Box observation ending with the N-dim one-hot, and
    sub-env i observing one-hot e_i after reset. N = 1 (a single task followed by the one-hot ``[1.0]``) is
    a valid layout.

    :param env: the vectorised env.
    :param n_tasks: the task count the caller expects (from a checkpoint, say), or None.
    :param min_tasks: the smallest task count the caller accepts (2 for an algorithm that compares tasks).
    :raises ValueError: with what is wrong, when the env does not follow the layout.
    """
    n_envs = env.num_envs
    if n_envs < min_tasks:
        plural = "s" if min_tasks > 1 else ""
        raise ValueError(
            f"A multi-task env needs at least {min_tasks} task{plural} (one sub-env per task); got {n_envs} sub-env"
            f"{'' if n_envs == 1 else 's'}: {MAKE_ENV_FIX}."
        )
    obs_space = env.observation_space
    if not isinstance(obs_space, spaces.Box) or len(obs_space.shape) != 1:
        raise ValueError(
            f"A multi-task env needs a flat Box observation (state + one-hot), got {obs_space}: "
            f"{env_fix(n_envs, min_tasks)}."
        )
    if n_tasks is not None and n_envs != n_tasks:
        raise ValueError(f"Expected an env with one sub-env per task ({n_tasks} tasks), got {n_envs} sub-envs.")
    if obs_space.shape[0] <= n_envs:
        raise ValueError(
            f"Observation of size {obs_space.shape[0]} cannot hold a state and a {n_envs}-dim one-hot: "
            f"the env must have one sub-env per task and append the task one-hot to the state: "
            f"{env_fix(n_envs, min_tasks)}."
        )
    return n_envs


def check_one_hot(obs: np.ndarray, n_tasks: int) -> None:
    """Check that row i of a task-major batch of observations (one per sub-env) ends with one-hot e_i.

    :raises ValueError: when the one-hot is missing or does not match the sub-env order.
    """
    tail = np.asarray(obs)[:, -n_tasks:]
    if not np.array_equal(tail, np.eye(n_tasks, dtype=tail.dtype)):
        raise ValueError(
            f"Sub-env i must observe the one-hot e_i in its last {n_tasks} entries (one sub-env per task, "
            f"one-hot appended); the observations' last entries are not an identity matrix: {env_fix(n_tasks)}."
        )


def check_not_gymnasium_vector_env(env: Any) -> None:
    """Refuse a gymnasium VectorEnv, which SB3 takes for an old OpenAI Gym env, and an env id, which SB3 would make
    into a single-task env.

    :raises ValueError: naming :func:`~sb3_mtte.make_mt_env` instead.
    """
    if isinstance(env, str):
        raise ValueError(f"env {env!r} is a name, not a multi-task env: pass make_mt_env({env!r}) instead.")
    if isinstance(env, gym.vector.VectorEnv):
        raise ValueError(
            f"{type(env).__name__} is a gymnasium VectorEnv, which SB3 does not take: {MAKE_ENV_FIX}, an SB3 VecEnv "
            "with one sub-env per task."
        )


def check_positive_int(name: str, value: Any, example: str) -> None:
    """:raises ValueError: unless ``value`` is a positive int; ``name`` says what it counts, ``example`` a value."""
    if isinstance(value, bool) or not isinstance(value, Integral) or value < 1:
        raise ValueError(f"{name} must be a positive int such as {example}, got {value!r}.")


def caller_stacklevel() -> int:
    """``warnings.warn``'s ``stacklevel`` that points at the first caller outside this package (a subclass's
    override of a method calling its base's adds a frame)."""
    frame, level = sys._getframe(1), 1
    while frame.f_back is not None and frame.f_globals.get("__name__", "").startswith("sb3_mtte."):
        frame, level = frame.f_back, level + 1
    return level


def check_finite(name: str, value: th.Tensor) -> None:
    """Stop training with an error naming the loss when it is NaN or infinite."""
    if not bool(th.isfinite(value).all()):
        raise FloatingPointError(f"The {name} is not finite ({value.detach().cpu().numpy()}); training stopped.")


@th.no_grad()
def polyak_update(params: Iterable[th.Tensor], target_params: Iterable[th.Tensor], tau: float) -> None:
    """target <- (1 - tau) target + tau param, in place, as SB3's ``polyak_update``; one ``lerp_`` per tensor reads
    both tensors once and writes the target once (SB3's ``mul_`` then ``add`` passes over the target twice more),
    which matters for N per-task critics. Equal to SB3's up to float rounding.

    :param params: the online parameters.
    :param target_params: the target parameters, updated in place.
    :param tau: the soft update coefficient in [0, 1].
    """
    for param, target in zip(params, target_params, strict=True):
        target.lerp_(param, tau)
