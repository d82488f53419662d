"""The arguments of MTSACTE, each with its type and range, in one table (:data:`MTSACTE_ARGUMENTS`): MTSAC's
(:mod:`sb3_mtte.mtsac.checks`) that MTSACTE takes, and its own."""

from __future__ import annotations

from collections.abc import Mapping
from numbers import Integral
from typing import Any

from sb3_mtte.mtsac.checks import (
    MTSAC_ARGUMENTS,
    NONE,
    POLICY_KWARGS_RULE,
    ArgumentSpec,
    choice,
    flag,
    integer,
    number,
    policy_kwargs_in_range,
)
from sb3_mtte.mtsacte.transfer import ESTIMATORS

NT_MEASURES = ("per_batch", "mean", "significant")
MTSAC_ONLY = ("ent_coef_arch", "gradient_surgery", "cagrad_c")
"""Arguments of MTSAC that MTSACTE does not take."""
RATES_RULE = "nt_step_size and c_vae must be >= 0 and rep_learning_rate > 0"
ITERATION_RULE = "iteration_length (H) and rep_gradient_steps must be at least 1"


def check_n_select(n_select: int, n_tasks: int) -> None:
    """:raises ValueError: unless M, the size of the benign set C_s (Eq. 7), satisfies 1 <= M < N."""
    if not 1 <= n_select < n_tasks:
        raise ValueError(
            f"n_select (M) must satisfy 1 <= M < N = {n_tasks}, got {n_select} (default N // 2 = {n_tasks // 2})."
        )


def _check_n_select_of_tasks(n_select: int | None, n_tasks: int) -> None:
    if n_select is not None:
        check_n_select(n_select, n_tasks)


def _chunk_size_in_range(value: Any) -> bool:
    return value in ("auto", None) or (isinstance(value, Integral) and value >= 1)


MTSACTE_ARGUMENTS: dict[str, ArgumentSpec] = {
    **{name: spec for name, spec in MTSAC_ARGUMENTS.items() if name not in MTSAC_ONLY},
    "critic_arch": ArgumentSpec(
        "MTSACTE's critics are per task and critic_arch must be 'per_task': a shared critic is "
        "MTSAC(..., critic_arch='shared')",
        (str,),
        lambda value: value == "per_task",
    ),
    "policy_kwargs": ArgumentSpec(
        f"{POLICY_KWARGS_RULE}, and without rep_learning_rate: rep_learning_rate is an argument of MTSACTE, as in "
        "MTSACTE(..., rep_learning_rate=1e-3)",
        (Mapping, NONE),
        lambda value: policy_kwargs_in_range(value) and (value is None or "rep_learning_rate" not in value),
        type_rule="policy_kwargs must be a dict or None",
    ),
    "n_select": ArgumentSpec(
        "n_select (M, the size of the benign set C_s) must be None (N // 2) or an int with 1 <= M < N",
        (Integral, NONE),
        lambda value: value is None or value >= 1,
        task_check=_check_n_select_of_tasks,
    ),
    "top_k": integer("top_k (K) must be at least 1, an int such as 30", 1),
    "nt_step_size": number(RATES_RULE, 0),
    "c_vae": number(RATES_RULE, 0),
    "rep_learning_rate": number(RATES_RULE, 0, ends="(]"),
    "iteration_length": integer(ITERATION_RULE, 1),
    "rep_gradient_steps": integer(ITERATION_RULE, 1),
    "nt_estimator": choice("nt_estimator", ESTIMATORS),
    "use_vae": flag("use_vae"),
    "use_topk": flag("use_topk"),
    "nt_chunk_size": ArgumentSpec(
        "nt_chunk_size must be 'auto', None or a positive int", (str, Integral, NONE), _chunk_size_in_range
    ),
    "nt_measure": choice("nt_measure", NT_MEASURES),
}
"""Every argument of :class:`~sb3_mtte.MTSACTE` but ``policy`` and ``env``; ``n_select < N`` is checked once N is
known."""
