"""Policies of the MTSAC family (the paper's Table-1 baselines).

- ``MlpPolicy`` (SAC-MT): one actor on state + one-hot.
- ``MultiHeadPolicy`` (SAC-MT-MH): shared trunk on state + one-hot, one output head per task.
- ``SoftModularPolicy`` (SAC-soft-modular, Yang et al. 2020): a routing network over layers of modules.
- ``IndependentPolicy`` (SAC-Ind): N independent actors on the state alone.

Every actor maps observations (state followed by the N-dim one-hot) to a tanh-squashed Gaussian through the
interface of :class:`~sb3_mtte.common.policies.MultiTaskActor`: task-major ``(N, L, ...)`` batches for training,
rows in any order (tasks gathered from the one-hot) for acting.
"""

from __future__ import annotations

from typing import Any

import torch as th
from gymnasium import spaces
from stable_baselines3.common.type_aliases import Schedule
from torch import nn

from sb3_mtte.common.ensemble import EnsembleLinear, EnsembleMLP, mlp
from sb3_mtte.common.policies import MultiTaskActor, MultiTaskPolicy


class SharedActor(MultiTaskActor):
    """SAC-MT: one MLP on state + one-hot."""

    def __init__(self, state_dim, action_dim, n_tasks, net_arch, activation_fn) -> None:
        super().__init__(state_dim, action_dim, n_tasks)
        self.net = mlp(state_dim + n_tasks, net_arch, 2 * action_dim, activation_fn)

    @property
    def shared_rows_network(self) -> nn.Module:
        return self.net

    def dist_params(self, obs: th.Tensor, task_ids: th.Tensor | None = None) -> th.Tensor:
        return self.net(obs)


class MultiHeadActor(MultiTaskActor):
    """SAC-MT-MH: shared trunk on state + one-hot, one linear output head per task (batched)."""

    gathers_tasks = True

    def __init__(self, state_dim, action_dim, n_tasks, net_arch, activation_fn) -> None:
        super().__init__(state_dim, action_dim, n_tasks)
        self.trunk = mlp(state_dim + n_tasks, net_arch, 0, activation_fn)
        self.heads = EnsembleLinear(n_tasks, net_arch[-1], 2 * action_dim)

    def dist_params(self, obs: th.Tensor, task_ids: th.Tensor | None = None) -> th.Tensor:
        latent = self.trunk(obs)
        if task_ids is None:
            return self.heads(latent)
        return self.heads.forward_gather(latent, task_ids)


class IndependentActor(MultiTaskActor):
    """SAC-Ind: N independent MLPs on the state alone (batched as one ensemble)."""

    gathers_tasks = True

    def __init__(self, state_dim, action_dim, n_tasks, net_arch, activation_fn) -> None:
        super().__init__(state_dim, action_dim, n_tasks)
        self.nets = EnsembleMLP(n_tasks, state_dim, net_arch, 2 * action_dim, activation_fn)

    def dist_params(self, obs: th.Tensor, task_ids: th.Tensor | None = None) -> th.Tensor:
        state = obs[..., : self.state_dim]
        if task_ids is None:
            return self.nets(state)
        return self.nets.forward_gather(state, task_ids)


