"""Actor, critic and policy built from one task-conditioned network class (MOORE, PaCo).

A task-conditioned network holds C independent copies (1 for the actor, ``n_critics`` for the twin critics) as
stacked weights, and has two entry points:

- ``forward(x)``: ``x`` of shape ``(C, N, L, in)``, task-major (row block i belongs to task i), returns
  ``(C, N, L, out)``;
- ``forward_gather(x, task_ids)``: ``x`` of shape ``(C, B, in)``, rows of any tasks, returns ``(C, B, out)``.

Both see the state without the one-hot; the task enters through the network's per-task weights.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, ClassVar, NamedTuple

import torch as th
from gymnasium import spaces
from stable_baselines3.common.type_aliases import Schedule
from torch import nn

from sb3_mtte.common.critics import MultiTaskCritic
from sb3_mtte.common.policies import MultiTaskActor
from sb3_mtte.mtsac.policies import MTSACPolicy


class NetworkShape(NamedTuple):
    """What every task-conditioned network is built from, beside its structure's own arguments.

    :param n_copies: number of independent networks C (1 actor, or the twin critics).
    :param in_features: input size (the state, or state + action).
    :param n_tasks: number of tasks N.
    :param hidden_sizes: hidden widths.
    :param out_features: output size.
    :param activation_fn: activation between layers.
    """

    n_copies: int
    in_features: int
    n_tasks: int
    hidden_sizes: list[int]
    out_features: int
    activation_fn: type[nn.Module]


NetworkFactory = Callable[[NetworkShape], nn.Module]
"""``shape -> network``."""


def init_task_weights_(task_weights: th.Tensor) -> th.Tensor:
    """He-uniform init of ``(C, N, K)`` per-task weights, as a linear layer on the one-hot (fan-in N), in place."""
    bound = (6.0 / task_weights.shape[-2]) ** 0.5
    return nn.init.uniform_(task_weights, -bound, bound)


class TaskConditionedActor(MultiTaskActor):
    """A tanh-Gaussian actor whose whole network is one task-conditioned network on the state.

    :param network: factory of the network (see :data:`NetworkFactory`).
    """

    gathers_tasks = True

    def __init__(self, state_dim, action_dim, n_tasks, net_arch, activation_fn, network: NetworkFactory) -> None:
        super().__init__(state_dim, action_dim, n_tasks)
        self.net = network(NetworkShape(1, state_dim, n_tasks, net_arch, 2 * action_dim, activation_fn))

    def dist_params(self, obs: th.Tensor, task_ids: th.Tensor | None = None) -> th.Tensor:
        state = obs[..., : self.state_dim].unsqueeze(0)
        if task_ids is None:
            return self.net(state)[0]
        return self.net.forward_gather(state, task_ids)[0]


class TaskConditionedCritic(nn.Module):
    """Twin Q-networks Q_j(s, a | task) as one task-conditioned network with ``n_critics`` copies.

    :param network: the network, built with ``n_critics`` copies, input state + action, output 1.
    :param n_tasks: number of tasks N.
    :param n_critics: number of twin Q-networks.
    """

    def __init__(self, network: nn.Module, n_tasks: int, n_critics: int) -> None:
        super().__init__()
        self.q_net, self.n_tasks, self.n_critics = network, n_tasks, n_critics

    def forward(self, obs: th.Tensor, actions: th.Tensor) -> th.Tensor:
        """:param obs: ``(N, L, state + N)``. :param actions: ``(N, L, A)``. :return: ``(n_critics, N, L)``."""
        x = th.cat([obs[..., : -self.n_tasks], actions], dim=-1)
        return self.q_net(x.unsqueeze(0).expand(self.n_critics, *x.shape)).squeeze(-1)


class TaskConditionedPolicy(MTSACPolicy):
    """MTSAC policy whose actor (and, with ``structured_critic``, critic) is a task-conditioned network.

    :param observation_space: flat Box: state followed by the N-dim one-hot.
    :param action_space: Box action space.
    :param lr_schedule: learning-rate schedule.
    :param structured_critic: the twin critics are the same structure (True), or the package's per-task critics of
        ``critic_arch`` (False).
    :param kwargs: every other argument of :class:`~sb3_mtte.mtsac.policies.MTSACPolicy`.
    """

    network_class: ClassVar[type[nn.Module]]

    def __init__(
        self,
        observation_space: spaces.Box,
        action_space: spaces.Box,
        lr_schedule: Schedule,
        structured_critic: bool = True,
        **kwargs: Any,
    ) -> None:
        if structured_critic and kwargs.get("critic_arch", "per_task") != "per_task":
            raise ValueError("critic_arch sets the package's critics: use it with structured_critic=False.")
        self.structured_critic = structured_critic
        super().__init__(observation_space, action_space, lr_schedule, **kwargs)

    def network_kwargs(self) -> dict[str, Any]:
        """The structure's own arguments (number of experts, parameter sets, ...)."""
        return {}

    def network(self, shape: NetworkShape) -> nn.Module:
        """Build the structure in ``shape``."""
        return self.network_class(shape, **self.network_kwargs())

    @property
    def actor_class(self):  # type: ignore[override]
        return lambda *args, **kwargs: TaskConditionedActor(*args, network=self.network, **kwargs)

    def make_critic(self, critic_arch: str = "per_task") -> MultiTaskCritic | TaskConditionedCritic:  # type: ignore[override]
        if not self.structured_critic:
            return super().make_critic(critic_arch)
        in_features = self.state_dim + self.action_dim
        net = self.network(
            NetworkShape(self.n_critics, in_features, self.n_tasks, self.arch("qf"), 1, self.activation_fn)
        )
        return TaskConditionedCritic(net, self.n_tasks, self.n_critics)

    def structured_networks(self) -> list[nn.Module]:
        """The task-conditioned networks of the policy: actor, then critic and target when they are structured."""
        nets = [self.actor.net]
        if self.structured_critic:
            nets += [self.critic.q_net, self.critic_target.q_net]
        return nets

    def _get_constructor_parameters(self) -> dict[str, Any]:
        return {**super()._get_constructor_parameters(), "structured_critic": self.structured_critic}
