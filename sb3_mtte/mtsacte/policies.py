"""MTSACTE policy: task embedding E_phi(z|s, one-hot), decoder D(z, one-hot) -> s, policy pi_theta(a|s, z),
and N per-task twin critics Q_psi_i(s, a) with targets (one batched ensemble)."""

from __future__ import annotations

from typing import Any

import torch as th
from gymnasium import spaces
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from torch import nn

from sb3_mtte.common.distributions import split_mean_log_std, squashed_gaussian_sample
from sb3_mtte.common.ensemble import mlp
from sb3_mtte.common.policies import MultiTaskPolicy


class MTSACTEPolicy(MultiTaskPolicy):
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
        if critic_arch != "per_task":
            raise ValueError("MTSACTE uses one twin critic per task (critic_arch='per_task').")
        super().__init__(
            observation_space,
            action_space,
            n_tasks,
            net_arch,
            activation_fn,
            n_critics,
            optimizer_class,
            optimizer_kwargs,
        )
        self.z_dim, self.rep_learning_rate = z_dim, rep_learning_rate
        act, state_dim, action_dim = activation_fn, self.state_dim, self.action_dim
        self.encoder = mlp(state_dim + n_tasks, self.arch("embed"), 2 * z_dim, act)
        self.decoder = mlp(z_dim + n_tasks, self.arch("decoder"), state_dim, act)
        self.actor = mlp(state_dim + z_dim, self.arch("pi"), 2 * action_dim, act)
        self.actor.optimizer = self.make_optimizer(self.actor.parameters(), lr_schedule(1))
        self._build_critics(lr_schedule, "per_task")
        rep_params = [*self.encoder.parameters(), *self.decoder.parameters()]
        self.rep_optimizer = self.make_optimizer(rep_params, rep_learning_rate)

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

    def set_training_mode(self, mode: bool) -> None:
        for module in (self.actor, self.critic, self.encoder, self.decoder):
            module.train(mode)
        self.training = mode

    def _get_constructor_parameters(self) -> dict[str, Any]:
        return {
            **super()._get_constructor_parameters(),
            "z_dim": self.z_dim,
            "rep_learning_rate": self.rep_learning_rate,
        }


MlpPolicy = MTSACTEPolicy
