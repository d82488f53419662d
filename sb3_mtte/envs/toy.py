"""Toy multi-task benchmarks in pure numpy: a 2-D point that must reach a task-specific goal.

Built for fast tests of multi-task learners (thousands of steps/s on one CPU core) and as a small place where
negative transfer shows. Every task shares the same dynamics and the same state; only the goal differs, and
the goal is not observed: the task can be told apart only through the one-hot appended by
:class:`~sb3_mtte.envs.wrappers.MultiTaskWrapper`.

- State (4-d, in [-1, 1]): position (x, y) and velocity (vx, vy) = last displacement / step size.
- Action in [-1, 1]^2: the point moves by ``step_size * action`` (0.1), clipped to the arena [-1, 1]^2.
- Start: the origin jittered by up to 0.05 per coordinate.
- Goals: at distance 0.7 from the origin. Each task has 50 goal variations (its goal jittered by up to 0.05
  per coordinate), drawn once from the seed; one is picked at every reset.
- Reward per step: ``-distance / 2`` (about [-1, 0]) plus 1 while within the success radius (0.1).
- Success: within the success radius at any step. Episodes are truncated after 50 steps (never terminated).

Benchmarks (:data:`TOY_BENCHMARKS`):

- ``"toy-conflict"``: goals of tasks 0..N-2 spread over +-30 degrees around +x ("agree-i"); the goal of the
  last task ("conflict") is at -x, so the same states are rewarded for opposite actions.
- ``"toy-agree"``: all N goals spread over +-30 degrees around +x (a control without conflict).

Names take an optional task count: ``"toy-conflict-6"`` is ``"toy-conflict"`` with ``n_tasks=6`` (default 4).
"""

from __future__ import annotations

import re
from collections.abc import Callable
from functools import partial
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.wrappers import TimeLimit

from sb3_mtte.common.scripted import ScriptedPolicy
from sb3_mtte.envs.wrappers import MultiTaskWrapper

STEP_SIZE = 0.1
GOAL_DISTANCE = 0.7
GOAL_SPREAD = np.pi / 6
GOAL_JITTER = 0.05
START_JITTER = 0.05
SUCCESS_RADIUS = 0.1
N_GOAL_VARIATIONS = 50
DEFAULT_MAX_EPISODE_STEPS = 50
DEFAULT_N_TASKS = 4


def _on_circle(angles: np.ndarray) -> np.ndarray:
    return GOAL_DISTANCE * np.stack([np.cos(angles), np.sin(angles)], axis=-1)


def _fan(n: int) -> np.ndarray:
    """n angles spread evenly over +-GOAL_SPREAD around +x (0 for a single one)."""
    return np.zeros(1) if n == 1 else np.linspace(-GOAL_SPREAD, GOAL_SPREAD, n)


def toy_conflict(n_tasks: int) -> tuple[list[str], np.ndarray]:
    """Tasks 0..N-2 with goals on the +x side, the last task with its goal at -x.

    :param n_tasks: number of tasks N (at least 2).
    :return: task names and goal centres, shape (N, 2).
    """
    if n_tasks < 2:
        raise ValueError(f"toy-conflict needs at least 2 tasks, got {n_tasks}.")
    centers = np.concatenate([_on_circle(_fan(n_tasks - 1)), _on_circle(np.array([np.pi]))])
    return [f"agree-{i}" for i in range(n_tasks - 1)] + ["conflict"], centers


def toy_agree(n_tasks: int) -> tuple[list[str], np.ndarray]:
    """All N tasks with goals on the +x side.

    :param n_tasks: number of tasks N (at least 1).
    :return: task names and goal centres, shape (N, 2).
    """
    if n_tasks < 1:
        raise ValueError(f"toy-agree needs at least 1 task, got {n_tasks}.")
    return [f"agree-{i}" for i in range(n_tasks)], _on_circle(_fan(n_tasks))


