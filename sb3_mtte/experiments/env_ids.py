"""Env ids of the benchmarks and the VecEnv "class" that makes sub-env i run task i.

Env ids ``MT10``, ``MT20``, ``MT25``, ``MT50``, ``DEV6`` (the development benchmark), ``toy-conflict``, ``toy-agree``
(and ``toy-conflict-<N>`` with N >= 2, ``toy-agree-<N>`` with N >= 1), any list of Meta-World v3 env names joined by
``_`` (``reach-v3_push-v3``), each also with a budget suffix (``MT10-smoke``): the suffix picks another entry of the
hyperparameter file and names the run folder, the benchmark is the same. rl-zoo builds every sub-env with the same
constructor; :class:`MultiTaskVecEnvFactory` (the role of ``ExperimentManager.default_vec_env_cls``, with rl-zoo's
``--vec-env`` choice inside) tells constructor i which task to build.
"""

from __future__ import annotations

import contextlib
import contextvars
import os
import signal
from collections.abc import Callable, Sequence
from typing import Any

import gymnasium as gym
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecEnv

from sb3_mtte.common.utils import did_you_mean
from sb3_mtte.envs import MT50_TASKS, TOY_BENCHMARKS, make_env_fns
from sb3_mtte.envs.metaworld_envs import TASK_LIST_SEPARATOR, is_task_list, metaworld_task_names
from sb3_mtte.envs.toy import parse_toy_name

BUDGET_SUFFIXES = ("smoke", "cpu", "100k")
"""Env-id suffixes that select another hyperparameter entry (``MT10-smoke``) for the same benchmark."""

STANDARD_BENCHMARKS = ("MT10", "MT20", "MT25", "MT50", "DEV6", "toy-conflict", "toy-agree")


def split_env_id(env_id: str) -> tuple[str, str | None]:
    """``"MT10-smoke"`` -> ``("MT10", "smoke")``; ``"MT10"`` -> ``("MT10", None)``."""
    for suffix in BUDGET_SUFFIXES:
        if env_id.endswith(f"-{suffix}"):
            return env_id[: -len(suffix) - 1], suffix
    return env_id, None


def benchmark_task_names(benchmark: str) -> list[str]:
    """Task names of a benchmark name (``"MT10"``, ``"toy-conflict-6"``, ``"reach-v3_push-v3"``, ...), without
    building any env.

    :raises ValueError: for an unknown benchmark (naming the nearest env id), a toy with too few tasks, or a task
        list with an unknown name (naming the nearest ones).
    """

    toy = parse_toy_name(benchmark)
    if toy is not None:
        if toy[1] < TOY_MIN_TASKS[toy[0]]:
            raise ValueError(_toy_count_problem(*toy))
        return TOY_BENCHMARKS[toy[0]](toy[1])[0]
    task_names = metaworld_task_names(benchmark)
    if task_names is not None:
        return task_names
    raise ValueError(f"Unknown benchmark {benchmark!r}: {benchmark_help(benchmark)}")


def env_id_n_tasks(env_id: str) -> int:
    """Number of tasks of the benchmark an env id names."""
    return len(benchmark_task_names(split_env_id(env_id)[0]))


TOY_MIN_TASKS = {"toy-conflict": 2, "toy-agree": 1}
"""The fewest tasks of each toy benchmark: ``toy-conflict`` needs a task that agrees and the one that conflicts."""


def _toy_count_problem(toy: str, n_tasks: int) -> str:
    return (
        f"{toy} has at least {TOY_MIN_TASKS[toy]} tasks, not {n_tasks}: give {toy}-<N> with N >= {TOY_MIN_TASKS[toy]}."
    )


def standard_env_ids() -> list[str]:
    """Every env id of :data:`STANDARD_BENCHMARKS`, each without and with every budget suffix."""
    return [f"{benchmark}{suffix}" for benchmark in STANDARD_BENCHMARKS for suffix in ("", *_SUFFIXES)]


_SUFFIXES = tuple(f"-{suffix}" for suffix in BUDGET_SUFFIXES)