class SoftModularActor(MultiTaskActor):
    """Soft modularization (Yang et al., 2020), batched over modules.

    A state encoder f(s) and a task embedding g(one-hot) of the same width D feed a routing network that, per
    sample, outputs for every layer l >= 1 a matrix of soft weights p^l (m x m, softmax over the source module):

        p^1 = W_d^1 ReLU(f(s) * g),   p^{l+1} = W_d^{l+1} ReLU(W_u^l p^l * f(s) * g).

    The base network has ``n_layers`` layers of ``n_modules`` modules (one linear layer + ReLU each). Every module
    of layer 0 reads f(s); module j of layer l+1 reads sum_i p^l[j, i] * out_i^l; the output head reads the sum
    of the last layer's module outputs. Modules of a layer are one batched ensemble (one bmm), routing is an
    einsum: no loop over modules or tasks.

    Deviation from the original: module width 128, 4 layers x 4 modules by default, and the state encoder f(s)
    is ``net_arch`` (2 x 400), so D = ``net_arch[-1]``.

    :param n_layers: number of module layers L.
    :param n_modules: modules per layer m.
    :param module_size: width d of each module.
    """

    def __init__(
        self,
        state_dim,
        action_dim,
        n_tasks,
        net_arch,
        activation_fn,
        n_layers: int = 4,
        n_modules: int = 4,
        module_size: int = 128,
    ) -> None:
        super().__init__(state_dim, action_dim, n_tasks)
        if n_layers < 2 or n_modules < 1:
            raise ValueError("SoftModularPolicy needs n_layers >= 2 and n_modules >= 1.")
        self.n_layers, self.n_modules = n_layers, n_modules
        self.state_encoder = mlp(state_dim, net_arch, 0, activation_fn)  # f(s)
        self.task_encoder = nn.Linear(n_tasks, net_arch[-1])  # g(one-hot)
        self.route_down = nn.ModuleList(nn.Linear(net_arch[-1], n_modules * n_modules) for _ in range(n_layers - 1))
        self.route_up = nn.ModuleList(nn.Linear(n_modules * n_modules, net_arch[-1]) for _ in range(n_layers - 2))
        sizes = [net_arch[-1]] + [module_size] * n_layers
        self.modules_per_layer = nn.ModuleList(
            EnsembleLinear(n_modules, sizes[k], sizes[k + 1]) for k in range(n_layers)
        )
        self.head = nn.Linear(module_size, 2 * action_dim)
        self.activation = activation_fn()

    def dist_params(self, obs: th.Tensor, task_ids: th.Tensor | None = None) -> th.Tensor:
        """Rows are independent samples: any leading dims are flattened for the routing and restored."""
        leading = obs.shape[:-1]
        obs = obs.reshape(-1, obs.shape[-1])
        state, one_hot = obs[:, : self.state_dim], obs[:, self.state_dim :]
        features = self.state_encoder(state)
        context = features * self.task_encoder(one_hot)
        m = self.n_modules
        logits = self.route_down[0](th.relu(context))
        x = self.activation(self.modules_per_layer[0](features.unsqueeze(0).expand(m, -1, -1)))  # (m, B, d)
        for layer in range(1, self.n_layers):
            weights = logits.view(-1, m, m).softmax(dim=-1)  # (B, target j, source i)
            x = th.einsum("bji,ibd->jbd", weights, x)
            x = self.activation(self.modules_per_layer[layer](x))
            if layer < self.n_layers - 1:
                logits = self.route_down[layer](th.relu(self.route_up[layer - 1](logits) * context))
        return self.head(x.sum(dim=0)).view(*leading, -1)


class MTSACPolicy(MultiTaskPolicy):
    """Actor + twin critics (+ targets) for the MTSAC family. Default alias ``"MlpPolicy"`` (SAC-MT).

    :param observation_space: flat Box: state followed by the N-dim one-hot.
    :param action_space: Box action space.
    :param lr_schedule: learning-rate schedule.
    :param critic_arch: ``"per_task"`` (one twin Q per task, default) or ``"shared"``.
    :param actor_kwargs: extra keyword arguments of the actor class (e.g. soft-modular depth).
    :param kwargs: ``n_tasks`` (set by the algorithm), ``net_arch`` (a list for actor and critic or
        ``dict(pi=[...], qf=[...])``), ``activation_fn``, ``n_critics``, ``optimizer_class`` and ``optimizer_kwargs``
        of :class:`~sb3_mtte.common.policies.MultiTaskPolicy`.
    """

    actor_class: type[MultiTaskActor] = SharedActor
    def __init__(
        self,
        observation_space: spaces.Box,
        action_space: spaces.Box,
        lr_schedule: Schedule,
        critic_arch: str = "per_task",
        actor_kwargs: dict[str, Any] | None = None,
        **kwargs: Any,
    ) -> None:
        super().__init__(observation_space, action_space, **kwargs)
        self.critic_arch = critic_arch
        self.actor_kwargs = actor_kwargs or {}
        self.actor = self.actor_class(
            self.state_dim, self.action_dim, self.n_tasks, self.arch("pi"), self.activation_fn, **self.actor_kwargs
        )
        self.actor.optimizer = self.make_optimizer(self.actor.parameters(), lr_schedule(1))
        self._build_critics(lr_schedule, critic_arch)

    def action_log_prob(self, obs: th.Tensor, noise: th.Tensor | None = None) -> tuple[th.Tensor, th.Tensor]:
        return self.actor(obs, noise)

    def _get_constructor_parameters(self) -> dict[str, Any]:
        return {
            **super()._get_constructor_parameters(),
            "critic_arch": self.critic_arch,
            "actor_kwargs": self.actor_kwargs,
        }

    def act(self, observation: th.Tensor, deterministic: bool = False) -> th.Tensor:
        """Actions for observations in any order."""
        return self.actor.act(observation, deterministic)

    def set_training_mode(self, mode: bool) -> None:
        self.actor.train(mode)
        self.critic.train(mode)
        self.training = mode


class MultiHeadPolicy(MTSACPolicy):
    """SAC-MT-MH: shared trunk, one output head per task."""

    actor_class = MultiHeadActor


class SoftModularPolicy(MTSACPolicy):
    """SAC-soft-modular: soft modularization actor (``actor_kwargs``: n_layers, n_modules, module_size)."""

    actor_class = SoftModularActor


class IndependentPolicy(MTSACPolicy):
    """SAC-Ind: N independent actors on the state alone, with per-task critics."""

    actor_class = IndependentActor


MlpPolicy = MTSACPolicy
