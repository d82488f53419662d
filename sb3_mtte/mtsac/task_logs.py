"""The train log keys of MTSAC (and MTSACTE): SB3's, and the critic loss of every task."""

from __future__ import annotations

import numpy as np
from stable_baselines3.common.logger import Logger

from sb3_mtte.common.utils import task_log_key

CRITIC_LOSS_KEY = "train/critic_loss"
"""The mean of the tasks' soft Bellman errors; ``<key>/<i>_<task>`` each task's."""
CLIP_FRACTION_KEY = "train/q_loss_clip_fraction"
"""The share of samples the clip of Eq. 16 dropped, averaged over the updates between two dumps."""
MEAN_STATS = ("q_loss_clip_fraction",)
"""The update statistics logged as their mean between two dumps (the others: the last update's)."""


def record_train_stats(logger: Logger, stats: dict[str, np.ndarray], n_updates: int, task_names: list[str]) -> None:
    """Record SB3's ``train/*`` keys and every task's critic loss from the statistics of the updates."""
    logger.record("train/n_updates", n_updates, exclude="tensorboard")
    logger.record("train/actor_loss", float(stats["actor_loss"]))
    logger.record(CRITIC_LOSS_KEY, float(stats["critic_loss"].mean()))
    logger.record("train/ent_coef", float(stats["ent_coef"].mean()))
    if "ent_coef_loss" in stats:
        logger.record("train/ent_coef_loss", float(stats["ent_coef_loss"]))
    if "q_loss_clip_fraction" in stats:
        logger.record_mean(CLIP_FRACTION_KEY, float(stats["q_loss_clip_fraction"].mean()))
    for i, loss in enumerate(stats["critic_loss"]):
        name = task_names[i] if i < len(task_names) else None
        logger.record(task_log_key(CRITIC_LOSS_KEY, i, name), float(loss))
