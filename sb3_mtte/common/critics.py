"""Twin soft-Q critics for N tasks: one twin pair per task (the paper's setting) or one shared pair."""

from __future__ import annotations

import torch as th
from torch import nn

from sb3_mtte.common.ensemble import EnsembleMLP

CRITIC_ARCHS = ("per_task", "shared")


class MultiTaskCritic(nn.Module):
    """Twin Q-networks evaluated on a task-major batch in one batched pass.

    ``per_task``: Q_psi_i(s, a) for every task i, i.e. ``n_critics * N`` independent MLPs on (state, action),
    stored as one ensemble. ``shared``: ``n_critics`` MLPs on (state, one-hot, action) shared by all tasks.

    :param state_dim: size of the state (observation without the one-hot).
    :param action_dim: size of the action.
    :param n_tasks: number of tasks N.
    :param net_arch: hidden layer widths.
    :param activation_fn: activation function.
    :param critic_arch: ``"per_task"`` or ``"shared"``.
    :param n_critics: number of twin Q-networks (clipped double-Q uses their minimum).
    """

    def __init__(
        self,
        state_dim: int,
        action_dim: int,
        n_tasks: int,
        net_arch: list[int],
        activation_fn: type[nn.Module] = nn.ReLU,
        critic_arch: str = "per_task",
        n_critics: int = 2,
    ) -> None:
        super().__init__()
        if critic_arch not in CRITIC_ARCHS:
            raise ValueError(f"critic_arch must be one of {CRITIC_ARCHS}, got {critic_arch!r}.")
        self.n_tasks, self.n_critics, self.per_task = n_tasks, n_critics, critic_arch == "per_task"
        in_dim = state_dim + action_dim + (0 if self.per_task else n_tasks)
        n_members = n_critics * (n_tasks if self.per_task else 1)
        self.q_net = EnsembleMLP(n_members, in_dim, net_arch, 1, activation_fn)

    def forward(self, obs: th.Tensor, actions: th.Tensor) -> th.Tensor:
        """Q-values of a task-major batch.

        :param obs: ``(N, L, state_dim + N)`` observations.
        :param actions: ``(N, L, action_dim)``.
        :return: ``(n_critics, N, L)``.
        """
        n, c = self.n_tasks, self.n_critics
        if self.per_task:
            x = th.cat([obs[..., :-n], actions], dim=-1)
            length, width = x.shape[1:]
            x = x.unsqueeze(1).expand(n, c, length, width).reshape(n * c, length, width)
            return self.q_net(x).view(n, c, length).transpose(0, 1)
        x = th.cat([obs, actions], dim=-1)
        return self.q_net(x.view(1, -1, x.shape[-1]).expand(c, -1, -1)).view(c, n, -1)
