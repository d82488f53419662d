"""Meta-World v3 stepped natively through EnvPool: one single-env pool per task, for training only.

``make_mt_env(..., backend="envpool")`` builds the same multi-task VecEnv as Meta-World's own envs: sub-env i runs
task i, observes the 39-d state followed by the one-hot e_i, reports ``info["success"]`` and ``is_success`` every
step and is truncated at 500 steps. Each task's pool is EnvPool's C++ port of the task (task id
``MetaWorld/Reach-v3`` for ``reach-v3``). :class:`EnvPoolVecEnv` sends every task's action before it receives any
observation, so the pools step in parallel threads.

It is not Meta-World's benchmark, and :func:`env_protocol` says how (one source for run metadata and tables):

=================  ============================================  ==============================================
                   ``backend="metaworld"``                       ``backend="envpool"``
=================  ============================================  ==============================================
goals at reset     one of the task's 50 fixed variations          drawn fresh from the task's range
reward functions   ``"v2"`` and ``"v1"``                          ``"v2"`` only
source             the installed Meta-World release               Meta-World v3.0.0
evaluation         the official protocol                          refused: evaluate on Meta-World's envs
=================  ============================================  ==============================================

EnvPool is an extra: ``pip install "sb3-mtte[envpool]"``.
"""

from __future__ import annotations

import importlib.metadata
from collections.abc import Callable, Mapping, Sequence
from functools import partial
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.wrappers import TimeLimit
from stable_baselines3.common.vec_env import DummyVecEnv

from sb3_mtte.envs.metaworld_envs import REWARD_FUNCTION_VERSIONS, validate_task_names
from sb3_mtte.envs.wrappers import MultiTaskWrapper

BACKENDS = ("metaworld", "envpool")
"""What steps Meta-World's tasks (``backend``): Meta-World's own Python envs (the default) or EnvPool's C++ port."""

ENVPOOL_ENV_KWARGS = ("max_episode_steps", "reward_function_version")
"""Keyword arguments :func:`make_envpool_env_fns` accepts besides the seed (no rendering: training only)."""

ENVPOOL_REWARD_FUNCTION = REWARD_FUNCTION_VERSIONS[0]
"""The only reward functions EnvPool's Meta-World has (``"v2"``)."""

ENVPOOL_METAWORLD_SOURCE = "v3.0.0"
"""The Meta-World release whose source EnvPool's port follows."""

_STEP_INFO_KEYS = (
    "success",
    "near_object",
    "grasp_success",
    "grasp_reward",
    "in_place_reward",
    "obj_to_target",
    "unscaled_reward",
)
"""The per-step info of a Meta-World env, which EnvPool reports under the same names."""

_SEED_MODULUS = 2**31
"""EnvPool takes 32-bit signed seeds."""

_INSTALL_HINT = 'backend="envpool" needs EnvPool: pip install "sb3-mtte[envpool]".'
_EVALUATION_REFUSAL = (
    'EnvPool\'s Meta-World envs are for training only (fresh goals at every reset): evaluate on backend="metaworld".'
)


def check_backend(backend: Any) -> str:
    """``backend`` when it is one of :data:`BACKENDS`.

    :raises ValueError: otherwise.
    """
    if backend not in BACKENDS:
        raise ValueError(f"backend={backend!r} is not a backend: use {' or '.join(map(repr, BACKENDS))}.")
    return backend


def check_envpool_reward_function(version: str) -> None:
    """Refuse a reward function that EnvPool's Meta-World lacks.

    :raises ValueError: for anything but :data:`ENVPOOL_REWARD_FUNCTION`.
    """
    if version != ENVPOOL_REWARD_FUNCTION:
        raise ValueError(
            f"reward_function_version={version!r} is not in EnvPool's Meta-World, which has the "
            f'{ENVPOOL_REWARD_FUNCTION!r} reward functions only: leave it out or use backend="metaworld".'
        )


def _installed_version(distribution: str) -> str | None:
    try:
        return importlib.metadata.version(distribution)
    except importlib.metadata.PackageNotFoundError:
        return None


