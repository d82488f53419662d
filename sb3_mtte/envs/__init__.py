"""Multi-task environments: Meta-World v3 benchmarks and small toy benchmarks, one sub-env per task.

Every env built here follows the layout the algorithms of this package expect: sub-env i runs task i, its
observation is the task's state followed by the one-hot e_i (float32), ``info["task_index"]`` and
``info["is_success"]`` (success at any step of the episode) come with every step, and ``task_name`` is readable
with ``env.get_attr("task_name")``. A new goal variation is drawn at every reset from an RNG seeded by the
benchmark seed and the task index; ``env.env_method("set_eval_mode", True)`` cycles through them in order instead.

``backend="envpool"`` steps Meta-World's tasks through EnvPool's C++ port instead, for training only: its goals and
reward functions differ from the benchmark's, as :func:`env_protocol` records (:mod:`sb3_mtte.envs.envpool_envs`).

A single task is a valid multi-task env (``make_mt_env(["reach-v3"])``, or any gymnasium env wrapped in
:class:`OneHotTaskWrapper`): its observation ends with the one-hot ``[1.0]``.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import gymnasium as gym
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv

from sb3_mtte.common.utils import check_multitask_env, check_one_hot, did_you_mean, get_task_names
from sb3_mtte.envs.envpool_envs import (
    BACKENDS,
    ENVPOOL_ENV_KWARGS,
    EnvPoolVecEnv,
    backend_of,
    backend_protocol,
    check_backend,
    check_envpool_reward_function,
    envpool_vec_env_cls,
    make_envpool_env_fns,
)
from sb3_mtte.envs.metaworld_envs import (
    METAWORLD_BENCHMARKS,
    METAWORLD_ENV_KWARGS,
    MT10_TASKS,
    MT20_TASKS,
    MT25_TASKS,
    MT50_TASKS,
    REWARD_FUNCTION_VERSIONS,
    MetaWorldExpertPolicy,
    check_reward_function_version,
    make_metaworld_env_fns,
    metaworld_task_names,
)
from sb3_mtte.envs.toy import TOY_BENCHMARKS, TOY_ENV_KWARGS, ToyOraclePolicy, make_toy_env_fns, parse_toy_name
from sb3_mtte.envs.wrappers import MultiTaskWrapper, OneHotTaskWrapper

BenchmarkSpec = str | Sequence[str]
"""A benchmark name ("MT10", "MT25", a toy name, "reach-v3_push-v3") or a list of Meta-World v3 env names."""


def _valid_names() -> str:
    return (
        f"{sorted(METAWORLD_BENCHMARKS)}, {sorted(TOY_BENCHMARKS)} (optionally '-N'), or Meta-World v3 env names "
        "(sb3_mtte.envs.MT50_TASKS) in a list or joined by '_'"
    )


def make_env_fns(benchmark: BenchmarkSpec, seed: int = 0, **kwargs: Any) -> list[Callable[[], gym.Env]]:
    """One constructor per task (constructor i builds sub-env i), for any VecEnv class or a launcher.

    :param benchmark: see :func:`make_mt_env`.
    :param seed: benchmark seed.
    :param kwargs: see :func:`make_mt_env`.
    :raises ValueError: for an unknown benchmark or env name, or no task at all.
    """
    env_fns = _env_fns(benchmark, seed, **kwargs)
    if not env_fns:
        raise ValueError(f"A multi-task env needs at least 1 task; {benchmark!r} has none.")
    return env_fns


def _is_toy(benchmark: BenchmarkSpec) -> bool:
    return isinstance(benchmark, str) and parse_toy_name(benchmark) is not None


def env_kwargs_names(benchmark: BenchmarkSpec, backend: str = BACKENDS[0]) -> tuple[str, ...]:
    """The keyword arguments of :func:`make_mt_env` that build ``benchmark``'s sub-envs with ``backend``."""
    if _is_toy(benchmark):
        return ("n_tasks", *TOY_ENV_KWARGS)
    if check_backend(backend) == "envpool":
        return ("n_tasks", *ENVPOOL_ENV_KWARGS, "backend")
    return ("n_tasks", *METAWORLD_ENV_KWARGS, "backend")


