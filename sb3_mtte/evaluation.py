"""Success-rate evaluation of a multi-task policy, following Meta-World's official protocol.

Each task runs ``episodes_per_task`` episodes, one per goal variation in order (the env is put in evaluation
mode, which cycles goal variations deterministically), with deterministic actions by default. An episode is a
success when the task was solved at any step; a task's success rate is the fraction of its successful episodes,
and the benchmark score is the mean of the per-task rates. All sub-envs step in lock-step; a sub-env that has
finished its quota keeps stepping, but its further episodes are not counted.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.vec_env import VecEnv

from sb3_mtte.common.update_monitor import record_train_stats
from sb3_mtte.common.utils import check_multitask_env, check_positive_int, get_task_names, task_log_key


class Predictor(Protocol):
    """Anything with SB3's ``predict`` signature (an SB3 model, a policy, a scripted controller)."""

    def predict(
        self,
        observation: np.ndarray,
        state: Any = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = False,
    ) -> tuple[np.ndarray, Any]: ...


@dataclass
class SuccessResult:
    """Per-task success rates of one evaluation.

    :param task_names: the task names, in task order.
    :param success_rate: success rate of each task, shape (N,).
    :param mean: mean of the per-task rates.
    :param episodes_per_task: number of episodes each rate is computed from.
    """

    task_names: list[str]
    success_rate: np.ndarray
    mean: float = field(init=False)
    episodes_per_task: int = 0

    def __post_init__(self) -> None:
        self.success_rate = np.asarray(self.success_rate, dtype=np.float64)
        self.mean = float(self.success_rate.mean()) if self.success_rate.size else float("nan")

    def as_dict(self) -> dict[str, Any]:
        """JSON-friendly form: ``{"mean": m, "per_task": {name: rate}}``; a name that several tasks share is followed
        by each task's index, ``"Pendulum-v1 (task 1)"``, so that every task keeps its own key."""
        shared = {name for name in self.task_names if self.task_names.count(name) > 1}
        keys = [f"{name} (task {i})" if name in shared else name for i, name in enumerate(self.task_names)]
        per_task = {key: float(rate) for key, rate in zip(keys, self.success_rate, strict=True)}
        return {"mean": self.mean, "per_task": per_task}


def _set_eval_mode(env: VecEnv, enabled: bool, terminate_on_success: bool) -> bool:
    """Switch the sub-envs' goal cycling (and termination on success); False when the env has no eval mode."""
    if not env.has_attr("set_eval_mode"):
        return False
    env.env_method("set_eval_mode", enabled)
    if env.has_attr("set_terminate_on_success"):
        env.env_method("set_terminate_on_success", enabled and terminate_on_success)
    return True


def evaluate_success(
    model: Predictor,
    env_or_benchmark: VecEnv | str | list[str],
    episodes_per_task: int = 50,
    deterministic: bool = True,
    seed: int | None = None,
    terminate_on_success: bool = True,
    env_kwargs: dict[str, Any] | None = None,
    on_episode: Callable[[int], None] | None = None,
) -> SuccessResult:
    """Success rate of each task, Meta-World's official protocol (one episode per goal variation).

    :param model: anything with SB3's ``predict(obs, state, episode_start, deterministic)``, batched over the
        N sub-envs.
    :param env_or_benchmark: a VecEnv built by :func:`sb3_mtte.envs.make_mt_env` (reset here, switched to
        evaluation mode and back), or a benchmark spec to build one from (closed afterwards).
    :param episodes_per_task: episodes per task (50 = every goal variation once).
    :param deterministic: use deterministic actions.
    :param seed: seed of the env built from a spec (0 when None); for a given VecEnv, passed to ``env.seed``.
    :param terminate_on_success: end episodes at their first success, as Meta-World's evaluation does; the
        success rate is the same, and evaluation is faster.
    :param env_kwargs: keyword arguments of :func:`sb3_mtte.envs.make_mt_env` for the env built from a spec
        (``reward_function_version``: some Meta-World tasks measure success differently under ``"v1"``).
    :param on_episode: called with the task index at each counted episode (a progress display).
    :return: the per-task success rates and their mean.
    """
    if episodes_per_task < 1:
        raise ValueError(f"episodes_per_task must be >= 1, got {episodes_per_task}.")
    owns_env = not isinstance(env_or_benchmark, VecEnv)
    if owns_env:
        from sb3_mtte.envs import make_mt_env

        env = make_mt_env(env_or_benchmark, seed=0 if seed is None else seed, **(env_kwargs or {}))
    else:
        env = env_or_benchmark
        if seed is not None:
            env.seed(seed)
    try:
        n_tasks = check_multitask_env(env)
        _check_model_fits(model, env)
        if not _set_eval_mode(env, True, terminate_on_success):
            warnings.warn("The env has no evaluation mode (set_eval_mode): goal variations are not cycled.")
        try:
            rates = _run_episodes(model, env, n_tasks, episodes_per_task, deterministic, on_episode)
        finally:
            _set_eval_mode(env, False, terminate_on_success)
        return SuccessResult(get_task_names(env), rates, episodes_per_task=episodes_per_task)
    finally:
        if owns_env:
            env.close()


def _check_model_fits(model: Predictor, env: VecEnv) -> None:
    """Refuse an env whose observations the model was not trained on (another benchmark or number of tasks)."""
    space = getattr(model, "observation_space", None)
    if space is not None and space.shape != env.observation_space.shape:
        raise ValueError(
            f"The model takes observations of shape {space.shape}, this env gives {env.observation_space.shape} "
            f"({env.num_envs} tasks): evaluate it on the benchmark it was trained on."
        )


