"""MOORE (Hendawi et al., ICLR 2024): a mixture of orthogonal experts.

k expert encoders map the state to k representations h_1..h_k (one d-dim vector each, per state); the
Gram-Schmidt process makes them an orthonormal set u_1..u_k; a task's representation is
tanh(sum_j w_tau[j] u_j) with task-specific weights w_tau (k), read by a per-task output head.
"""

from __future__ import annotations

from typing import Any

import torch as th
from gymnasium import spaces
from stable_baselines3.common.type_aliases import Schedule
from torch import nn

from sb3_mtte.common.ensemble import EnsembleLinear, EnsembleMLP
from sb3_mtte.mtsac.task_conditioned import NetworkShape, TaskConditionedPolicy, init_task_weights_

GRAM_SCHMIDT_EPS = 1e-8


def gram_schmidt_coefficients(gram: th.Tensor, eps: float = GRAM_SCHMIDT_EPS) -> th.Tensor:
    """Classical Gram-Schmidt of k vectors V, written as the lower-triangular T with U = T V, from G = V V^T alone.

    u_1 = v_1 / |v_1|,  u_i = w_i / |w_i| with w_i = v_i - sum_{j<i} <v_i, u_j> u_j: row i of T holds w_i's
    coefficients over V (so <v_i, u_j> = (T G)[j, i] and |w_i|^2 = a G a^T), divided by |w_i| + eps. Only k x k
    matrices are touched, so the d-dimensional vectors are read twice (G, then T V) instead of once per projection.
    Exact in exact arithmetic; in floating point a norm loses accuracy when w_i is nearly zero (vectors nearly
    collinear), as |w_i|^2 comes from a difference of Gram entries.

    :param gram: ``(..., k, k)`` Gram matrices.
    :param eps: added to every norm (a zero vector stays zero).
    :return: ``(..., k, k)`` lower-triangular coefficients.
    """
    k = gram.shape[-1]
    unit = th.eye(k, dtype=gram.dtype, device=gram.device)
    rows: list[th.Tensor] = []
    for i in range(k):
        a = unit[i].expand(gram.shape[:-1])
        if rows:
            done = th.stack(rows, dim=-2)  # (..., i, k): u_j = done[j] V
            dots = (done @ gram[..., i : i + 1]).squeeze(-1)  # <v_i, u_j>
            a = a - (dots.unsqueeze(-2) @ done).squeeze(-2)
        squared_norm = (a.unsqueeze(-2) @ gram @ a.unsqueeze(-1)).squeeze(-1)
        rows.append(a / (squared_norm.clamp_min(0).sqrt() + eps))
    return th.stack(rows, dim=-2)


def gram_schmidt(vectors: th.Tensor, eps: float = GRAM_SCHMIDT_EPS) -> th.Tensor:
    """Classical Gram-Schmidt over the second-to-last axis, batched over the leading axes.

    :param vectors: ``(..., k, d)`` k vectors per batch entry, k <= d.
    :param eps: added to every norm (a zero vector stays zero).
    :return: ``(..., k, d)`` orthonormal vectors, the same order and span.
    """
    return gram_schmidt_coefficients(vectors @ vectors.transpose(-1, -2), eps) @ vectors


def orthonormal_combination(vectors: th.Tensor, weights: th.Tensor) -> th.Tensor:
    """sum_j weights[j] u_j with u the Gram-Schmidt basis of ``vectors``, as (weights^T T) V: the basis is never
    built.

    :param vectors: ``(..., k, d)``.
    :param weights: ``(..., k)``, broadcast against the leading axes of ``vectors``.
    :return: ``(..., d)``.
    """
    coefficients = gram_schmidt_coefficients(vectors @ vectors.transpose(-1, -2))
    combined = weights.unsqueeze(-2) @ coefficients  # (..., 1, k)
    return (combined @ vectors).squeeze(-2)


