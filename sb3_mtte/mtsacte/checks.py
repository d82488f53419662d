"""Checks of MTSACTE's own arguments, beside MTSAC's (:mod:`sb3_mtte.mtsac.checks`): each raises one ValueError
that names the accepted values."""

from __future__ import annotations

from typing import Any

from sb3_mtte.mtsacte.transfer import ESTIMATORS

NT_MEASURES = ("per_batch", "mean", "significant")


def check_policy_kwargs(policy_kwargs: dict[str, Any] | None) -> None:
    """:raises ValueError: when ``policy_kwargs`` holds ``rep_learning_rate``, an argument of MTSACTE itself."""
    if policy_kwargs and "rep_learning_rate" in policy_kwargs:
        raise ValueError(
            "rep_learning_rate is an argument of MTSACTE (MTSACTE(..., rep_learning_rate=...)), not of policy_kwargs."
        )


def check_top_k(top_k: int) -> None:
    """:raises ValueError: unless K, the best episodes kept per task, is at least 1."""
    if top_k < 1:
        raise ValueError(f"top_k (K) must be at least 1, got {top_k}.")


def check_nt_estimator(nt_estimator: str) -> None:
    """:raises ValueError: for an estimator other than ``"virtual_step"`` and ``"gradient_dot"``."""
    if nt_estimator not in ESTIMATORS:
        raise ValueError(f"nt_estimator must be one of {ESTIMATORS}, got {nt_estimator!r}.")


def check_rates(nt_step_size: float, c_vae: float, rep_learning_rate: float) -> None:
    """:raises ValueError: for a negative alpha (Eq. 4) or c_vae (Eq. 14), or a learning rate of J^rep that is not
    positive."""
    if nt_step_size < 0 or c_vae < 0 or rep_learning_rate <= 0:
        raise ValueError("nt_step_size and c_vae must be >= 0 and rep_learning_rate > 0.")


def check_nt_chunk_size(nt_chunk_size: int | str | None) -> None:
    """:raises ValueError: unless the chunk size is ``"auto"``, None or a positive int."""
    if not (nt_chunk_size in ("auto", None) or (isinstance(nt_chunk_size, int) and nt_chunk_size >= 1)):
        raise ValueError(f"nt_chunk_size must be 'auto', None or a positive int, got {nt_chunk_size!r}.")


def check_nt_measure(nt_measure: str) -> None:
    """:raises ValueError: for a measure other than those of :data:`NT_MEASURES`."""
    if nt_measure not in NT_MEASURES:
        raise ValueError(f"nt_measure must be one of {NT_MEASURES}, got {nt_measure!r}.")


def check_iteration(iteration_length: int, rep_gradient_steps: int) -> None:
    """:raises ValueError: unless H and the J^rep updates of every iteration are at least 1."""
    if iteration_length < 1 or rep_gradient_steps < 1:
        raise ValueError("iteration_length (H) and rep_gradient_steps must be at least 1.")


def check_per_task_critics(critic_arch: str) -> None:
    """:raises ValueError: for critics other than per task (mu of Eq. 6 reads each task's own critics)."""
    if critic_arch != "per_task":
        raise ValueError(
            f"MTSACTE's critics are per task (critic_arch='per_task'), got {critic_arch!r}: a shared critic is "
            "MTSAC(..., critic_arch='shared')."
        )


def check_n_select(n_select: int, n_tasks: int) -> None:
    """:raises ValueError: unless M, the size of the benign set C_s (Eq. 7), satisfies 1 <= M < N."""
    if not 1 <= n_select < n_tasks:
        raise ValueError(
            f"n_select (M) must satisfy 1 <= M < N = {n_tasks}, got {n_select} (default N // 2 = {n_tasks // 2})."
        )
