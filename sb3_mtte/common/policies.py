"""What every multi-task policy of this package shares: its sizes, Adam defaults, and per-task twin critics."""

from __future__ import annotations

from typing import Any

import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from torch import nn

from sb3_mtte.common.critics import MultiTaskCritic

DEFAULT_NET_ARCH = [400, 400]


class MultiTaskPolicy(BasePolicy):
    """Base of the MTSAC and MTSACTE policies. Observations are the state followed by the N-dim one-hot.

    :param observation_space: flat Box: state followed by the N-dim one-hot.
    :param action_space: Box action space.
    :param n_tasks: number of tasks N.
    :param net_arch: hidden widths of every network, a list, or a dict by network name (``pi``, ``qf``, ...) whose
        missing entries are 2 x 400.
    :param activation_fn: activation function.
    :param n_critics: twin Q-networks per critic.
    :param optimizer_class: optimizer class.
    :param optimizer_kwargs: optimizer keyword arguments (``fused=True`` for Adam/AdamW by default).
    """

    def __init__(
        self,
        observation_space: spaces.Box,
        action_space: spaces.Box,
        n_tasks: int,
        net_arch: list[int] | dict[str, list[int]] | None,
        activation_fn: type[nn.Module],
        n_critics: int,
        optimizer_class: type[th.optim.Optimizer],
        optimizer_kwargs: dict[str, Any] | None,
    ) -> None:
        if optimizer_kwargs is None:
            optimizer_kwargs = {"fused": True} if optimizer_class in (th.optim.Adam, th.optim.AdamW) else {}
        super().__init__(
            observation_space,
            action_space,
            optimizer_class=optimizer_class,
            optimizer_kwargs=optimizer_kwargs,
            squash_output=True,
            normalize_images=False,
        )
        self.net_arch = net_arch if net_arch is not None else DEFAULT_NET_ARCH
        self.n_tasks, self.activation_fn, self.n_critics = n_tasks, activation_fn, n_critics
        self.state_dim = observation_space.shape[0] - n_tasks
        self.action_dim = action_space.shape[0]

    def arch(self, network: str) -> list[int]:
        """Hidden widths of ``network`` (``"pi"``, ``"qf"``, ...)."""
        if isinstance(self.net_arch, dict):
            return self.net_arch.get(network, DEFAULT_NET_ARCH)
        return self.net_arch

    def make_optimizer(self, parameters, lr: float) -> th.optim.Optimizer:
        return self.optimizer_class(parameters, lr=lr, **self.optimizer_kwargs)

    def make_critic(self, critic_arch: str = "per_task") -> MultiTaskCritic:
        return MultiTaskCritic(
            self.state_dim, self.action_dim, self.n_tasks, self.arch("qf"), self.activation_fn, critic_arch, self.n_critics
        )

    def _build_critics(self, lr_schedule: Schedule, critic_arch: str) -> None:
        """Critic with its optimizer, and a frozen copy as Polyak target."""
        self.critic = self.make_critic(critic_arch)
        self.critic.optimizer = self.make_optimizer(self.critic.parameters(), lr_schedule(1))
        self.critic_target = self.make_critic(critic_arch)
        self.critic_target.load_state_dict(self.critic.state_dict())
        self.critic_target.requires_grad_(False)
        self.critic_target.train(False)

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(
            lr_schedule=self._dummy_schedule,  # type: ignore[attr-defined]
            n_tasks=self.n_tasks,
            net_arch=self.net_arch,
            activation_fn=self.activation_fn,
            n_critics=self.n_critics,
            optimizer_class=self.optimizer_class,
            optimizer_kwargs=self.optimizer_kwargs,
        )
        return data

    def forward(self, obs: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        return self._predict(obs, deterministic)