def backend_protocol(backend: str) -> dict[str, Any]:
    """How the tasks that ``backend`` steps differ from Meta-World's benchmark, JSON-friendly.

    Keys: ``backend``; ``label`` (a short name for plots and tables); ``benchmark_protocol`` (False when the
    training envs differ from the benchmark's); ``goals``, ``reward_functions``, ``source`` (each difference);
    ``official_evaluation`` (whether the envs run the benchmark's evaluation); ``differences`` (one sentence each,
    empty for Meta-World's own envs).
    """
    if check_backend(backend) == "metaworld":
        return {
            "backend": backend,
            "label": "Meta-World",
            "benchmark_protocol": True,
            "goals": "one of the task's 50 fixed goal variations, drawn at every reset",
            "reward_functions": list(REWARD_FUNCTION_VERSIONS),
            "source": f"Meta-World {_installed_version('metaworld')}",
            "official_evaluation": True,
            "differences": [],
        }
    return {
        "backend": backend,
        "label": f"EnvPool (fresh goals, {ENVPOOL_REWARD_FUNCTION} rewards, Meta-World {ENVPOOL_METAWORLD_SOURCE})",
        "benchmark_protocol": False,
        "goals": "drawn fresh from the task's range at every reset",
        "reward_functions": [ENVPOOL_REWARD_FUNCTION],
        "source": f"Meta-World {ENVPOOL_METAWORLD_SOURCE} in EnvPool {_installed_version('envpool')}",
        "official_evaluation": False,
        "differences": [
            "Each reset draws the goal and object positions fresh from the task's range, where the benchmark "
            "draws one of 50 fixed variations per task.",
            f"Only the {ENVPOOL_REWARD_FUNCTION} reward functions exist.",
            f"The tasks follow Meta-World {ENVPOOL_METAWORLD_SOURCE}'s source.",
        ],
    }


def envpool_task_id(task_name: str) -> str:
    """EnvPool's id of a Meta-World v3 task, as EnvPool names it: ``"reach-v3"`` -> ``"MetaWorld/Reach-v3"``."""
    from envpool.mujoco.metaworld.registration import metaworld_task_id

    return metaworld_task_id(task_name)


def require_envpool() -> None:
    """Import EnvPool's Meta-World registration.

    :raises ImportError: when EnvPool is not installed, naming the install.
    """
    try:
        import envpool.mujoco.metaworld.registration  # noqa: F401
    except ImportError as error:
        raise ImportError(_INSTALL_HINT) from error


def envpool_state_space() -> spaces.Box:
    """Bounds of the 39-d state, as Meta-World's envs give them here: hand and gripper bounded, the rest not."""
    from metaworld.sawyer_xyz_env import SawyerXYZEnv

    hand = SawyerXYZEnv._HAND_SPACE
    free = np.full(14, np.inf)
    low = np.hstack([hand.low, -1.0, -free, hand.low, -1.0, -free, np.full(3, -np.inf)])
    high = np.hstack([hand.high, 1.0, free, hand.high, 1.0, free, np.full(3, np.inf)])
    return spaces.Box(low, high, dtype=np.float64)


class EnvPoolTaskEnv(gym.Env):
    """One Meta-World v3 task as a gymnasium env, stepped by a single-env EnvPool pool.

    The pool is built at the first reset after :meth:`seed` (EnvPool fixes its seed when a pool is made).
    :meth:`send` starts a step that the next :meth:`step` with the same action completes.

    :param task_name: Meta-World v3 env name.
    :param max_episode_steps: the pool's truncation length.
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": []}

    def __init__(self, task_name: str, max_episode_steps: int = 500) -> None:
        require_envpool()
        self.task_name = task_name
        self.max_episode_steps = int(max_episode_steps)
        self.observation_space = envpool_state_space()
        self.action_space = spaces.Box(-1.0, 1.0, (4,), dtype=np.float32)
        self._seed = 0
        self._pool: Any = None
        self._sent: np.ndarray | None = None
        self._env_id = np.zeros(1, dtype=np.int32)

    def seed(self, seed: int) -> None:
        """Seed the next pool (built at the next reset): the same seed gives the same episodes."""
        self.close()
        self._seed = int(seed) % _SEED_MODULUS

    def _make_pool(self) -> Any:
        import envpool

        return envpool.make_gymnasium(
            envpool_task_id(self.task_name),
            num_envs=1,
            seed=self._seed,
            max_episode_steps=self.max_episode_steps,
            partially_observable=False,  # the goal in the observation, as Meta-World's multi-task benchmarks
        )

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        """Reset to goal and object positions drawn from the task's range."""
        if seed is not None:
            self.seed(seed)
        if self._pool is None:
            self._pool = self._make_pool()
        elif self._sent is not None:
            self._pool.recv()  # a step sent and never completed
        self._sent = None
        states, _ = self._pool.reset(self._env_id)
        return self._state(states), {}

    def send(self, action: np.ndarray) -> None:
        """Start a step; the next :meth:`step` completes it."""
        self._sent = np.clip(np.asarray(action, dtype=np.float32), -1.0, 1.0).reshape(1, 4)
        self._pool.send(self._sent, self._env_id)

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        """Complete the step :meth:`send` started (start it first when none was sent).

        :raises RuntimeError: when a wrapper changed the action after it was sent.
        """
        if self._sent is None:
            self.send(action)
        elif not np.array_equal(self._sent, np.clip(np.asarray(action, dtype=np.float32), -1.0, 1.0).reshape(1, 4)):
            raise RuntimeError("An env wrapper changed the action EnvPoolVecEnv sent: use DummyVecEnv instead.")
        self._sent = None
        states, _, terminated, truncated, pool_info = self._pool.recv()
        info = {key: float(pool_info[key][0]) for key in _STEP_INFO_KEYS}
        reward = info["unscaled_reward"]  # the reward in double precision, as Meta-World returns it
        return self._state(states), reward, bool(terminated[0]), bool(truncated[0]), info

    def _state(self, states: np.ndarray) -> np.ndarray:
        """Meta-World clips its observation to the hand's and gripper's bounds."""
        return np.clip(states[0], self.observation_space.low, self.observation_space.high)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.close()
        self._pool, self._sent = None, None


