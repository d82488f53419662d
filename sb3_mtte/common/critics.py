"""Twin soft-Q critics for N tasks: one twin pair per task (the paper's setting) or one shared pair."""

from __future__ import annotations

import torch as th
from torch import nn
from torch.func import functional_call

from sb3_mtte.common.ensemble import EnsembleMLP
from sb3_mtte.common.gradient_surgery import KeepsRows

CRITIC_ARCHS = ("per_task", "shared")


class MultiTaskCritic(KeepsRows, nn.Module):
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

    @property
    def shared_rows_network(self) -> nn.Module | None:
        return None if self.per_task else self.q_net

    def task_parameters(self) -> dict[str, th.Tensor]:
        """The Q-networks' parameters by task, ``{name: (N, n_critics, ...)}``, the layout of
        :meth:`forward_stacked`: views of the per-task members, or the shared twins repeated for every task."""
        if self.per_task:
            return {
                name: p.view(self.n_tasks, self.n_critics, *p.shape[1:]) for name, p in self.q_net.named_parameters()
            }
        return {name: p.expand(self.n_tasks, *p.shape) for name, p in self.q_net.named_parameters()}

    def forward_stacked(self, task_params: dict[str, th.Tensor], obs: th.Tensor, actions: th.Tensor) -> th.Tensor:
        """Q-values of task-major rows, each task's rows through its own set of twin parameters.

        :param task_params: ``{name: (T, n_critics, ...)}`` as :meth:`task_parameters` gives them, for T tasks (all,
            a subset, or one with a leading axis of 1).
        :param obs: ``(T, B, state_dim + N)`` observations.
        :param actions: ``(T, B, action_dim)``.
        :return: ``(T, n_critics, B)``.
        """
        x = th.cat([obs[..., : -self.n_tasks] if self.per_task else obs, actions], dim=-1)
        n_sets, length, width = x.shape
        x = x.unsqueeze(1).expand(n_sets, self.n_critics, length, width).reshape(-1, length, width)
        members = {name: p.flatten(0, 1) for name, p in task_params.items()}
        return functional_call(self.q_net, members, (x,)).view(n_sets, self.n_critics, length)

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
        x = th.cat([obs, actions], dim=-1).unsqueeze(0).expand(c, -1, -1, -1)
        q_values = self.q_net(x.flatten(1, 2))
        self._keep_rows(x, q_values, task_dim=1)
        return q_values.view(c, n, -1)