TOY_BENCHMARKS: dict[str, Callable[[int], tuple[list[str], np.ndarray]]] = {
    "toy-conflict": toy_conflict,
    "toy-agree": toy_agree,
}
"""Toy benchmark name -> constructor ``f(n_tasks) -> (task_names, goal_centres)``."""

_TOY_NAME = re.compile(r"^toy-?(conflict|agree)(?:-(\d+))?$")


def parse_toy_name(name: str, n_tasks: int | None = None) -> tuple[str, int] | None:
    """``("toy-conflict", N)`` for a toy benchmark name such as ``"toy-conflict-6"`` or ``"ToyConflict-6"``.

    :param name: the benchmark name.
    :param n_tasks: task count given separately; must agree with one in the name.
    :return: canonical name and task count, or None when ``name`` is not a toy benchmark.
    """
    match = _TOY_NAME.match(name.strip().lower().replace("_", "-"))
    if match is None:
        return None
    canonical = f"toy-{match.group(1)}"
    from_name = int(match.group(2)) if match.group(2) else None
    if from_name is not None and n_tasks is not None and from_name != n_tasks:
        raise ValueError(f"{name!r} names {from_name} tasks but n_tasks={n_tasks} was given.")
    count = from_name if from_name is not None else n_tasks
    return canonical, DEFAULT_N_TASKS if count is None else count


class PointGoalEnv(gym.Env):
    """A point in [-1, 1]^2 that must reach a goal; one goal variation is active per episode.

    :param goals: the goal variations, shape (n_goals, 2).
    :param step_size: displacement per step for a unit action.
    :param success_radius: distance to the goal that counts as success.
    :param render_mode: None or ``"rgb_array"`` (a small top-down image).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 20}  # noqa: RUF012  # as gymnasium.Env declares it

    def __init__(
        self,
        goals: np.ndarray,
        step_size: float = STEP_SIZE,
        success_radius: float = SUCCESS_RADIUS,
        render_mode: str | None = None,
    ) -> None:
        self.goals = np.asarray(goals, dtype=np.float64).reshape(-1, 2)
        self.step_size = step_size
        self.success_radius = success_radius
        self.render_mode = render_mode
        self.observation_space = spaces.Box(-1.0, 1.0, shape=(4,), dtype=np.float32)
        self.action_space = spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)
        self.goal = self.goals[0].copy()
        self._pos = np.zeros(2)
        self._vel = np.zeros(2)

    def seed(self, seed: int) -> None:
        """Seed the start-state RNG (Meta-World style; ``reset(seed=...)`` works as well).

        :param seed: the seed.
        """
        self.np_random = np.random.default_rng(seed)
        self.action_space.seed(seed)

    def set_goal_variation(self, index: int) -> None:
        """Use goal variation ``index`` from the next reset on.

        :param index: index into ``goals``.
        """
        self.goal = self.goals[index].copy()

    def _obs(self) -> np.ndarray:
        return np.concatenate([self._pos, self._vel]).astype(np.float32)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        self._pos = self.np_random.uniform(-START_JITTER, START_JITTER, size=2)
        self._vel = np.zeros(2)
        return self._obs(), {}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        action = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        new_pos = np.clip(self._pos + self.step_size * action, -1.0, 1.0)
        self._vel = (new_pos - self._pos) / self.step_size
        self._pos = new_pos
        distance = float(np.hypot(*(self._pos - self.goal)))
        success = distance <= self.success_radius
        reward = -0.5 * distance + (1.0 if success else 0.0)
        return self._obs(), reward, False, False, {"success": success, "distance": distance}

    def render(self) -> np.ndarray | None:
        if self.render_mode != "rgb_array":
            return None
        size = 64
        image = np.full((size, size, 3), 255, dtype=np.uint8)

        def pixel(p: np.ndarray) -> tuple[int, int]:
            col, row = ((np.clip(p, -1, 1) + 1) / 2 * (size - 1)).round().astype(int)
            return size - 1 - row, col

        for point, color in ((self.goal, (0, 160, 0)), (self._pos, (200, 0, 0))):
            row, col = pixel(point)
            image[max(row - 1, 0) : row + 2, max(col - 1, 0) : col + 2] = color
        return image


def goal_variations(center: np.ndarray, seed: int, task_index: int) -> np.ndarray:
    """The 50 goal variations of a task: its centre jittered, drawn from ``(seed, task_index)``.

    :param center: the task's goal centre, shape (2,).
    :param seed: the benchmark seed.
    :param task_index: the task index.
    :return: shape (50, 2).
    """
    rng = np.random.default_rng([seed, task_index, 1])
    return center + rng.uniform(-GOAL_JITTER, GOAL_JITTER, size=(N_GOAL_VARIATIONS, 2))


def make_toy_task_env(
    center: np.ndarray,
    task_name: str,
    task_index: int,
    n_tasks: int,
    seed: int = 0,
    max_episode_steps: int | None = None,
    render_mode: str | None = None,
) -> gym.Env:
    """Sub-env ``task_index`` of a toy benchmark (the wrapped :class:`PointGoalEnv`).

    :param center: the task's goal centre.
    :param task_name: the task's name.
    :param task_index: its index i (one-hot e_i).
    :param n_tasks: number of tasks N.
    :param seed: benchmark seed.
    :param max_episode_steps: truncation length (default 50).
    :param render_mode: None or ``"rgb_array"``.
    """
    env = PointGoalEnv(goal_variations(np.asarray(center), seed, task_index), render_mode=render_mode)
    env = TimeLimit(env, max_episode_steps or DEFAULT_MAX_EPISODE_STEPS)
    return MultiTaskWrapper(
        env,
        task_index=task_index,
        n_tasks=n_tasks,
        task_name=task_name,
        n_goals=N_GOAL_VARIATIONS,
        set_goal=env.unwrapped.set_goal_variation,
        seed=int(np.random.SeedSequence([seed, task_index]).generate_state(1)[0]),
    )


TOY_ENV_KWARGS = ("max_episode_steps", "render_mode")
"""Keyword arguments of a toy benchmark's envs (besides the seed and the task count)."""


