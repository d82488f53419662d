"""The multi-task side of an SB3 off-policy algorithm: one sub-env per task, per-task success logs, checkpoints
that carry the RNG states. The update itself is the subclass's (:class:`sb3_mtte.MTSAC`)."""

from __future__ import annotations

from collections import deque
from typing import Any, ClassVar

import numpy as np
import torch as th
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback
from stable_baselines3.common.vec_env import VecEnv

from sb3_mtte.common.buffers import MultiTaskReplayBuffer
from sb3_mtte.common.checkpoints import capture_rng_state, check_checkpoint, restore_rng_state
from sb3_mtte.common.update_monitor import UpdateMonitor
from sb3_mtte.common.utils import (
    check_multitask_env,
    check_not_gymnasium_vector_env,
    check_one_hot,
    get_task_names,
    task_log_key,
)

SUCCESS_KEY = "rollout/success"
"""``<key>/<i>_<task>``: the share of task i's last finished episodes that succeeded (SB3's ``stats_window_size``)."""


class MultiTaskOffPolicyAlgorithm(OffPolicyAlgorithm):
    """SB3's off-policy algorithm on a VecEnv with one sub-env per task (observation = state + one-hot).

    It checks the env's layout (:meth:`_setup_tasks`, :meth:`set_env`, the first observations of ``learn``), builds
    the replay buffer of one column per task lazily, records ``rollout/success/<i>_<task>`` beside SB3's keys, dumps
    the logs once per step and saves the RNG states with the model. Success comes from the ``is_success`` of
    finished episodes, per task (``info["task_index"]``, else the sub-env), over SB3's ``stats_window_size``.

    A subclass calls :meth:`_setup_tasks` once SB3's ``__init__`` has run, and builds :attr:`update_monitor` in its
    set-up.
    """

    min_tasks: ClassVar[int] = 1
    """Smallest task count N the algorithm accepts (1: a single task with the one-hot ``[1.0]`` is SAC)."""
    replay_buffer: MultiTaskReplayBuffer | None
    update_monitor: UpdateMonitor
    """What the updates leave for the host to read: read at every dump, checked at every save."""
    unsaved_attributes: ClassVar[tuple[str, ...]] = ("_task_success", "_last_dump_timesteps")
    """Attributes of this class that a checkpoint leaves out."""

    def _setup_tasks(self) -> None:
        """N and the task names from the env (none without an env, as in ``load(path, env=None)``)."""
        self.n_tasks = check_multitask_env(self.env, min_tasks=self.min_tasks) if self.env is not None else 0
        self.task_names: list[str] = get_task_names(self.env) if self.env is not None else []

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
        result = super()._setup_learn(total_timesteps, callback, reset_num_timesteps, tb_log_name, progress_bar)
        check_one_hot(self._last_obs, self.n_tasks)  # type: ignore[arg-type]
        if not hasattr(self, "_task_success") or reset_num_timesteps:
            self._task_success = [deque(maxlen=self._stats_window_size) for _ in range(self.n_tasks)]
        return result

    def set_env(self, env: GymEnv, force_reset: bool = True) -> None:
        check_not_gymnasium_vector_env(env)
        if isinstance(env, VecEnv):
            check_multitask_env(env, self.n_tasks, min_tasks=self.min_tasks)
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
        super().dump_logs()

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
        check_checkpoint(path, cls.__name__, n_tasks)
        model = super().load(path, env=env, device=device, **kwargs)
        rng_state = model.__dict__.pop("rng_state", None)
        if rng_state is not None:
            restore_rng_state(rng_state, model.action_space)
        return model
