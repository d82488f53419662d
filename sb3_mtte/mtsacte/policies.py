"""MTSACTE policy: task embedding E_phi(z|s, one-hot), decoder D(z, one-hot) -> s, policy pi_theta(a|s, z),
and N per-task twin critics Q_psi_i(s, a) with targets (one batched ensemble)."""

from __future__ import annotations

import math
from typing import Any

import torch as th
from gymnasium import spaces
from stable_baselines3.common.type_aliases import Schedule

from sb3_mtte.common.distributions import gaussian_sample, split_mean_log_std, squashed_gaussian
from sb3_mtte.common.ensemble import mlp
from sb3_mtte.common.policies import MultiTaskActor, MultiTaskPolicy

DETERMINISTIC_Z = ("mean", "sample")


class EmbeddingActor(MultiTaskActor):
    """pi_theta(a | s, z): the multi-task actor interface on the state followed by the representation z.

    Its inputs are ``(state, z)`` instead of (state, one-hot): the task enters only through z ~ E_phi. Its
    distribution parameters are ``net``'s output, under one parameter set or K stacked ones (:meth:`forward_stacked`
    hands the rows of all tasks to ``net``'s own stacked forward); a subclass that changes :meth:`dist_params`
    overrides :meth:`forward_stacked` too.

    :param state_dim: size of the state.
    :param z_dim: size of z.
    :param action_dim: size of the action.
    :param n_tasks: number of tasks N.
    :param net_arch: hidden layer widths.
    :param activation_fn: activation function.
    """

    def __init__(
        self, state_dim: int, z_dim: int, action_dim: int, n_tasks: int, net_arch: list[int], activation_fn
    ) -> None:
        super().__init__(state_dim, action_dim, n_tasks)
        self.net = mlp(state_dim + z_dim, net_arch, 2 * action_dim, activation_fn)

    def dist_params(self, obs: th.Tensor, task_ids: th.Tensor | None = None) -> th.Tensor:
        return self.net(obs)

    def forward_stacked(
        self, params: dict[str, th.Tensor], obs: th.Tensor, noise: th.Tensor
    ) -> tuple[th.Tensor, th.Tensor]:
        net_params = {name.removeprefix("net."): value for name, value in params.items()}
        dist = self.net.forward_stacked(net_params, obs.reshape(1, -1, obs.shape[-1]))
        return squashed_gaussian(dist.view(dist.shape[0], *obs.shape[:-1], -1), noise)


