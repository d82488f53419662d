"""The multi-task side of an SB3 off-policy algorithm: one sub-env per task, per-task success logs, checkpoints
that carry the RNG states. The update itself is the subclass's (:class:`sb3_mtte.MTSAC`)."""

from __future__ import annotations

import contextlib
from collections import deque
from collections.abc import Iterator
from typing import Any, ClassVar

import numpy as np
import torch as th
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, RolloutReturn, TrainFreq
from stable_baselines3.common.vec_env import VecEnv

from sb3_mtte.common.buffers import MultiTaskReplayBuffer
from sb3_mtte.common.checkpoints import (
    capture_rng_state,
    check_checkpoint,
    incomplete_checkpoint_error,
    restore_rng_state,
)
from sb3_mtte.common.overlapped_rollout import collect_overlapped, learn_overlapped
from sb3_mtte.common.update_monitor import UpdateMonitor
from sb3_mtte.common.utils import (
    check_multitask_env,
    check_not_gymnasium_vector_env,
    check_one_hot,
    env_fix,
    get_task_names,
    task_log_key,
)

SUCCESS_KEY = "rollout/success"
"""``<key>/<i>_<task>``: the share of task i's last finished episodes that succeeded (SB3's ``stats_window_size``)."""


class MultiTaskOffPolicyAlgorithm(OffPolicyAlgorithm):
    """SB3's off-policy algorithm on a VecEnv with one sub-env per task (observation = state + one-hot).

    It checks the env's layout at construction (:meth:`_setup_tasks`, :meth:`_check_first_observations`), in
    :meth:`set_env` and in the first observations of ``learn``. It builds the replay buffer of one column per task
    lazily, records ``rollout/success/<i>_<task>`` beside SB3's keys, dumps the logs once per step and saves the RNG
    states with the model. Success comes from the ``is_success`` of
    finished episodes, per task (``info["task_index"]``, else the sub-env), over SB3's ``stats_window_size``.

    A subclass calls :meth:`_setup_tasks` once SB3's ``__init__`` has run, builds :attr:`update_monitor` in its
    set-up, and calls :meth:`_check_first_observations` once its constructor has set the model up.
    """

    min_tasks: ClassVar[int] = 1
    """Smallest task count N the algorithm accepts (1: a single task with the one-hot ``[1.0]`` is SAC)."""
    replay_buffer: MultiTaskReplayBuffer | None
    update_monitor: UpdateMonitor
    """What the updates leave for the host to read: read at every dump, checked at every save."""
    unsaved_attributes: ClassVar[tuple[str, ...]] = (
        "_task_success",
        "_last_dump_timesteps",
        "_episodes_by_step_end",
        "_first_obs",
    )
    """Attributes of this class that a checkpoint leaves out."""
    overlap_env_step: bool = False
    """Whether each step's updates run between sending its actions and receiving its observations, so that they
    sample the transitions before that step (:mod:`~sb3_mtte.common.overlapped_rollout`); saved with the model."""

    def _setup_tasks(self) -> None:
        """N and the task names from the env (none without an env, as in ``load(path, env=None)``)."""
        self.n_tasks = check_multitask_env(self.env, min_tasks=self.min_tasks) if self.env is not None else 0
        self.task_names: list[str] = get_task_names(self.env) if self.env is not None else []
        if self.env is not None:
            check_declared_tasks(self.env, self.min_tasks)

    def _check_first_observations(self) -> None:
        """Refuse at construction an env whose first observations do not end with the one-hot e_i of sub-env i.

        Sub-envs that declare their tasks (:func:`check_declared_tasks`) were checked without a reset. Any other env
        is reset here, once, and the first ``learn`` starts from these observations instead of resetting it again.
        """
        if self.env is None or declares_tasks(self.env):
            return
        first_obs = self.env.reset()
        check_one_hot(first_obs, self.n_tasks)  # type: ignore[arg-type]
        self._first_obs = first_obs

    def _setup_replay_buffer(self) -> None:
        """Build the replay buffer (lazily, so ``load(path, env=None)`` allocates none)."""
        if self.replay_buffer is None:
            self.replay_buffer = self.replay_buffer_class(
                self.buffer_size,
                self.observation_space,
                self.action_space,
                device=self.device,
                n_envs=self.n_tasks,
                optimize_memory_usage=self.optimize_memory_usage,
                **self.replay_buffer_kwargs,
            )

    def _setup_learn(
        self,
        total_timesteps: int,
        callback: MaybeCallback = None,
        reset_num_timesteps: bool = True,
        tb_log_name: str = "run",
        progress_bar: bool = False,
    ):
        self._setup_replay_buffer()
        with _reset_returning(self.env, self.__dict__.pop("_first_obs", None)):
            result = super()._setup_learn(total_timesteps, callback, reset_num_timesteps, tb_log_name, progress_bar)
        check_one_hot(self._last_obs, self.n_tasks)  # type: ignore[arg-type]
        if not hasattr(self, "_task_success") or reset_num_timesteps:
            self._task_success = [deque(maxlen=self._stats_window_size) for _ in range(self.n_tasks)]
        return result

    def learn(
        self,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str = "run",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ):
        """SB3's ``learn``; with :attr:`overlap_env_step` the updates run inside the rollouts."""
        arguments = (total_timesteps, callback, log_interval, tb_log_name, reset_num_timesteps, progress_bar)
        if self.overlap_env_step:
            return learn_overlapped(self, *arguments)
        return super().learn(*arguments)

    def collect_rollouts(
        self,
        env: VecEnv,
        callback: BaseCallback,
        train_freq: TrainFreq,
        replay_buffer: ReplayBuffer,
        action_noise: ActionNoise | None = None,
        learning_starts: int = 0,
        log_interval: int | None = None,
    ) -> RolloutReturn:
        """SB3's rollout; with :attr:`overlap_env_step` its last step updates while the envs step."""
        arguments = (env, callback, train_freq, replay_buffer, action_noise, learning_starts, log_interval)
        if self.overlap_env_step:
            return collect_overlapped(self, *arguments)
        return super().collect_rollouts(*arguments)

    def set_env(self, env: GymEnv, force_reset: bool = True) -> None:
        check_not_gymnasium_vector_env(env)
        if isinstance(env, VecEnv):
            check_multitask_env(env, self.n_tasks, min_tasks=self.min_tasks)
            check_declared_tasks(env, self.min_tasks)
        self.__dict__.pop("_first_obs", None)
        super().set_env(env, force_reset)
        self.task_names = get_task_names(self.env)  # type: ignore[arg-type]

    # ------------------------------------------------------------------------------------------------- logs
    def _task_name(self, index: int) -> str | None:
        return self.task_names[index] if index < len(self.task_names) else None

    def _update_info_buffer(self, infos: list[dict[str, Any]], dones: np.ndarray | None = None) -> None:
        """SB3's, then the success of every finished episode in its task's window."""
        super()._update_info_buffer(infos, dones)
        if dones is None:
            return
        self._episodes_by_step_end = (self.num_timesteps, self._episode_num + int(np.count_nonzero(dones)))
        for index in np.flatnonzero(dones):
            success = infos[index].get("is_success")
            if success is not None:
                self._task_success[infos[index].get("task_index", index)].append(float(success))

    def dump_logs(self) -> None:
        """Read the update monitor (a non-finite loss stops training here at the latest), then SB3's dump with every
        task's success, once per step: SB3 calls it for every finished episode that reaches a multiple of
        ``log_interval``, so several sub-envs ending at one step would print the same table two or three times."""
        self.update_monitor.read()
        if getattr(self, "_last_dump_timesteps", None) == self.num_timesteps:
            return
        self._last_dump_timesteps = self.num_timesteps
        for i, successes in enumerate(getattr(self, "_task_success", [])):
            if successes:
                self.logger.record(task_log_key(SUCCESS_KEY, i, self._task_name(i)), float(np.mean(successes)))
        episodes_counted = self._episode_num
        self._episode_num = self._episodes_at_step_end()
        try:
            super().dump_logs()  # its time/episodes: every episode that ends at this step, of every sub-env
        finally:
            self._episode_num = episodes_counted

    def _episodes_at_step_end(self) -> int:
        """The episodes finished by the end of this step. SB3 counts a step's finished episodes one by one, and may
        dump the logs after the first: with several sub-envs, ``_episode_num`` then lacks the rest."""
        step, episodes = getattr(self, "_episodes_by_step_end", (None, 0))
        return max(self._episode_num, episodes) if step == self.num_timesteps else self._episode_num

    # ------------------------------------------------------------------------------------------ save / load
    def save(self, path, exclude=None, include=None) -> None:
        """Save the model; the RNG states are saved with it so that a resumed run continues exactly."""
        self.update_monitor.check()
        self.rng_state = capture_rng_state(self.action_space)
        try:
            super().save(path, exclude=exclude, include=include)
        finally:
            del self.rng_state

    @classmethod
    def load(cls, path, env: GymEnv | None = None, device: th.device | str = "auto", **kwargs):  # type: ignore[override]
        """Load a model saved by this class; a checkpoint of another algorithm or task count raises ValueError.

        ``env=None`` is enough for prediction and evaluation: no replay buffer is allocated. The RNG states saved
        with the model are restored, so training resumed from a model and its replay buffer continues as if it
        had never stopped (CPU).
        """
        n_tasks = env.num_envs if isinstance(env, VecEnv) else None
        problem = incomplete_checkpoint_error(path)
        if problem is not None:
            raise ValueError(problem)
        check_checkpoint(path, cls.__name__, n_tasks)
        model = super().load(path, env=env, device=device, **kwargs)
        rng_state = model.__dict__.pop("rng_state", None)
        if rng_state is not None:
            restore_rng_state(rng_state, model.action_space)
        return model


