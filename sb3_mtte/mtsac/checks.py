"""Checks of MTSAC's own arguments: each raises one ValueError that names the accepted values.

The checks of arguments that other parts share (the env, batch and buffer sizes, the learning rate, gradient surgery)
stand beside those parts (:mod:`sb3_mtte.common.utils`, :mod:`sb3_mtte.common.gradient_surgery`).
"""

from __future__ import annotations

import math

ENT_COEF_ARCHS = ("per_task", "shared")
UPDATE_PATHS = ("auto", "eager", "cuda_graph")


def check_q_loss_clip(q_loss_clip: float | None) -> None:
    """:raises ValueError: unless ``q_loss_clip`` (V_clip of Eq. 16) is a positive finite number or None."""
    if q_loss_clip is not None and not (q_loss_clip > 0 and math.isfinite(q_loss_clip)):
        raise ValueError(f"q_loss_clip (V_clip) must be a positive number or None, got {q_loss_clip}.")


def check_ent_coef_arch(ent_coef_arch: str) -> None:
    """:raises ValueError: for an ``ent_coef_arch`` other than ``"per_task"`` and ``"shared"``."""
    if ent_coef_arch not in ENT_COEF_ARCHS:
        raise ValueError(f"ent_coef_arch must be one of {ENT_COEF_ARCHS}, got {ent_coef_arch!r}.")


def check_update_path(update_path: str) -> None:
    """:raises ValueError: for an ``update_path`` other than ``"auto"``, ``"eager"`` and ``"cuda_graph"``."""
    if update_path not in UPDATE_PATHS:
        raise ValueError(f"update_path must be one of {UPDATE_PATHS}, got {update_path!r}.")
