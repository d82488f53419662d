"""Meta-World v3 multi-task benchmarks as one single-task env per task.

Benchmarks:

- ``MT10`` (:data:`MT10_TASKS`): the official Meta-World MT10, in Meta-World's order. The paper lists "open box"
  among its MT10 tasks where the official MT10 has window-close; this package uses the official list.
- ``MT20`` (:data:`MT20_TASKS`): the first 20 tasks of MT50 in MT50's order (the paper's MT20). Its goal
  variations are those MT50 draws for these tasks with the same seed.
- ``MT25`` (:data:`MT25_TASKS`): Meta-World v3's MT25 (MT10 and 15 more tasks), in Meta-World's order.
- ``MT50`` (:data:`MT50_TASKS`): all 50 tasks, in Meta-World's MT50 order.
- ``DEV6`` (:data:`DEV6_TASKS`): the development benchmark, six tasks outside MT10 and MT20 in three pairs that
  share a scene (faucet-open/close, plate-slide/-back, handle-press/pull).
- any list of distinct v3 env names, e.g. ``["reach-v3", "push-v3"]``, also written as one string joined by
  ``"_"``: ``"reach-v3_push-v3"`` (:func:`metaworld_task_names`).

``reward_function_version`` picks Meta-World v3's reward functions (:data:`REWARD_FUNCTION_VERSIONS`): ``"v2"``,
Meta-World's default, or ``"v1"``; some tasks (push, ...) also measure success differently under ``"v1"``.

Each task has Meta-World's 50 goal variations (``metaworld.Task`` objects, generated from the seed the way
``metaworld.MT10(seed=...)`` does). The state is Meta-World's 39-d goal-observable observation; the one-hot,
goal sampling, success tracking and seeding come from :class:`~sb3_mtte.envs.wrappers.MultiTaskWrapper`.

Measured on a 2-core CPU shared with other jobs (DummyVecEnv, random actions): building MT10 takes 7-12 s
(about 5.5 s of it generating the goal variations, which are cached per process for a given task list and
seed: a second build takes about 2 s); stepping runs at 1.5k-2.7k env steps/s (150-270 vector steps/s); one
reset takes about 8 ms. Meta-World's scripted experts score 0.98 on MT10 under :func:`evaluate_success
<sb3_mtte.evaluation.evaluate_success>` (50 episodes per task).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence
from functools import lru_cache, partial
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.wrappers import TimeLimit

from sb3_mtte.common.scripted import ScriptedPolicy
from sb3_mtte.common.utils import nearest_names
from sb3_mtte.envs.wrappers import MultiTaskWrapper

MT10_TASKS: list[str] = [
    "reach-v3",
    "push-v3",
    "pick-place-v3",
    "door-open-v3",
    "drawer-open-v3",
    "drawer-close-v3",
    "button-press-topdown-v3",
    "peg-insert-side-v3",
    "window-open-v3",
    "window-close-v3",
]
"""The official Meta-World MT10, in Meta-World's order."""

MT50_TASKS: list[str] = [
    "assembly-v3", "basketball-v3", "bin-picking-v3", "box-close-v3", "button-press-topdown-v3",
    "button-press-topdown-wall-v3", "button-press-v3", "button-press-wall-v3", "coffee-button-v3",
    "coffee-pull-v3", "coffee-push-v3", "dial-turn-v3", "disassemble-v3", "door-close-v3", "door-lock-v3",
    "door-open-v3", "door-unlock-v3", "hand-insert-v3", "drawer-close-v3", "drawer-open-v3", "faucet-open-v3",
    "faucet-close-v3", "hammer-v3", "handle-press-side-v3", "handle-press-v3", "handle-pull-side-v3",
    "handle-pull-v3", "lever-pull-v3", "pick-place-wall-v3", "pick-out-of-hole-v3", "pick-place-v3",
    "plate-slide-v3", "plate-slide-side-v3", "plate-slide-back-v3", "plate-slide-back-side-v3",
    "peg-insert-side-v3", "peg-unplug-side-v3", "soccer-v3", "stick-push-v3", "stick-pull-v3", "push-v3",
    "push-wall-v3", "push-back-v3", "reach-v3", "reach-wall-v3", "shelf-place-v3", "sweep-into-v3", "sweep-v3",
    "window-open-v3", "window-close-v3",
]  # fmt: skip
"""All 50 Meta-World v3 tasks, in Meta-World's MT50 order."""

MT20_TASKS: list[str] = MT50_TASKS[:20]
"""The first 20 tasks of MT50 (the paper's MT20)."""

MT25_TASKS: list[str] = [
    *MT10_TASKS,
    "coffee-pull-v3",
    "pick-out-of-hole-v3",
    "disassemble-v3",
    "pick-place-wall-v3",
    "basketball-v3",
    "stick-pull-v3",
    "button-press-wall-v3",
    "faucet-open-v3",
    "door-lock-v3",
    "lever-pull-v3",
    "sweep-into-v3",
    "faucet-close-v3",
    "coffee-button-v3",
    "button-press-topdown-wall-v3",
    "dial-turn-v3",
]
"""Meta-World v3's MT25 (MT10 followed by 15 more tasks), in Meta-World's order."""