# ------------------------------------------------------------------------------------------------ env layout
def declares_tasks(env: VecEnv) -> bool:
    """Whether every sub-env declares its task with ``task_index`` and ``n_tasks``, as the package's wrappers do."""
    return env.has_attr("task_index") and env.has_attr("n_tasks")


def check_declared_tasks(env: VecEnv, min_tasks: int = 1) -> None:
    """Check the task each sub-env declares, without a reset: sub-env i must be task i of N tasks, N the sub-env
    count. An env whose sub-envs declare none passes (its first observations are checked instead).

    :raises ValueError: naming the first sub-env that breaks the layout.
    """
    if not declares_tasks(env):
        return
    n_envs = env.num_envs
    for i, (index, n_tasks) in enumerate(zip(env.get_attr("task_index"), env.get_attr("n_tasks"), strict=True)):
        if (index, n_tasks) != (i, n_envs):
            raise ValueError(
                f"Sub-env {i} observes the one-hot of task {index} of {n_tasks}, but sub-env i must observe the "
                f"one-hot e_i of N = {n_envs} tasks, one sub-env per task: {env_fix(n_envs, min_tasks)}."
            )


@contextlib.contextmanager
def _reset_returning(env: VecEnv | None, first_obs: Any) -> Iterator[None]:
    """While open, ``env.reset()`` returns ``first_obs`` (the observations of a reset already made) unless it is
    None."""
    if env is None or first_obs is None:
        yield
        return
    env.reset = lambda: first_obs  # type: ignore[method-assign]
    try:
        yield
    finally:
        del env.reset