def check_env_kwargs(benchmark: BenchmarkSpec, env_kwargs: Mapping[str, Any] | None) -> None:
    """Refuse a keyword argument that ``benchmark``'s envs do not take, naming the nearest valid one.

    :raises TypeError: for an unknown keyword (``ValueError`` for a reward function or backend the benchmark lacks).
    """
    reward_function_version(benchmark, env_kwargs)
    backend = backend_of(env_kwargs)
    valid = env_kwargs_names(benchmark, backend)
    where = f"{benchmark!r}" if backend == BACKENDS[0] else f"{benchmark!r} with backend={backend!r}"
    for key in env_kwargs or {}:
        if key == "backend" and _is_toy(benchmark):
            raise ValueError(f"backend picks what steps Meta-World's tasks: leave it out for {benchmark!r}.")
        if key not in valid:
            hint = did_you_mean(key, valid)
            raise TypeError(
                f"{key} is not an env keyword argument of {where}: {hint + ' ' if hint else ''}valid: "
                f"{', '.join(valid)}."
            )


def _env_fns(benchmark: BenchmarkSpec, seed: int, **kwargs: Any) -> list[Callable[[], gym.Env]]:
    check_env_kwargs(benchmark, kwargs)
    n_tasks = kwargs.pop("n_tasks", None)
    backend = kwargs.pop("backend", BACKENDS[0])
    if isinstance(benchmark, str):
        toy = parse_toy_name(benchmark, n_tasks)
        if toy is not None:
            return make_toy_env_fns(toy[0], seed=seed, n_tasks=toy[1], **kwargs)
        task_names = metaworld_task_names(benchmark)
        if task_names is None:
            raise ValueError(f"Unknown benchmark {benchmark!r}; valid: {_valid_names()}.")
    else:
        task_names = list(benchmark)
    if n_tasks is not None and n_tasks != len(task_names):
        raise ValueError(f"n_tasks does not match the {len(task_names)} tasks of {benchmark!r}.")
    if backend == "envpool":
        return make_envpool_env_fns(task_names, seed=seed, **kwargs)
    return make_metaworld_env_fns(task_names, seed=seed, **kwargs)


def reward_function_version(benchmark: BenchmarkSpec, env_kwargs: Mapping[str, Any] | None = None) -> str | None:
    """The Meta-World reward function that ``env_kwargs`` (keyword arguments of :func:`make_mt_env`) select for
    ``benchmark``, Meta-World's default ``"v2"`` when they name none; None for a toy benchmark.

    :raises ValueError: for a version Meta-World does not have, one EnvPool does not have (``"v1"`` with
        ``backend="envpool"``), or one given to a toy benchmark.
    """
    kwargs = env_kwargs or {}
    if not _is_toy(benchmark):
        version = check_reward_function_version(kwargs.get("reward_function_version", REWARD_FUNCTION_VERSIONS[0]))
        if backend_of(kwargs) == "envpool":
            check_envpool_reward_function(version)
        return version
    if "reward_function_version" in kwargs:
        raise ValueError(f"reward_function_version is a Meta-World option: leave it out for {benchmark!r}.")
    return None


def env_protocol(benchmark: BenchmarkSpec, env_kwargs: Mapping[str, Any] | None = None) -> dict[str, Any] | None:
    """How the envs that ``env_kwargs`` (keyword arguments of :func:`make_mt_env`) select for ``benchmark`` differ
    from Meta-World's benchmark, JSON-friendly (:func:`~sb3_mtte.envs.envpool_envs.backend_protocol`); None for a
    toy benchmark.

    ``label`` names the backend in plots and tables; ``benchmark_protocol`` is False for ``backend="envpool"``,
    whose ``differences`` are: fresh goals at every reset, the v2 reward functions only, Meta-World v3.0.0's source.

    :raises ValueError: for an unknown backend.
    """
    return None if _is_toy(benchmark) else backend_protocol(backend_of(env_kwargs))


def official_env_kwargs(env_kwargs: Mapping[str, Any] | None) -> dict[str, Any]:
    """``env_kwargs`` without ``backend``: the envs of the benchmark's official evaluation (Meta-World's own)."""
    return {key: value for key, value in (env_kwargs or {}).items() if key != "backend"}


