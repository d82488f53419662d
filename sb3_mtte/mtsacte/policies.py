"""MTSACTE policy: task embedding E_phi(z|s, one-hot), decoder D(z, one-hot) -> s, policy pi_theta(a|s, z),
and N per-task twin critics Q_psi_i(s, a) with targets (one batched ensemble)."""

from __future__ import annotations

from typing import Any

import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from torch import nn

from sb3_mtte.common.critics import MultiTaskCritic
from sb3_mtte.common.distributions import split_mean_log_std, squashed_gaussian_sample
from sb3_mtte.common.ensemble import mlp
from sb3_mtte.mtsac.policies import DEFAULT_NET_ARCH


class MTSACTEPolicy(BasePolicy):
    """Networks of multi-task SAC with a task embedding network (Fig. 2 of the paper).

    ``encoder`` maps (state, one-hot) to the mean and log-std of a diagonal Gaussian over z; ``decoder`` maps
    (z, one-hot) back to the state; ``actor`` maps (state, z) to a tanh-squashed Gaussian over actions.

    :param observation_space: flat Box: state followed by the N-dim one-hot.
    :param action_space: Box action space.
    :param lr_schedule: learning-rate schedule of the actor and critics.
    :param n_tasks: number of tasks N.
    :param net_arch: hidden widths of every network (2 x 400 by default, as in Appendix B), a list or
        ``dict(pi=..., qf=..., embed=..., decoder=...)``.
    :param activation_fn: activation function.
    :param z_dim: size of the representation z (8 in the paper).
    :param rep_learning_rate: learning rate of the encoder and decoder (J^rep).
    :param n_critics: twin critics per task.
    :param critic_arch: must be ``"per_task"`` (kept for a uniform constructor with MTSAC).
    :param optimizer_class: optimizer class.
    :param optimizer_kwargs: optimizer keyword arguments (fused Adam by default).
    """

    def __init__(
        self,
        observation_space: spaces.Box,
        action_space: spaces.Box,
        lr_schedule: Schedule,
        n_tasks: int = 1,
        net_arch: list[int] | dict[str, list[int]] | None = None,
        activation_fn: type[nn.Module] = nn.ReLU,
        z_dim: int = 8,
        rep_learning_rate: float = 3e-4,
        n_critics: int = 2,
        critic_arch: str = "per_task",
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
        if critic_arch != "per_task":
            raise ValueError("MTSACTE uses one twin critic per task (critic_arch='per_task').")
        self.net_arch = net_arch if net_arch is not None else DEFAULT_NET_ARCH
        arch = self.net_arch if isinstance(self.net_arch, dict) else {}
        default = self.net_arch if isinstance(self.net_arch, list) else DEFAULT_NET_ARCH
        self.archs = {key: arch.get(key, default) for key in ("pi", "qf", "embed", "decoder")}
        self.n_tasks, self.activation_fn, self.z_dim = n_tasks, activation_fn, z_dim
        self.rep_learning_rate, self.n_critics = rep_learning_rate, n_critics
        self.state_dim = observation_space.shape[0] - n_tasks
        self.action_dim = action_space.shape[0]
        self._build(lr_schedule)

    def _build(self, lr_schedule: Schedule) -> None:
        act = self.activation_fn
        self.encoder = mlp(self.state_dim + self.n_tasks, self.archs["embed"], 2 * self.z_dim, act)
        self.decoder = mlp(self.z_dim + self.n_tasks, self.archs["decoder"], self.state_dim, act)
        self.actor = mlp(self.state_dim + self.z_dim, self.archs["pi"], 2 * self.action_dim, act)
        self.critic = self.make_critic()
        self.critic_target = self.make_critic()
        self.critic_target.load_state_dict(self.critic.state_dict())
        self.critic_target.requires_grad_(False)
        self.critic_target.train(False)
        opt, kwargs = self.optimizer_class, self.optimizer_kwargs
        self.actor.optimizer = opt(self.actor.parameters(), lr=lr_schedule(1), **kwargs)
        self.critic.optimizer = opt(self.critic.parameters(), lr=lr_schedule(1), **kwargs)
        rep_params = [*self.encoder.parameters(), *self.decoder.parameters()]
        self.rep_optimizer = opt(rep_params, lr=self.rep_learning_rate, **kwargs)

    def make_critic(self) -> MultiTaskCritic:
        return MultiTaskCritic(
            self.state_dim, self.action_dim, self.n_tasks, self.archs["qf"], self.activation_fn, "per_task", self.n_critics
        )

    def embedding_params(self, obs: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """Mean and log-std of E_phi(z | s, one-hot)."""
        return split_mean_log_std(self.encoder(obs))

    def embed(self, obs: th.Tensor, deterministic: bool = False) -> th.Tensor:
        """z ~ E_phi(.|s, one-hot), or its mean when deterministic."""
        mean, log_std = self.embedding_params(obs)
        return mean if deterministic else mean + log_std.exp() * th.randn_like(mean)

    def action_log_prob(self, obs: th.Tensor, noise: th.Tensor | None = None) -> tuple[th.Tensor, th.Tensor]:
        """Reparameterised actions and log-probabilities with z ~ E_phi detached (theta only, Alg. 1)."""
        with th.no_grad():
            z = self.embed(obs)
        mean, log_std = split_mean_log_std(self.actor(th.cat([obs[:, : self.state_dim], z], dim=1)))
        return squashed_gaussian_sample(mean, log_std, noise)

    def _predict(self, observation: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        z = self.embed(observation, deterministic)
        mean, log_std = split_mean_log_std(self.actor(th.cat([observation[:, : self.state_dim], z], dim=1)))
        return th.tanh(mean) if deterministic else squashed_gaussian_sample(mean, log_std)[0]

    def forward(self, obs: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        return self._predict(obs, deterministic)

    def set_training_mode(self, mode: bool) -> None:
        for module in (self.actor, self.critic, self.encoder, self.decoder):
            module.train(mode)
        self.training = mode

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(
            lr_schedule=self._dummy_schedule,  # type: ignore[attr-defined]
            n_tasks=self.n_tasks,
            net_arch=self.net_arch,
            activation_fn=self.activation_fn,
            z_dim=self.z_dim,
            rep_learning_rate=self.rep_learning_rate,
            n_critics=self.n_critics,
            optimizer_class=self.optimizer_class,
            optimizer_kwargs=self.optimizer_kwargs,
        )
        return data


MlpPolicy = MTSACTEPolicy