def _run_episodes(
    model: Predictor,
    env: VecEnv,
    n_tasks: int,
    episodes: int,
    deterministic: bool,
    on_episode: Callable[[int], None] | None = None,
) -> np.ndarray:
    """Step all sub-envs until each has finished ``episodes`` episodes; return each one's success fraction."""
    done_count = np.zeros(n_tasks, dtype=np.int64)
    success_count = np.zeros(n_tasks, dtype=np.int64)
    reported = np.zeros(n_tasks, dtype=bool)
    obs = env.reset()
    state = None
    episode_start = np.ones(n_tasks, dtype=bool)
    while (done_count < episodes).any():
        actions, state = model.predict(obs, state=state, episode_start=episode_start, deterministic=deterministic)
        obs, _, dones, infos = env.step(actions)
        for i in np.flatnonzero(dones):
            if done_count[i] < episodes:
                done_count[i] += 1
                success_count[i] += bool(infos[i].get("is_success", False))
                reported[i] |= "is_success" in infos[i]
                if on_episode is not None:
                    on_episode(int(i))
        episode_start = dones
    if not reported.all():
        silent = ", ".join(str(i) for i in np.flatnonzero(~reported))
        warnings.warn(
            f"Tasks {silent} report no is_success at the end of their episodes: their success counts as 0. "
            "Wrap such an env so that its info holds is_success (OneHotTaskWrapper's success_key names the info key).",
            stacklevel=3,
        )
    return success_count / episodes


class MultiTaskEvalCallback(BaseCallback):
    """Evaluate per-task success every ``eval_freq`` calls (vector steps) and log it.

    Logs ``eval/success_rate`` (mean over tasks) and one ``eval/success/<ii>_<task>`` key per task, and, when
    ``log_path`` is given, rewrites ``log_path/evaluations.npz`` with keys ``timesteps`` (T,),
    ``success_rate`` (T, N) and ``task_names`` (N,) after every evaluation.

    :param eval_env: a VecEnv built by :func:`sb3_mtte.envs.make_mt_env` or a benchmark spec to build one from.
    :param eval_freq: evaluate every this many calls of the callback (one per vector step); <= 0 disables.
    :param episodes_per_task: episodes per task of each evaluation.
    :param deterministic: use deterministic actions.
    :param log_path: folder of ``evaluations.npz``, or None.
    :param seed: seed of the env built from a spec.
    :param verbose: 1 prints a line per evaluation.
    """

    def __init__(
        self,
        eval_env: VecEnv | str | list[str],
        eval_freq: int = 10_000,
        episodes_per_task: int = 50,
        deterministic: bool = True,
        log_path: str | os.PathLike | None = None,
        seed: int | None = None,
        verbose: int = 0,
    ) -> None:
        super().__init__(verbose=verbose)
        check_positive_int("episodes_per_task (the zoo's --eval-episodes)", episodes_per_task, "10")
        if not isinstance(eval_env, VecEnv):
            from sb3_mtte.envs import make_mt_env

            eval_env = make_mt_env(eval_env, seed=0 if seed is None else seed)
        self.eval_env = eval_env
        self.eval_freq = eval_freq
        self.episodes_per_task = episodes_per_task
        self.deterministic = deterministic
        self.log_path = None if log_path is None else os.fspath(log_path)
        self.task_names = get_task_names(eval_env)
        self.evaluations_timesteps: list[int] = []
        self.evaluations_success: list[np.ndarray] = []
        self.last_result: SuccessResult | None = None

    def _init_callback(self) -> None:
        n_train = self.training_env.num_envs if self.training_env is not None else None
        check_multitask_env(self.eval_env, n_train)
        if self.log_path is not None:
            os.makedirs(self.log_path, exist_ok=True)

    def _on_step(self) -> bool:
        if self.eval_freq > 0 and self.n_calls % self.eval_freq == 0:
            self.evaluate()
        return True

    def evaluate(self) -> SuccessResult:
        """Run one evaluation now, log it and save it."""
        result = evaluate_success(self.model, self.eval_env, self.episodes_per_task, self.deterministic)
        self.last_result = result
        self.evaluations_timesteps.append(self.num_timesteps)
        self.evaluations_success.append(result.success_rate)
        self.logger.record("eval/success_rate", result.mean)
        for i, (name, rate) in enumerate(zip(result.task_names, result.success_rate, strict=True)):
            self.logger.record(task_log_key("eval/success", i, name), float(rate))
        if self.verbose >= 1:
            print(f"Eval num_timesteps={self.num_timesteps}, mean success rate={result.mean:.3f}")
        if self.log_path is not None:
            self.save_evaluations()
        self.logger.record("time/total_timesteps", self.num_timesteps, exclude="tensorboard")
        record_train_stats(self.model)
        self.logger.dump(self.num_timesteps)
        return result

    def save_evaluations(self) -> None:
        """Write every evaluation so far to ``<log_path>/evaluations.npz``, replacing the file in one step (a run
        killed while writing leaves the previous file whole)."""
        path = os.path.join(self.log_path, "evaluations.npz")  # type: ignore[arg-type]
        tmp = os.path.join(self.log_path, ".tmp_evaluations.npz")  # type: ignore[arg-type]
        np.savez(
            tmp,
            timesteps=np.asarray(self.evaluations_timesteps),
            success_rate=np.stack(self.evaluations_success),
            task_names=np.asarray(self.task_names),
        )
        os.replace(tmp, path)