def _no_goal(index: int) -> None:
    """EnvPool's tasks have no fixed goal variations to set."""


class EnvPoolTaskWrapper(MultiTaskWrapper):
    """:class:`~sb3_mtte.envs.wrappers.MultiTaskWrapper` for an EnvPool task: no fixed goal variations
    (``goal_index`` is -1) and no evaluation mode."""

    def _next_goal(self) -> int:
        return -1

    def set_eval_mode(self, enabled: bool) -> None:
        """Refuse the evaluation mode: EnvPool draws every goal fresh, the benchmark's evaluation cycles 50.

        :raises ValueError: when ``enabled``.
        """
        if enabled:
            raise ValueError(_EVALUATION_REFUSAL)


def make_envpool_task_env(
    task_name: str,
    task_index: int,
    n_tasks: int,
    seed: int = 0,
    max_episode_steps: int | None = None,
    reward_function_version: str = ENVPOOL_REWARD_FUNCTION,
) -> gym.Env:
    """Sub-env ``task_index``: one EnvPool task, truncated, wrapped in :class:`EnvPoolTaskWrapper`.

    :param task_name: Meta-World v3 env name.
    :param task_index: index i of the task (one-hot e_i).
    :param n_tasks: number of tasks N.
    :param seed: benchmark seed; the pool gets a seed derived from it and the task index, as Meta-World's envs do.
    :param max_episode_steps: truncation length (Meta-World's 500 when None).
    :param reward_function_version: ``"v2"``, the only one EnvPool has.
    """
    check_envpool_reward_function(reward_function_version)
    steps = int(max_episode_steps or 500)
    return EnvPoolTaskWrapper(
        TimeLimit(EnvPoolTaskEnv(task_name, steps), steps),
        task_index=task_index,
        n_tasks=n_tasks,
        task_name=task_name,
        n_goals=1,
        set_goal=_no_goal,
        seed=int(np.random.SeedSequence([seed, task_index]).generate_state(1)[0]),
    )


def make_envpool_env_fns(task_names: Sequence[str], seed: int = 0, **kwargs: Any) -> list[Callable[[], gym.Env]]:
    """One EnvPool env constructor per task, in task order.

    :param task_names: Meta-World v3 env names.
    :param seed: benchmark seed.
    :param kwargs: any of :data:`ENVPOOL_ENV_KWARGS`.
    :raises ImportError: when EnvPool is not installed.
    """
    unknown = set(kwargs) - set(ENVPOOL_ENV_KWARGS)
    if unknown:
        raise TypeError(
            f'Unexpected keyword argument(s) {sorted(unknown)} for backend="envpool" (training only); valid: '
            f"{', '.join(ENVPOOL_ENV_KWARGS)}."
        )
    check_envpool_reward_function(kwargs.get("reward_function_version", ENVPOOL_REWARD_FUNCTION))
    require_envpool()
    names = validate_task_names(task_names)
    return [partial(make_envpool_task_env, name, i, len(names), seed, **kwargs) for i, name in enumerate(names)]


class EnvPoolVecEnv(DummyVecEnv):
    """``DummyVecEnv`` that sends every EnvPool task's action to its pool before it receives any.

    ``step_async`` sends, ``step_wait`` receives: work between them overlaps the env step. Any other sub-env (one
    of Meta-World's own, an evaluation env's) steps in ``step_wait`` as in ``DummyVecEnv``.

    :param env_fns: env constructors (:func:`make_envpool_env_fns`, optionally wrapped in ``Monitor``).
    """

    def __init__(self, env_fns: list[Callable[[], gym.Env]]) -> None:
        super().__init__(env_fns)
        self._pools = [env.unwrapped if isinstance(env.unwrapped, EnvPoolTaskEnv) else None for env in self.envs]

    def step_async(self, actions: np.ndarray) -> None:
        super().step_async(actions)
        for pool, action in zip(self._pools, self.actions, strict=True):
            if pool is not None:
                pool.send(action)


def envpool_vec_env_cls(vec_env_cls: type) -> type:
    """The VecEnv class that runs EnvPool tasks given the one asked for: :class:`EnvPoolVecEnv` for
    ``DummyVecEnv`` (the pools step in parallel threads), any other class as it is."""
    return EnvPoolVecEnv if vec_env_cls is DummyVecEnv else vec_env_cls


def backend_of(env_kwargs: Mapping[str, Any] | None) -> str:
    """The backend ``env_kwargs`` (keyword arguments of ``make_mt_env``) select, ``"metaworld"`` when none."""
    return check_backend((env_kwargs or {}).get("backend", BACKENDS[0]))