def make_toy_env_fns(
    benchmark: str,
    seed: int = 0,
    n_tasks: int | None = None,
    max_episode_steps: int | None = None,
    render_mode: str | None = None,
) -> list[Callable[[], gym.Env]]:
    """One env constructor per task of a toy benchmark, in task order.

    :param benchmark: a toy benchmark name (see :data:`TOY_BENCHMARKS`), optionally with ``-N``.
    :param seed: benchmark seed.
    :param n_tasks: number of tasks (default 4, or the one in the name).
    :param max_episode_steps: truncation length (default 50).
    :param render_mode: None or ``"rgb_array"``.
    """
    parsed = parse_toy_name(benchmark, n_tasks)
    if parsed is None:
        raise ValueError(f"Unknown toy benchmark {benchmark!r}; valid: {sorted(TOY_BENCHMARKS)} (optionally '-N').")
    name, n = parsed
    names, centers = TOY_BENCHMARKS[name](n)
    return [
        partial(make_toy_task_env, centers[i], names[i], i, n, seed, max_episode_steps, render_mode) for i in range(n)
    ]


class ToyOraclePolicy(ScriptedPolicy):
    """Scripted policy that heads straight for each task's goal centre (an SB3-style ``predict``).

    :param benchmark: toy benchmark name (optionally with ``-N``).
    :param n_tasks: number of tasks, as given to ``make_mt_env``.
    """

    def __init__(self, benchmark: str, n_tasks: int | None = None) -> None:
        parsed = parse_toy_name(benchmark, n_tasks)
        if parsed is None:
            raise ValueError(f"Unknown toy benchmark {benchmark!r}.")
        _, self.centers = TOY_BENCHMARKS[parsed[0]](parsed[1])
        self.n_tasks = len(self.centers)

    def task_actions(self, states: np.ndarray, tasks: np.ndarray) -> np.ndarray:
        return (self.centers[tasks] - states[:, :2]) / STEP_SIZE
