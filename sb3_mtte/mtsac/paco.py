"""PaCo (Sun et al., NeurIPS 2022): parameter-compositional multi-task networks.

Every layer holds K parameter sets Phi = [phi_1 .. phi_K]; task tau's parameters are theta_tau = Phi w_tau with
task-specific weights w_tau (K). A task whose loss exceeds a threshold is masked out of the update and its w_tau
is reset afterwards: here, as in the authors' code, to a random convex combination
of the w of the tasks that did not collapse. The shared sets Phi are never reset.
"""

from __future__ import annotations

import math
from itertools import pairwise
from typing import Any

import torch as th
from gymnasium import spaces
from stable_baselines3.common.type_aliases import Schedule
from torch import nn

from sb3_mtte.common.update_hooks import CollapseReset, UpdateHook
from sb3_mtte.mtsac.task_conditioned import NetworkShape, TaskConditionedPolicy, init_task_weights_


def compose_parameters(parameter_sets: th.Tensor, task_weights: th.Tensor) -> th.Tensor:
    """theta_tau = Phi w_tau for every copy c and task tau, one contraction.

    :param parameter_sets: ``(C, K, ...)`` the K shared sets of every copy.
    :param task_weights: ``(C, N, K)``.
    :return: ``(C, N, ...)``.
    """
    return th.einsum("ck...,cnk->cn...", parameter_sets, task_weights)


def interpolated_task_weights(task_weights: th.Tensor, collapsed: th.Tensor, mix: th.Tensor) -> th.Tensor:
    """Task weights with every collapsed task's w replaced by a convex combination of the others' w.

    :param task_weights: ``(C, N, K)``.
    :param collapsed: ``(N,)`` bool.
    :param mix: ``(n_collapsed, n_kept)`` non-negative, rows summing to 1.
    :return: ``(C, N, K)`` new weights (the kept tasks' rows unchanged).
    """
    new = task_weights.clone()
    new[:, collapsed] = th.einsum("jm,cmk->cjk", mix, task_weights[:, ~collapsed])
    return new


class PaCoNetwork(nn.Module):
    """C independent PaCo MLPs: every linear layer is K parameter sets composed per task by w (N, K).

    :param shape: the copies, sizes and activation (:class:`~sb3_mtte.mtsac.task_conditioned.NetworkShape`).
    :param n_parameter_sets: K.
    """

    def __init__(self, shape: NetworkShape, n_parameter_sets: int = 5) -> None:
        super().__init__()
        if n_parameter_sets < 1:
            raise ValueError(f"PaCo needs n_parameter_sets (K) >= 1, got {n_parameter_sets}.")
        n_copies, in_features, n_tasks, hidden_sizes, out_features, activation_fn = shape
        self.n_copies, self.n_tasks, self.n_parameter_sets = n_copies, n_tasks, n_parameter_sets
        sizes = [in_features, *hidden_sizes, out_features]
        self.weights = nn.ParameterList(
            nn.Parameter(th.empty(n_copies, n_parameter_sets, a, b)) for a, b in pairwise(sizes)
        )
        self.biases = nn.ParameterList(nn.Parameter(th.empty(n_copies, n_parameter_sets, 1, b)) for b in sizes[1:])
        self.task_weights = nn.Parameter(th.empty(n_copies, n_tasks, n_parameter_sets))
        self.activation = activation_fn()
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """Every set like ``nn.Linear``; w He-uniform, as a linear layer on the one-hot (fan-in N)."""
        for weight, bias in zip(self.weights, self.biases, strict=True):
            bound = 1.0 / math.sqrt(weight.shape[-2])
            nn.init.uniform_(weight, -bound, bound)
            nn.init.uniform_(bias, -bound, bound)
        init_task_weights_(self.task_weights.data)

    def task_parameters(self) -> list[tuple[th.Tensor, th.Tensor]]:
        """Per layer, every task's (weight ``(C, N, in, out)``, bias ``(C, N, 1, out)``)."""
        return [
            (compose_parameters(w, self.task_weights), compose_parameters(b, self.task_weights))
            for w, b in zip(self.weights, self.biases, strict=True)
        ]

    def forward(self, x: th.Tensor) -> th.Tensor:
        """:param x: ``(C, N, L, in)`` task-major. :return: ``(C, N, L, out)``."""
        c, n, length = x.shape[:3]
        x = x.reshape(c * n, length, -1)
        layers = self.task_parameters()
        for index, (weight, bias) in enumerate(layers):
            x = th.baddbmm(bias.flatten(0, 1), x, weight.flatten(0, 1))
            if index < len(layers) - 1:
                x = self.activation(x)
        return x.view(c, n, length, -1)

    def forward_gather(self, x: th.Tensor, task_ids: th.Tensor) -> th.Tensor:
        """:param x: ``(C, B, in)``. :param task_ids: ``(B,)`` task of every row. :return: ``(C, B, out)``."""
        c, rows = x.shape[:2]
        x = x.reshape(c * rows, 1, -1)
        layers = self.task_parameters()
        for index, (weight, bias) in enumerate(layers):
            x = th.baddbmm(bias[:, task_ids].flatten(0, 1), x, weight[:, task_ids].flatten(0, 1))
            if index < len(layers) - 1:
                x = self.activation(x)
        return x.view(c, rows, -1)