def env_id_problem(env_id: str) -> str | None:
    """What is wrong with an env id that names no benchmark, in one sentence, or None when there is nothing to say
    beyond the valid forms: the nearest env id (``MT10-smok``: ``MT10-smoke``), the fewest tasks of a toy
    (``toy-conflict-1``), or the unknown names of a task list."""
    benchmark = split_env_id(env_id)[0]
    toy = parse_toy_name(benchmark)
    if toy is not None and toy[1] < TOY_MIN_TASKS[toy[0]]:
        return _toy_count_problem(*toy)
    if is_task_list(benchmark):
        try:
            metaworld_task_names(benchmark)
        except ValueError as error:
            return str(error)
    return did_you_mean(env_id, standard_env_ids()) or None


def benchmark_help(env_id: str | None = None) -> str:
    """The env ids the launcher accepts, in words; for an ``env_id`` that names no benchmark, what is wrong with it
    first (:func:`env_id_problem`): the nearest env id, a toy's fewest tasks, a task list's unknown names."""
    problem = None if env_id is None else env_id_problem(env_id)
    forms = (
        "MT10, MT20, MT25, MT50, DEV6, toy-conflict, toy-agree, toy-conflict-<N> (N >= 2), toy-agree-<N> (N >= 1) "
        "or Meta-World v3 env names joined by '_' (reach-v3_push-v3), optionally with a budget suffix "
        f"({', '.join(_SUFFIXES)})."
    )
    if problem is not None and is_task_list(split_env_id(env_id or "")[0]):
        return problem
    return forms if problem is None else f"{problem} The env ids: {forms}"


def env_id_of_tasks(task_names: Sequence[str]) -> str | None:
    """The benchmark whose tasks are ``task_names`` in this order (a checkpoint's), or None: a standard benchmark
    (``MT10``), a toy with its task count (``toy-conflict-6``; ``toy-conflict`` for the default 4), or Meta-World v3
    env names joined by ``_``."""
    names = list(task_names)
    for benchmark in STANDARD_BENCHMARKS:
        if benchmark_task_names(benchmark) == names:
            return benchmark
    for toy, minimum in TOY_MIN_TASKS.items():
        if len(names) >= minimum and TOY_BENCHMARKS[toy](len(names))[0] == names:
            return f"{toy}-{len(names)}"
    if names and all(name in MT50_TASKS for name in names) and len(set(names)) == len(names):
        return TASK_LIST_SEPARATOR.join(names)
    return None


_ENTRY_POINT = "sb3_mtte.experiments.env_ids:make_task_env"
_TASK_CONTEXT: contextvars.ContextVar[tuple[int, int] | None] = contextvars.ContextVar("sb3_mtte_task", default=None)


def make_task_env(benchmark: str, task_index: int | None = None, seed: int | None = None, **kwargs: Any) -> gym.Env:
    """Gymnasium entry point of the registered ids: sub-env ``task_index`` of ``benchmark``.

    Inside :class:`MultiTaskVecEnvFactory` the task index and the benchmark seed come from the sub-env's position;
    elsewhere pass ``task_index`` (and ``seed``) explicitly.

    :param benchmark: benchmark name.
    :param task_index: the task this env runs.
    :param seed: benchmark seed (goal variations); default: the factory's seed, else 0.
    :param kwargs: env keyword arguments of :func:`sb3_mtte.envs.make_mt_env` (``max_episode_steps``,
        ``render_mode``, ...).
    """

    context = _TASK_CONTEXT.get()
    if task_index is None:
        if context is None:
            raise gym.error.Error(
                f"{benchmark!r} is a multi-task benchmark with one sub-env per task: build it with "
                "sb3_mtte.envs.make_mt_env, with sb3-mtte train, or pass task_index=i."
            )
        task_index = context[0]
    if seed is None:
        seed = context[1] if context is not None else 0
    env_fns = make_env_fns(benchmark, seed=int(seed), **kwargs)
    return env_fns[task_index]()


def register_env_id(env_id: str) -> bool:
    """Register ``env_id`` (a benchmark name, optionally with a budget suffix) with gymnasium.

    :return: True when registered now or before, False when ``env_id`` is no benchmark of this package.
    """
    if env_id in gym.envs.registry:
        return gym.envs.registry[env_id].entry_point == _ENTRY_POINT
    benchmark = split_env_id(env_id)[0]
    try:
        benchmark_task_names(benchmark)
    except ValueError:
        return False
    gym.register(
        id=env_id,
        entry_point=_ENTRY_POINT,
        kwargs={"benchmark": benchmark},
        disable_env_checker=True,
    )
    return True