class MooreNetwork(nn.Module):
    """C independent MOORE networks: k experts, Gram-Schmidt, task weights, tanh, one output head per task.

    Experts are one ensemble of C * k MLPs (hidden layers ``shape.hidden_sizes[:-1]``, linear output of width
    d = ``shape.hidden_sizes[-1]``); heads are one ensemble of C * N linear layers.

    :param shape: the copies, sizes and activation (:class:`~sb3_mtte.mtsac.task_conditioned.NetworkShape`).
    :param n_experts: number of experts k (1 <= k <= d).
    """

    def __init__(self, shape: NetworkShape, n_experts: int = 4) -> None:
        super().__init__()
        n_copies, in_features, n_tasks, hidden_sizes, out_features, activation_fn = shape
        check_moore_arguments(n_experts, hidden_sizes)
        self.n_copies, self.n_tasks, self.n_experts = n_copies, n_tasks, n_experts
        width = hidden_sizes[-1]
        self.experts = EnsembleMLP(n_copies * n_experts, in_features, hidden_sizes[:-1], width, activation_fn)
        self.task_weights = nn.Parameter(init_task_weights_(th.empty(n_copies, n_tasks, n_experts)))
        self.heads = EnsembleLinear(n_copies * n_tasks, width, out_features)

    def expert_outputs(self, x: th.Tensor) -> th.Tensor:
        """:param x: ``(C, B, in)``. :return: ``(C, B, k, d)``, the raw outputs of the k experts for every row."""
        c, k = self.n_copies, self.n_experts
        rows = x.unsqueeze(1).expand(c, k, *x.shape[1:]).reshape(c * k, *x.shape[1:])
        return self.experts(rows).view(c, k, x.shape[1], -1).transpose(1, 2)

    def orthonormal_experts(self, x: th.Tensor) -> th.Tensor:
        """:param x: ``(C, B, in)``. :return: ``(C, B, k, d)``, orthonormal over k for every row."""
        return gram_schmidt(self.expert_outputs(x))

    def forward(self, x: th.Tensor) -> th.Tensor:
        """:param x: ``(C, N, L, in)`` task-major. :return: ``(C, N, L, out)``."""
        c, n, length = x.shape[:3]
        experts = self.expert_outputs(x.reshape(c, n * length, -1)).view(c, n, length, self.n_experts, -1)
        features = th.tanh(orthonormal_combination(experts, self.task_weights.unsqueeze(2)))
        return self.heads(features.reshape(c * n, length, -1)).view(c, n, length, -1)

    def forward_gather(self, x: th.Tensor, task_ids: th.Tensor) -> th.Tensor:
        """:param x: ``(C, B, in)``. :param task_ids: ``(B,)`` task of every row. :return: ``(C, B, out)``."""
        c, rows = x.shape[:2]
        features = th.tanh(orthonormal_combination(self.expert_outputs(x), self.task_weights[:, task_ids]))
        heads = (th.arange(c, device=x.device).unsqueeze(1) * self.n_tasks + task_ids).reshape(-1)
        return self.heads.forward_gather(features.reshape(c * rows, -1), heads).view(c, rows, -1)


def check_moore_arguments(n_experts: int, hidden_sizes: list[int]) -> None:
    if not hidden_sizes:
        raise ValueError("MOORE needs at least one hidden layer: its last width is the representation size d.")
    if not 1 <= n_experts <= hidden_sizes[-1]:
        raise ValueError(
            f"MOORE needs 1 <= n_experts <= d (orthonormal vectors of dimension d = {hidden_sizes[-1]}), "
            f"got n_experts={n_experts}."
        )


class MOOREPolicy(TaskConditionedPolicy):
    """MTSAC policy whose actor and twin critics are MOORE networks (Hendawi et al., 2024).

    :param observation_space: flat Box: state followed by the N-dim one-hot.
    :param action_space: Box action space.
    :param lr_schedule: learning-rate schedule.
    :param n_experts: number of experts k (the paper: 4 on MT10, 6 on MT50).
    :param kwargs: ``structured_critic`` and every argument of :class:`~sb3_mtte.mtsac.policies.MTSACPolicy`.
    """

    network_class = MooreNetwork

    def __init__(
        self,
        observation_space: spaces.Box,
        action_space: spaces.Box,
        lr_schedule: Schedule,
        n_experts: int = 4,
        **kwargs: Any,
    ) -> None:
        self.n_experts = n_experts
        super().__init__(observation_space, action_space, lr_schedule, **kwargs)

    def network_kwargs(self) -> dict[str, Any]:
        return {"n_experts": self.n_experts}

    def _get_constructor_parameters(self) -> dict[str, Any]:
        return {**super()._get_constructor_parameters(), "n_experts": self.n_experts}