class PaCoPolicy(TaskConditionedPolicy):
    """MTSAC policy whose actor and twin critics are PaCo networks, with the reset of collapsed tasks.

    Every update, its :class:`~sb3_mtte.common.update_hooks.CollapseReset` hook marks the tasks whose critic loss
    exceeds ``task_loss_threshold``: they take no part in that update, and :meth:`reset_task_weights` then resets
    their w in every PaCo network (actor, critics and target critics) and counts the reset in ``collapse_counts``.

    :param observation_space: flat Box: state followed by the N-dim one-hot.
    :param action_space: Box action space.
    :param lr_schedule: learning-rate schedule.
    :param n_parameter_sets: K (the authors' MT10 setting: 5).
    :param task_loss_threshold: a task whose loss exceeds it is masked and reset (the authors': 3e3); None: never.
    :param kwargs: ``structured_critic`` and every argument of :class:`~sb3_mtte.mtsac.policies.MTSACPolicy`.
    """

    network_class = PaCoNetwork

    def __init__(
        self,
        observation_space: spaces.Box,
        action_space: spaces.Box,
        lr_schedule: Schedule,
        n_parameter_sets: int = 5,
        task_loss_threshold: float | None = 3e3,
        **kwargs: Any,
    ) -> None:
        if task_loss_threshold is not None and not task_loss_threshold > 0:
            raise ValueError(f"task_loss_threshold must be positive or None, got {task_loss_threshold}.")
        self.n_parameter_sets, self.task_loss_threshold = n_parameter_sets, task_loss_threshold
        super().__init__(observation_space, action_space, lr_schedule, **kwargs)
        self.register_buffer("collapse_counts", th.zeros(self.n_tasks, dtype=th.long))

    def network_kwargs(self) -> dict[str, Any]:
        return {"n_parameter_sets": self.n_parameter_sets}

    def update_hooks(self) -> list[UpdateHook]:
        """PaCo's mask of the tasks above ``task_loss_threshold`` and their reset after the update."""
        return [CollapseReset(self)]

    @th.no_grad()
    def reset_task_weights(self, collapsed: th.Tensor) -> None:
        """New w for the ``collapsed`` tasks (``(N,)`` bool) in every PaCo network; the others stay as they are.

        Each collapsed task gets a random convex combination of the kept tasks' w (the authors' ``interpolate``),
        the same combination in the actor and the critics; the target critics take the critics' new w. When every
        task collapsed, w is drawn as at initialisation.
        """
        n_kept = int((~collapsed).sum())
        mix = th.rand(int(collapsed.sum()), n_kept, device=collapsed.device)
        mix = mix / mix.sum(dim=1, keepdim=True)
        for net in self.structured_networks()[:2]:
            if n_kept:
                net.task_weights.copy_(interpolated_task_weights(net.task_weights, collapsed, mix))
            else:
                init_task_weights_(net.task_weights)
        if self.structured_critic:
            self.critic_target.q_net.task_weights[:, collapsed] = self.critic.q_net.task_weights[:, collapsed]
        self.collapse_counts += collapsed.long()

    def _get_constructor_parameters(self) -> dict[str, Any]:
        return {
            **super()._get_constructor_parameters(),
            "n_parameter_sets": self.n_parameter_sets,
            "task_loss_threshold": self.task_loss_threshold,
        }