DEV6_TASKS: list[str] = [
    "faucet-open-v3",
    "faucet-close-v3",
    "plate-slide-v3",
    "plate-slide-back-v3",
    "handle-press-v3",
    "handle-pull-v3",
]
"""The development benchmark: six tasks outside MT10 and MT20, in three pairs that share a scene, where only the
task identity tells which way to move the object. Defaults are chosen on it, never on a reported benchmark."""

METAWORLD_BENCHMARKS: dict[str, list[str]] = {
    "MT10": MT10_TASKS,
    "MT20": MT20_TASKS,
    "MT25": MT25_TASKS,
    "MT50": MT50_TASKS,
    "DEV6": DEV6_TASKS,
}
"""Named Meta-World benchmark -> its task names."""

TASK_LIST_SEPARATOR = "_"
"""Joins Meta-World v3 env names into one benchmark name: ``"reach-v3_push-v3"``."""

REWARD_FUNCTION_VERSIONS = ("v2", "v1")
"""Meta-World v3's reward functions (``reward_function_version``), its default first."""

METAWORLD_ENV_KWARGS = (
    "max_episode_steps",
    "reward_function_version",
    "render_mode",
    "camera_name",
    "camera_id",
    "width",
    "height",
)
"""Keyword arguments :func:`make_metaworld_env_fns` accepts besides the seed."""


def check_reward_function_version(version: Any) -> str:
    """``version`` when it is one of :data:`REWARD_FUNCTION_VERSIONS`.

    :raises ValueError: otherwise (Meta-World itself would silently use v1's rewards).
    """
    if version not in REWARD_FUNCTION_VERSIONS:
        raise ValueError(
            f"reward_function_version={version!r} is not a Meta-World v3 reward function: use "
            f"{' or '.join(map(repr, REWARD_FUNCTION_VERSIONS))} (the default is {REWARD_FUNCTION_VERSIONS[0]!r})."
        )
    return version


def _nearest_names(name: str) -> str:
    return f"{name!r} (nearest: {', '.join(nearest_names(name, MT50_TASKS, n=3, cutoff=0.0))})"


def validate_task_names(task_names: Sequence[str]) -> list[str]:
    """Check a list of Meta-World v3 env names.

    :param task_names: the names.
    :return: the names as a list.
    :raises ValueError: on an unknown name (naming the nearest valid ones) or a repeated name.
    """
    names = list(task_names)
    unknown = [name for name in names if name not in MT50_TASKS]
    if unknown:
        raise ValueError(
            f"Unknown Meta-World v3 env name {', '.join(map(_nearest_names, unknown))}; every name is in "
            "sb3_mtte.envs.MT50_TASKS."
        )
    if len(set(names)) != len(names):
        raise ValueError(f"Task names must be distinct (one sub-env per task), got {names}.")
    return names


def is_task_list(name: str) -> bool:
    """Whether a benchmark name is Meta-World v3 env names joined by :data:`TASK_LIST_SEPARATOR` (or one name)."""
    return TASK_LIST_SEPARATOR in name or name.endswith("-v3")


def metaworld_task_names(name: str) -> list[str] | None:
    """Task names of a named Meta-World benchmark (:data:`METAWORLD_BENCHMARKS`, any case) or of a task list
    (``"reach-v3_push-v3"``); None for any other name.

    :raises ValueError: for a task list with an unknown or repeated name.
    """
    if name.upper() in METAWORLD_BENCHMARKS:
        return list(METAWORLD_BENCHMARKS[name.upper()])
    if is_task_list(name):
        return validate_task_names(name.split(TASK_LIST_SEPARATOR))
    return None


@lru_cache(maxsize=4)
def goal_variations(task_names: tuple[str, ...], seed: int) -> tuple[tuple[Any, ...], ...]:
    """Meta-World's 50 goal variations (``metaworld.Task``) of each task, generated as Meta-World's benchmarks do.

    With the MT10, MT25 or MT50 list this is ``metaworld.MT10(seed=seed).train_tasks`` (resp. MT25, MT50); any
    other list uses the same generator on its own tasks, so a prefix of MT50 (MT20) gets MT50's variations. Cached.

    :param task_names: the tasks, in order.
    :param seed: the benchmark seed.
    :return: per task, its 50 ``metaworld.Task`` objects.
    """
    import metaworld
    from metaworld import env_dict

    names = validate_task_names(task_names)
    benchmark = next((key for key in ("MT10", "MT25", "MT50") if names == METAWORLD_BENCHMARKS[key]), None)
    if benchmark is not None:
        tasks = getattr(metaworld, benchmark)(seed=seed).train_tasks
    else:
        classes = env_dict._get_env_dict(names)
        args_kwargs = env_dict._get_args_kwargs(env_dict.ALL_V3_ENVIRONMENTS, classes)
        tasks = metaworld._make_tasks(classes, args_kwargs, metaworld._MT_OVERRIDE, seed=seed)
    return tuple(tuple(task for task in tasks if task.env_name == name) for name in names)


