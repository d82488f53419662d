"""What every multi-task policy of this package shares: the actor interface, sizes, Adam defaults, per-task critics.

Training batches are task-major ``(N, L, ...)``: L rows of task 0, then task 1, ... on a leading task axis, so
per-task parts (heads, independent networks, critics) run as one batched matmul. Acting reads the task of each row
from its one-hot and gathers the matching weights.
"""

from __future__ import annotations

from typing import Any

import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.preprocessing import preprocess_obs
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from torch import nn
from torch.func import functional_call, vmap

from sb3_mtte.common.critics import MultiTaskCritic
from sb3_mtte.common.distributions import squashed_gaussian, squashed_gaussian_action
from sb3_mtte.common.gradient_surgery import KeepsRows
from sb3_mtte.common.update_hooks import UpdateHook
from sb3_mtte.common.utils import task_ids_from_obs

DEFAULT_NET_ARCH = [400, 400]


class MultiTaskActor(KeepsRows, nn.Module):
    """A tanh-squashed Gaussian policy for N tasks; subclasses implement :meth:`dist_params`.

    One forward pass serves training and the per-task gradients of the negative-transfer evaluation (:meth:`forward`,
    task-major) and acting (:meth:`act`, rows in any order); :meth:`forward_stacked` is the same pass under several
    parameter sets at once (the virtual steps theta^k). All go through
    :func:`~sb3_mtte.common.distributions.squashed_gaussian`.

    :param state_dim: size of the state part of the input.
    :param action_dim: size of the action.
    :param n_tasks: number of tasks N.
    """

    gathers_tasks: bool = False
    """Whether :meth:`dist_params` needs each row's task index outside a task-major batch (per-task weights)."""

    def __init__(self, state_dim: int, action_dim: int, n_tasks: int) -> None:
        super().__init__()
        self.state_dim, self.action_dim, self.n_tasks = state_dim, action_dim, n_tasks

    def dist_params(self, obs: th.Tensor, task_ids: th.Tensor | None = None) -> th.Tensor:
        """Raw output (mean and log-std of the Gaussian before the tanh).

        :param obs: ``(N, L, obs_dim)`` task-major batch when ``task_ids`` is None, else ``(B, obs_dim)``.
        :param task_ids: ``(B,)`` task index of every row, or None for a task-major batch.
        :return: ``(..., 2A)``.
        """
        raise NotImplementedError

    def forward(self, obs: th.Tensor, noise: th.Tensor | None = None) -> tuple[th.Tensor, th.Tensor]:
        """Reparameterised actions ``(N, L, A)`` and log-probabilities ``(N, L)`` of a task-major batch.

        :param obs: ``(N, L, obs_dim)``.
        :param noise: ``(N, L, A)`` standard normal noise, or None to draw it.
        """
        params = self.dist_params(obs)
        self._keep_rows(obs, params)
        return squashed_gaussian(params, noise)

    def forward_stacked(
        self, params: dict[str, th.Tensor], obs: th.Tensor, noise: th.Tensor
    ) -> tuple[th.Tensor, th.Tensor]:
        """:meth:`forward` under K parameter sets at once, every set on the whole batch with the same noise.

        This generic form maps :meth:`forward` over the sets with ``vmap``; an actor that knows its network
        overrides it with an equal, faster form.

        :param params: ``{name: (K, ...)}``, named as :meth:`named_parameters`.
        :param obs: ``(N, L, obs_dim)`` task-major batch.
        :param noise: ``(N, L, A)`` standard normal noise.
        :return: actions ``(K, N, L, A)`` and log-probabilities ``(K, N, L)``.
        """
        return vmap(lambda set_params: functional_call(self, set_params, (obs, noise)))(params)

    def act(self, obs: th.Tensor, deterministic: bool = False) -> th.Tensor:
        """Actions ``(B, A)`` for observations ``(B, obs_dim)`` in any order (tasks read from the one-hot)."""
        task_ids = task_ids_from_obs(obs, self.n_tasks) if self.gathers_tasks else None
        return squashed_gaussian_action(self.dist_params(obs, task_ids), deterministic)


class MultiTaskPolicy(BasePolicy):
    """Base of the MTSAC and MTSACTE policies. Observations are the state followed by the N-dim one-hot.

    :param observation_space: flat Box: state followed by the N-dim one-hot.
    :param action_space: Box action space.
    :param n_tasks: number of tasks N (set by the algorithm).
    :param net_arch: hidden widths of every network (2 x 400 by default, as in Appendix B), a list, or a dict by
        network name (``pi``, ``qf``, ...) whose missing entries are 2 x 400.
    :param activation_fn: activation function.
    :param n_critics: twin Q-networks per critic.
    :param optimizer_class: optimizer class (Adam by default).
    :param optimizer_kwargs: optimizer keyword arguments (``fused=True`` for Adam/AdamW by default).
    """

    def __init__(
        self,
        observation_space: spaces.Box,
        action_space: spaces.Box,
        n_tasks: int = 1,
        net_arch: list[int] | dict[str, list[int]] | None = None,
        activation_fn: type[nn.Module] = nn.ReLU,
        n_critics: int = 2,
        optimizer_class: type[th.optim.Optimizer] = th.optim.Adam,
        optimizer_kwargs: dict[str, Any] | None = None,
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
            self.state_dim,
            self.action_dim,
            self.n_tasks,
            self.arch("qf"),
            self.activation_fn,
            critic_arch,
            self.n_critics,
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

    def action_log_prob(self, obs: th.Tensor, noise: th.Tensor | None = None) -> tuple[th.Tensor, th.Tensor]:
        """Reparameterised actions ``(N, L, A)`` and log-probabilities ``(N, L)`` of a task-major batch.

        :param obs: ``(N, L, state_dim + N)`` observations.
        :param noise: ``(N, L, A)`` standard normal noise, or None to draw it.
        """
        raise NotImplementedError

    def update_hooks(self) -> list[UpdateHook]:
        """The architecture's extensions of the update (:mod:`sb3_mtte.common.update_hooks`; PaCo's reset)."""
        return []

    def forward(self, obs: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        return self._predict(obs, deterministic)

    def _predict(self, observation: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        """:meth:`act` on the observations cast as SB3 casts them (float64 arrays and lists become float32)."""
        return self.act(preprocess_obs(observation, self.observation_space), deterministic)  # type: ignore[arg-type]

    def act(self, observation: th.Tensor, deterministic: bool = False) -> th.Tensor:
        """Actions ``(B, A)`` for float observations ``(B, state_dim + N)`` in any order."""
        raise NotImplementedError