class MTSACTEPolicy(MultiTaskPolicy):
    """Networks of multi-task SAC with a task embedding network (Fig. 2 of the paper).

    ``encoder`` maps (state, one-hot) to the mean and log-std of a diagonal Gaussian over z; ``decoder`` maps
    (z, one-hot) back to the state; ``actor`` maps (state, z) to a tanh-squashed Gaussian over actions.

    :param observation_space: flat Box: state followed by the N-dim one-hot.
    :param action_space: Box action space.
    :param lr_schedule: learning-rate schedule of the actor and critics.
    :param z_dim: size of the representation z (8 in the paper).
    :param rep_learning_rate: learning rate of the encoder and decoder (J^rep).
    :param z_init_std: E_phi's standard deviation at initialisation (the bias of its log-std head is set to
        ``log(z_init_std)``; 0.01, where E_phi's mean, which already differs between tasks, shows in the sampled z);
        None keeps PyTorch's initialisation (a standard deviation of about 1, where z starts as noise).
    :param z_mean_init_gain: factor on the initial weights and bias of E_phi's mean head (50, the default, chosen on
        DEV6 and kept on toy-conflict: the tasks' means start about 1 apart with 2 x 400 nets, the prior's scale; 1 is
        PyTorch's initialisation, where they start about 0.02 apart and z can lose the task).
    :param deterministic_z: what ``predict(deterministic=True)`` feeds the actor: ``"mean"``, E_phi's mean, or
        ``"sample"``, a sample of E_phi as in training.
    :param critic_arch: must be ``"per_task"`` (kept for a uniform constructor with MTSAC).
    :param kwargs: ``n_tasks``, ``net_arch`` (a list, or ``dict(pi=..., qf=..., embed=..., decoder=...)``),
        ``activation_fn``, ``n_critics`` (twin critics per task), ``optimizer_class`` and ``optimizer_kwargs`` of
        :class:`~sb3_mtte.common.policies.MultiTaskPolicy`.
    """

    def __init__(
        self,
        observation_space: spaces.Box,
        action_space: spaces.Box,
        lr_schedule: Schedule,
        z_dim: int = 8,
        rep_learning_rate: float = 3e-4,
        z_init_std: float | None = 0.01,
        z_mean_init_gain: float = 50.0,
        deterministic_z: str = "mean",
        critic_arch: str = "per_task",
        **kwargs: Any,
    ) -> None:
        if critic_arch != "per_task":
            raise ValueError("MTSACTE uses one twin critic per task (critic_arch='per_task').")
        if z_init_std is not None and not z_init_std > 0:
            raise ValueError(f"z_init_std must be a positive standard deviation or None, got {z_init_std}.")
        if not z_mean_init_gain > 0:
            raise ValueError(f"z_mean_init_gain must be a positive factor, got {z_mean_init_gain}.")
        if deterministic_z not in DETERMINISTIC_Z:
            raise ValueError(f"deterministic_z must be one of {DETERMINISTIC_Z}, got {deterministic_z!r}.")
        super().__init__(observation_space, action_space, **kwargs)
        self.z_dim, self.rep_learning_rate = z_dim, rep_learning_rate
        self.z_init_std, self.z_mean_init_gain, self.deterministic_z = z_init_std, z_mean_init_gain, deterministic_z
        act, state_dim, action_dim, n_tasks = self.activation_fn, self.state_dim, self.action_dim, self.n_tasks
        self.encoder = mlp(state_dim + n_tasks, self.arch("embed"), 2 * z_dim, act)
        with th.no_grad():
            self.encoder[-1].weight[:z_dim].mul_(z_mean_init_gain)
            self.encoder[-1].bias[:z_dim].mul_(z_mean_init_gain)
            if z_init_std is not None:
                self.encoder[-1].bias[z_dim:].fill_(math.log(z_init_std))
        self.decoder = mlp(z_dim + n_tasks, self.arch("decoder"), state_dim, act)
        self.actor = EmbeddingActor(state_dim, z_dim, action_dim, n_tasks, self.arch("pi"), act)
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
        return mean if deterministic else gaussian_sample(mean, log_std, th.randn_like(mean))

    def actor_input(self, state: th.Tensor, z: th.Tensor) -> th.Tensor:
        """The input of pi_theta: the state followed by z."""
        return th.cat([state, z], dim=-1)

    def action_log_prob(self, obs: th.Tensor, noise: th.Tensor | None = None) -> tuple[th.Tensor, th.Tensor]:
        """Task-major actions and log-probabilities with z ~ E_phi detached (theta only, Alg. 1)."""
        with th.no_grad():
            z = self.embed(obs)
        return self.actor(self.actor_input(obs[..., : self.state_dim], z), noise)

    def act(self, observation: th.Tensor, deterministic: bool = False) -> th.Tensor:
        """z ~ E_phi, then pi_theta's actions, for observations in any order."""
        z = self.embed(observation, deterministic and self.deterministic_z == "mean")
        return self.actor.act(self.actor_input(observation[..., : self.state_dim], z), deterministic)

    def set_training_mode(self, mode: bool) -> None:
        for module in (self.actor, self.critic, self.encoder, self.decoder):
            module.train(mode)
        self.training = mode

    def _get_constructor_parameters(self) -> dict[str, Any]:
        return {
            **super()._get_constructor_parameters(),
            "z_dim": self.z_dim,
            "rep_learning_rate": self.rep_learning_rate,
            "z_init_std": self.z_init_std,
            "z_mean_init_gain": self.z_mean_init_gain,
            "deterministic_z": self.deterministic_z,
        }


MlpPolicy = MTSACTEPolicy