def _state_space(raw: gym.Env) -> spaces.Box:
    """Bounds of the 39-d state shared by every task: Meta-World's, with unbounded goal entries.

    Meta-World bounds the goal entries by each task's own goal space; a VecEnv has a single observation
    space for all its sub-envs, so the goal entries (the last 3) are left unbounded instead.
    """
    space = raw.sawyer_observation_space
    low, high = space.low.copy(), space.high.copy()
    low[-3:], high[-3:] = -np.inf, np.inf
    return spaces.Box(low, high, dtype=np.float64)


def make_metaworld_task_env(
    task_name: str,
    task_index: int,
    n_tasks: int,
    goals: Sequence[Any],
    seed: int = 0,
    max_episode_steps: int | None = None,
    reward_function_version: str = REWARD_FUNCTION_VERSIONS[0],
    render_mode: str | None = None,
    camera_name: str | None = None,
    camera_id: int | None = None,
    width: int = 480,
    height: int = 480,
) -> gym.Env:
    """Sub-env ``task_index``: one Meta-World v3 env, truncated, wrapped in :class:`MultiTaskWrapper`.

    :param task_name: Meta-World v3 env name.
    :param task_index: index i of the task (one-hot e_i).
    :param n_tasks: number of tasks N.
    :param goals: the task's goal variations (``metaworld.Task`` objects).
    :param seed: benchmark seed; the env and its goal RNG get a seed derived from it and the task index.
    :param max_episode_steps: truncation length (Meta-World's 500 when None).
    :param reward_function_version: Meta-World's reward functions, ``"v2"`` or ``"v1"``.
    :param render_mode: None, ``"rgb_array"``, ``"depth_array"`` or ``"human"``.
    :param camera_name: MuJoCo camera to render from (e.g. ``"corner"``).
    :param camera_id: MuJoCo camera id (alternative to ``camera_name``).
    :param width: rendered image width.
    :param height: rendered image height.
    """
    from metaworld.env_dict import ALL_V3_ENVIRONMENTS

    raw = ALL_V3_ENVIRONMENTS[task_name](
        reward_function_version=reward_function_version,
        render_mode=render_mode,
        camera_name=camera_name,
        camera_id=camera_id,
        width=width,
        height=height,
    )
    raw.set_task(goals[0])  # a goal-observable task first, so the observation bounds include the goal
    steps = int(max_episode_steps or raw.max_path_length)
    raw.max_path_length = steps
    return MultiTaskWrapper(
        TimeLimit(raw, steps),
        task_index=task_index,
        n_tasks=n_tasks,
        task_name=task_name,
        n_goals=len(goals),
        set_goal=lambda k: raw.set_task(goals[k]),
        state_space=_state_space(raw),
        seed=int(np.random.SeedSequence([seed, task_index]).generate_state(1)[0]),
    )


def make_metaworld_env_fns(task_names: Sequence[str], seed: int = 0, **kwargs: Any) -> list[Callable[[], gym.Env]]:
    """One env constructor per task, in task order (goal variations are generated here, once).

    :param task_names: Meta-World v3 env names.
    :param seed: benchmark seed.
    :param kwargs: any of :data:`METAWORLD_ENV_KWARGS`.
    """
    unknown = set(kwargs) - set(METAWORLD_ENV_KWARGS)
    if unknown:
        valid = ", ".join(METAWORLD_ENV_KWARGS)
        raise TypeError(f"Unexpected keyword argument(s) {sorted(unknown)} for Meta-World; valid: {valid}.")
    if "reward_function_version" in kwargs:
        check_reward_function_version(kwargs["reward_function_version"])
    names = validate_task_names(task_names)
    goals = goal_variations(tuple(names), int(seed))
    return [
        partial(make_metaworld_task_env, name, i, len(names), goals[i], seed, **kwargs) for i, name in enumerate(names)
    ]


class MetaWorldExpertPolicy(ScriptedPolicy):
    """Meta-World's scripted expert of each task behind an SB3-style ``predict`` (batched over sub-envs).

    :param task_names: the benchmark's task names, in task order.
    """

    def __init__(self, task_names: Sequence[str]) -> None:
        from metaworld.policies import ENV_POLICY_MAP

        self.task_names = validate_task_names(task_names)
        self.experts = [ENV_POLICY_MAP[name]() for name in self.task_names]
        self.n_tasks = len(self.experts)

    def task_actions(self, states: np.ndarray, tasks: np.ndarray) -> np.ndarray:
        """Expert actions for 39-d states."""
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the experts warn about their own gains on every call
            rows = states.astype(np.float64)
            return np.stack([self.experts[t].get_action(row) for t, row in zip(tasks, rows, strict=True)])
