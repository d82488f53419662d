"""The per-task log keys of MTSAC (and MTSACTE): critic losses and rollout success of every task."""

from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np

from sb3_mtte.common.utils import task_log_key

CRITIC_LOSS_KEY = "train/critic_loss"
"""The mean of the tasks' soft Bellman errors; ``<key>/<i>_<task>`` each task's."""
CLIP_FRACTION_KEY = "train/q_loss_clip_fraction"
"""The share of samples the clip of Eq. 16 dropped, averaged over the updates between two dumps."""
MEAN_STATS = ("q_loss_clip_fraction",)
"""The update statistics logged as their mean between two dumps (the others: the last update's)."""


class PerTaskLogMixin:
    """Records ``train/critic_loss/<i>_<task>`` and ``rollout/success/<i>_<task>`` beside SB3's keys.

    Success comes from the ``is_success`` of finished episodes, per task (``info["task_index"]``, else the sub-env),
    over SB3's ``stats_window_size``.
    """

    n_tasks: int
    task_names: list[str]
    _task_success: list[deque]
    num_timesteps: int

    def _record_train_stats(self, stats: dict[str, np.ndarray]) -> None:
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("train/actor_loss", float(stats["actor_loss"]))
        self.logger.record(CRITIC_LOSS_KEY, float(stats["critic_loss"].mean()))
        self.logger.record("train/ent_coef", float(stats["ent_coef"].mean()))
        if "ent_coef_loss" in stats:
            self.logger.record("train/ent_coef_loss", float(stats["ent_coef_loss"]))
        if "q_loss_clip_fraction" in stats:
            self.logger.record_mean(CLIP_FRACTION_KEY, float(stats["q_loss_clip_fraction"].mean()))
        for i in range(self.n_tasks):
            self.logger.record(task_log_key(CRITIC_LOSS_KEY, i, self._task_name(i)), float(stats["critic_loss"][i]))

    def _task_name(self, index: int) -> str | None:
        return self.task_names[index] if index < len(self.task_names) else None

    def _update_info_buffer(self, infos: list[dict[str, Any]], dones: np.ndarray | None = None) -> None:
        super()._update_info_buffer(infos, dones)
        if dones is None:
            return
        for index in np.flatnonzero(dones):
            success = infos[index].get("is_success")
            if success is not None:
                self._task_success[infos[index].get("task_index", index)].append(float(success))

    def dump_logs(self) -> None:
        """SB3's log dump, once per step: SB3 calls it for every finished episode that reaches a multiple of
        ``log_interval``, so several sub-envs ending at one step would print the same table two or three times."""
        if getattr(self, "_last_dump_timesteps", None) == self.num_timesteps:
            return
        self._last_dump_timesteps = self.num_timesteps
        for i, successes in enumerate(getattr(self, "_task_success", [])):
            if successes:
                self.logger.record(task_log_key("rollout/success", i, self._task_name(i)), float(np.mean(successes)))
        super().dump_logs()