def make_mt_env(
    benchmark: BenchmarkSpec,
    seed: int = 0,
    vec_env_cls: type[VecEnv] = DummyVecEnv,
    vec_env_kwargs: dict[str, Any] | None = None,
    monitor: bool = True,
    backend: str = BACKENDS[0],
    **kwargs: Any,
) -> VecEnv:
    """Build a multi-task VecEnv: sub-env i runs task i and observes its state followed by the one-hot e_i.

    :param benchmark: ``"MT10"``, ``"MT20"``, ``"MT25"``, ``"MT50"``, a list of Meta-World v3 env names (or the
        names joined by ``"_"``: ``"reach-v3_push-v3"``), or a toy benchmark (``"toy-conflict"``, ``"toy-agree"``,
        optionally with the task count: ``"toy-conflict-6"``).
    :param seed: seed of the goal variations, of their sampling at every reset and of the envs: the same seed
        gives the same episodes for the same actions.
    :param vec_env_cls: SB3 VecEnv class (``DummyVecEnv`` or ``SubprocVecEnv``).
    :param vec_env_kwargs: keyword arguments of ``vec_env_cls`` (e.g. ``start_method`` for ``SubprocVecEnv``).
    :param monitor: wrap each sub-env in SB3's ``Monitor`` (episode return and length in ``info["episode"]``).
    :param backend: what steps Meta-World's tasks: ``"metaworld"`` (Meta-World's own envs, the benchmark) or
        ``"envpool"`` (EnvPool's C++ port, for training only: :func:`env_protocol`). With ``"envpool"``,
        ``DummyVecEnv`` becomes :class:`~sb3_mtte.envs.envpool_envs.EnvPoolVecEnv`, whose pools step in parallel.
    :param kwargs: ``max_episode_steps`` (Meta-World 500, toy 50); ``render_mode`` (``"rgb_array"`` for video);
        for Meta-World ``reward_function_version`` (``"v2"``, the default, or ``"v1"``), ``camera_name``,
        ``camera_id``, ``width``, ``height``; for toys ``n_tasks`` (default 4). ``backend="envpool"`` takes
        ``max_episode_steps`` and ``reward_function_version="v2"`` only.
    :raises ValueError: for an unknown benchmark, env name or backend, or an env that breaks the multi-task layout.
    :raises ImportError: for ``backend="envpool"`` without EnvPool installed.
    """
    if check_backend(backend) != BACKENDS[0]:
        kwargs["backend"] = backend
        vec_env_cls = envpool_vec_env_cls(vec_env_cls)
    env_fns = make_env_fns(benchmark, seed=seed, **kwargs)
    if monitor:
        env_fns = [_monitored(fn) for fn in env_fns]
    env = vec_env_cls(env_fns, **(vec_env_kwargs or {}))
    try:
        n_tasks = check_multitask_env(env, len(env_fns))
        check_one_hot(env.reset(), n_tasks)
    except Exception:
        env.close()
        raise
    return env


class _monitored:
    """Picklable constructor that wraps another one's env in SB3's ``Monitor``."""

    def __init__(self, env_fn: Callable[[], gym.Env]) -> None:
        self.env_fn = env_fn

    def __call__(self) -> gym.Env:
        return Monitor(self.env_fn())


__all__ = [
    "BACKENDS",
    "METAWORLD_BENCHMARKS",
    "MT10_TASKS",
    "MT20_TASKS",
    "MT25_TASKS",
    "MT50_TASKS",
    "REWARD_FUNCTION_VERSIONS",
    "TOY_BENCHMARKS",
    "BenchmarkSpec",
    "EnvPoolVecEnv",
    "MetaWorldExpertPolicy",
    "MultiTaskWrapper",
    "OneHotTaskWrapper",
    "ToyOraclePolicy",
    "check_env_kwargs",
    "env_kwargs_names",
    "env_protocol",
    "get_task_names",
    "make_env_fns",
    "make_mt_env",
    "official_env_kwargs",
    "reward_function_version",
]
