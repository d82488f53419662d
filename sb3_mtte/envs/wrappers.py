"""The wrappers that turn one single-task env into sub-env i of a multi-task benchmark.

:class:`MultiTaskWrapper` gives every sub-env the same contract, for Meta-World and the toy envs alike:

- observation = the env's state (float32) followed by the N-dim one-hot of the task;
- a goal variation drawn at every reset from a seeded RNG, or cycled in order in evaluation mode;
- ``info["task_index"]`` and ``info["is_success"]`` (success at any step of the episode so far) every step;
- attributes ``task_name`` and ``task_index``, readable with ``VecEnv.get_attr``;
- optional termination at the first success (Meta-World's evaluation protocol does this; the success of an
  episode is the same, and evaluation is faster).

:class:`OneHotTaskWrapper` applies the same contract to any gymnasium env with a flat Box observation, e.g.
``Pendulum-v1`` as a 1-task env (observation = state followed by ``[1.0]``) for MTSAC.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, SupportsFloat

import gymnasium as gym
import numpy as np
from gymnasium import spaces


class MultiTaskWrapper(gym.Wrapper):
    """Sub-env ``task_index`` of an ``n_tasks``-task benchmark.

    :param env: the single-task env (state observation, a flat Box).
    :param task_index: index i of the task; the observation ends with the one-hot e_i.
    :param n_tasks: number of tasks N of the benchmark (size of the one-hot).
    :param task_name: the task's name, e.g. ``"reach-v3"``.
    :param n_goals: number of goal variations of the task.
    :param set_goal: called with a goal-variation index in ``[0, n_goals)`` before every reset.
    :param state_space: bounds of the state part of the observation; the env's observation space when None.
    :param seed: seed of the goal-variation RNG and of the env (passed to ``env.unwrapped.seed`` when the env
        has that method, else to the env's next ``reset``).
    :param success_key: key of the per-step success flag in the env's info dict; None when the env has no
        success flag (then ``info["is_success"]`` is not reported).
    """

    def __init__(
        self,
        env: gym.Env,
        task_index: int,
        n_tasks: int,
        task_name: str,
        n_goals: int,
        set_goal: Callable[[int], None],
        state_space: spaces.Box | None = None,
        seed: int | None = None,
        success_key: str | None = "success",
    ) -> None:
        super().__init__(env)
        if not 0 <= task_index < n_tasks:
            raise ValueError(f"task_index must lie in [0, {n_tasks}), got {task_index}.")
        state_space = state_space if state_space is not None else env.observation_space
        if not isinstance(state_space, spaces.Box) or len(state_space.shape) != 1:
            raise ValueError(f"The single-task env needs a flat Box state, got {state_space}.")
        self.task_index = task_index
        self.n_tasks = n_tasks
        self.task_name = task_name
        self.n_goals = n_goals
        self.success_key = success_key
        self._set_goal = set_goal
        self._one_hot = np.zeros(n_tasks, dtype=np.float32)
        self._one_hot[task_index] = 1.0
        low = np.concatenate([state_space.low.astype(np.float32), np.zeros(n_tasks, dtype=np.float32)])
        high = np.concatenate([state_space.high.astype(np.float32), np.ones(n_tasks, dtype=np.float32)])
        self.observation_space = spaces.Box(low, high, dtype=np.float32)
        self.eval_mode = False
        self.terminate_on_success = False
        self.goal_index = -1
        self._eval_resets = 0
        self._success = False
        self._pending_seed: int | None = None
        self._goal_rng = np.random.default_rng(seed)
        if seed is not None:
            self.reseed(seed)

    def reseed(self, seed: int) -> None:
        """Seed the goal-variation RNG and the underlying env.

        An env with a ``seed`` method (Meta-World, the toys) is seeded now; any other gymnasium env is seeded by
        its next ``reset(seed=...)``.

        :param seed: the seed.
        """
        self._goal_rng = np.random.default_rng(seed)
        seed_fn = getattr(self.env.unwrapped, "seed", None)
        if callable(seed_fn):
            seed_fn(int(seed))
        else:
            self._pending_seed = int(seed)
        self.action_space.seed(int(seed))

    def set_eval_mode(self, enabled: bool) -> None:
        """Switch between random goal variations (training) and a deterministic cycle (evaluation).

        In evaluation mode, reset k after switching on uses goal variation ``k mod n_goals``.

        :param enabled: True for the evaluation cycle, False for random goal variations.
        """
        self.eval_mode = bool(enabled)
        self._eval_resets = 0

    def set_terminate_on_success(self, enabled: bool) -> None:
        """End episodes (``terminated=True``) at their first successful step; off by default.

        :param enabled: whether to terminate on success.
        """
        self.terminate_on_success = bool(enabled)

    def _next_goal(self) -> int:
        if self.eval_mode:
            goal = self._eval_resets % self.n_goals
            self._eval_resets += 1
            return goal
        return int(self._goal_rng.integers(self.n_goals))

    def _observation(self, state: np.ndarray) -> np.ndarray:
        return np.concatenate([np.asarray(state, dtype=np.float32), self._one_hot])

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        """Reset to a new goal variation; a given ``seed`` reseeds the goal RNG and the env first.

        :param seed: optional seed (SB3's ``VecEnv.seed`` passes one per sub-env).
        :param options: passed on to the env.
        """
        if seed is not None:
            self.reseed(seed)
        self.goal_index = self._next_goal()
        self._set_goal(self.goal_index)
        self._success = False
        state, info = self.env.reset(seed=self._pending_seed, options=options)
        self._pending_seed = None
        info = dict(info, task_index=self.task_index, goal_index=self.goal_index)
        return self._observation(state), info

    def step(self, action: np.ndarray) -> tuple[np.ndarray, SupportsFloat, bool, bool, dict]:
        """Step the env, adding ``task_index`` and, with a ``success_key``, ``is_success`` (success at any step so
        far) to the info."""
        state, reward, terminated, truncated, info = self.env.step(action)
        info = dict(info, task_index=self.task_index)
        if self.success_key is not None:
            self._success = self._success or bool(info.get(self.success_key, False))
            info["is_success"] = self._success
        if self.terminate_on_success and self._success:
            terminated = True
        return self._observation(state), float(reward), bool(terminated), bool(truncated), info

    def render(self) -> Any:
        """The env's frame, drawn in its own OpenGL context.

        Gymnasium's ``MujocoRenderer`` makes its context current only when it holds several viewers; with one env
        per task in a process, every task would otherwise draw with the context created last (another task's
        meshes and buffers).
        """
        viewer = getattr(getattr(self.env.unwrapped, "mujoco_renderer", None), "viewer", None)
        if viewer is not None:
            viewer.make_context_current()
        return self.env.render()


def _single_goal(index: int) -> None:
    """Goal setter of an env without goal variations."""


class OneHotTaskWrapper(MultiTaskWrapper):
    """A plain gymnasium env as task ``task_index`` of an ``n_tasks``-task env; by default its only task.

    The observation is the env's state followed by the one-hot e_i (``[1.0]`` for a single task, so that
    ``Pendulum-v1`` becomes a 1-task env for MTSAC), ``info["task_index"]`` comes with every step, and
    ``info["is_success"]`` too when the env reports a success flag under ``success_key``. The env has a single
    goal variation; ``reset(seed=...)`` seeds it as gymnasium does.

    :param env: the single-task env (flat Box observation).
    :param task_index: index i of the task.
    :param n_tasks: number of tasks N (size of the one-hot).
    :param task_name: the task's name; the env's id (or class name) when None.
    :param success_key: key of the env's per-step success flag in its info dict, or None when it has none.
    """

    def __init__(
        self,
        env: gym.Env,
        task_index: int = 0,
        n_tasks: int = 1,
        task_name: str | None = None,
        success_key: str | None = None,
    ) -> None:
        if task_name is None:
            task_name = env.spec.id if env.spec is not None else type(env.unwrapped).__name__
        super().__init__(
            env,
            task_index=task_index,
            n_tasks=n_tasks,
            task_name=task_name,
            n_goals=1,
            set_goal=_single_goal,
            success_key=success_key,
        )