def register_standard_env_ids() -> None:
    """Register :data:`STANDARD_BENCHMARKS`, each with and without every budget suffix."""
    for benchmark in STANDARD_BENCHMARKS:
        register_env_id(benchmark)
        for suffix in BUDGET_SUFFIXES:
            register_env_id(f"{benchmark}-{suffix}")


class _TaskEnvFn:
    """Picklable constructor that builds sub-env ``task_index`` by calling a zoo env constructor in context; in a
    process of its own (``own_process``), that process leaves Ctrl-C to the command, which ends it by closing its
    pipe (a terminal sends Ctrl-C to every process of the command)."""

    def __init__(self, env_fn: Callable[[], gym.Env], task_index: int, seed: int, own_process: bool = False) -> None:
        self.env_fn, self.task_index, self.seed, self.own_process = env_fn, task_index, seed, own_process

    def __call__(self) -> gym.Env:
        if self.own_process:
            with contextlib.suppress(ValueError):  # signal handlers belong to the main thread
                signal.signal(signal.SIGINT, signal.SIG_IGN)
        token = _TASK_CONTEXT.set((self.task_index, self.seed))
        try:
            return self.env_fn()
        finally:
            _TASK_CONTEXT.reset(token)


SUBPROC_MIN_CORES = 4
"""The fewest cores on which Meta-World's tasks stepped in subprocesses beat stepping them one after another (env
stepping alone, MT10: no faster on 2 cores, 1.57x on 4; docs/results/gpu_profile.json)."""
SUBPROC_MAX_TASKS_PER_CORE = 4
"""The most tasks per core given a process each (measured up to 3.1: MT50 on 16 cores, 5.9x; every process holds
its own Python, torch and MuJoCo, about a quarter of a GB, and rl-zoo's eval env doubles them)."""


def default_vec_env(env_id: str, cpu_count: int | None = None) -> str:
    """rl-zoo's ``--vec-env`` when none is given: ``"subproc"`` (one process per task, stepped in parallel) for a
    Meta-World benchmark of several tasks on a machine with at least :data:`SUBPROC_MIN_CORES` cores and at most
    :data:`SUBPROC_MAX_TASKS_PER_CORE` tasks per core, else ``"dummy"`` (a toy's steps cost less than a message to a
    process)."""
    cores = os.cpu_count() if cpu_count is None else cpu_count
    if parse_toy_name(split_env_id(env_id)[0]) is not None:
        return "dummy"
    cores, n_tasks = cores or 1, env_id_n_tasks(env_id)
    parallel = n_tasks > 1 and cores >= SUBPROC_MIN_CORES and n_tasks <= SUBPROC_MAX_TASKS_PER_CORE * cores
    return "subproc" if parallel else "dummy"


class MultiTaskVecEnvFactory:
    """A VecEnv "class" for rl-zoo: given N constructors of the same registered env, sub-env i builds task i.

    :param n_tasks: number of tasks N; the zoo must ask for N sub-envs.
    :param seed: benchmark seed handed to every sub-env (goal variations).
    :param vec_env_cls: the VecEnv class that runs the sub-envs (rl-zoo's ``--vec-env`` choice).
    :param wrapper: what wraps the VecEnv built, e.g. ``enjoy``'s episode report; None: nothing.
    """

    def __init__(
        self,
        n_tasks: int,
        seed: int = 0,
        vec_env_cls: type[VecEnv] = DummyVecEnv,
        wrapper: Callable[[VecEnv], VecEnv] | None = None,
    ) -> None:
        self.n_tasks, self.seed, self.vec_env_cls = n_tasks, int(seed), vec_env_cls
        self.wrapper = wrapper

    def __call__(self, env_fns: Sequence[Callable[[], gym.Env]], **vec_env_kwargs: Any) -> VecEnv:
        if len(env_fns) != self.n_tasks:
            raise ValueError(
                f"This benchmark has {self.n_tasks} tasks and needs one sub-env per task; got {len(env_fns)} "
                f"sub-envs (use n_envs={self.n_tasks}, or --n-envs {self.n_tasks} for enjoy)."
            )
        own_process = isinstance(self.vec_env_cls, type) and issubclass(self.vec_env_cls, SubprocVecEnv)
        fns = [_TaskEnvFn(fn, i, self.seed, own_process) for i, fn in enumerate(env_fns)]
        env = self.vec_env_cls(fns, **vec_env_kwargs)  # type: ignore[arg-type]
        return env if self.wrapper is None else self.wrapper(env)
