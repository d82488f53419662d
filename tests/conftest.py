"""Shared fixtures: small MTSACTE networks in float64, task-major batches with fixed noise, and a tiny
multi-task env whose episode returns are known in advance."""

from __future__ import annotations

import sb3_mtte  # noqa: F401  # first: the package sets OpenMP's spin-wait before torch loads

# isort: split

import copy
from collections.abc import Callable
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.vec_env import DummyVecEnv
from torch import nn

from sb3_mtte.common.relu_mlp import fused_relu_mlp
from sb3_mtte.mtsacte.policies import MTSACTEPolicy
from sb3_mtte.mtsacte.transfer import RepresentationBatch, TaskObjectives


# --------------------------------------------------------------------------------------------- networks
def make_te_policy(
    n_tasks: int = 4,
    state_dim: int = 3,
    action_dim: int = 2,
    z_dim: int = 3,
    net_arch: list[int] | None = None,
    activation_fn: type[nn.Module] = nn.ReLU,
    seed: int = 0,
    double: bool = True,
    critic_scale: float = 10.0,
) -> MTSACTEPolicy:
    """A small MTSACTE policy (encoder, decoder, actor, per-task twin critics), float64 by default.

    The critics' output layer is scaled by ``critic_scale`` so that the Q-terms (independent per task) dominate
    the entropy terms and the tasks' policy gradients conflict: mu is then neither all 0 nor all N. E_phi's mean head
    keeps PyTorch's scale (``z_mean_init_gain=1``), the setting the hand-checked cases were built on.
    """
    th.manual_seed(seed)
    obs_space = spaces.Box(-np.inf, np.inf, shape=(state_dim + n_tasks,), dtype=np.float32)
    act_space = spaces.Box(-1.0, 1.0, shape=(action_dim,), dtype=np.float32)
    policy = MTSACTEPolicy(
        obs_space,
        act_space,
        lambda _: 1e-3,
        n_tasks=n_tasks,
        net_arch=net_arch or [16, 16],
        activation_fn=activation_fn,
        z_dim=z_dim,
        z_mean_init_gain=1.0,
        optimizer_kwargs={},
    )
    with th.no_grad():
        policy.critic.q_net.layers[-1].weight.mul_(critic_scale)
        policy.critic_target.load_state_dict(policy.critic.state_dict())
    return policy.double() if double else policy


def make_rep_batch(policy: MTSACTEPolicy, batch_size: int = 8, seed: int = 1) -> RepresentationBatch:
    """A task-major batch (N, L, state + one-hot) with its z and action noise, in the policy's dtype."""
    dtype = next(policy.parameters()).dtype
    gen = th.Generator().manual_seed(seed)
    n = policy.n_tasks
    state = th.randn(n, batch_size, policy.state_dim, generator=gen, dtype=dtype)
    one_hot = th.eye(n, dtype=dtype)[:, None, :].expand(n, batch_size, n)
    obs = th.cat([state, one_hot], dim=-1)
    z_noise = th.randn(n, batch_size, policy.z_dim, generator=gen, dtype=dtype)
    action_noise = th.randn(n, batch_size, policy.action_dim, generator=gen, dtype=dtype)
    return RepresentationBatch(obs, z_noise, action_noise)


def make_ent_coef(n_tasks: int, dtype: th.dtype = th.float64) -> th.Tensor:
    """Distinct per-task entropy coefficients beta_i."""
    return th.linspace(0.005, 0.03, n_tasks, dtype=dtype)


@pytest.fixture
def small_setup():
    """``(policy, batch, ent_coef, objectives)``: N=4 tasks, L=8, net_arch=[16, 16], float64.

    With this seed and a step size of 1e-2, mu = [2, 3, 1, 2] (a tie between tasks 0 and 3).
    """
    policy = make_te_policy(seed=6)
    batch = make_rep_batch(policy, seed=106)
    ent_coef = make_ent_coef(policy.n_tasks)
    return policy, batch, ent_coef, TaskObjectives(policy, batch, ent_coef)


# ------------------------------------------------------------------------------- plain-loop references
# The paper's equations written out one task (or one sample) at a time with ordinary modules and autograd, without
# the package's vectorised functions: the reference the vectorised code is compared with.
def loop_split(out: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
    mean, log_std = out.chunk(2, dim=-1)
    return mean, log_std.clamp(-20.0, 2.0)


def loop_mlp(params: list[th.Tensor], x: th.Tensor, activation: nn.Module) -> th.Tensor:
    """``nn.Sequential(Linear, act, ..., Linear)`` evaluated from its parameter list [W0, b0, W1, b1, ...]."""
    n_layers = len(params) // 2
    for layer in range(n_layers):
        x = x @ params[2 * layer].T + params[2 * layer + 1]
        if layer < n_layers - 1:
            x = activation(x)
    return x


def loop_embedding(policy, batch: RepresentationBatch, i: int) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
    """z = mean + std * z_noise of task i's slice, from a plain call of the encoder."""
    mean, log_std = loop_split(policy.encoder(batch.obs[i]))
    return mean + log_std.exp() * batch.z_noise[i], mean, log_std


def loop_q(policy, member: int, x: th.Tensor) -> th.Tensor:
    """Critic ensemble member ``member`` (task i, twin j: i * n_critics + j) applied to ``x``, layer by layer."""
    layers = policy.critic.q_net.layers
    for index, layer in enumerate(layers):
        x = x @ layer.weight[member] + layer.bias[member, 0]
        if index < len(layers) - 1:
            x = policy.critic.q_net.activation(x)
    return x.squeeze(-1)


def loop_log_prob(mean: th.Tensor, log_std: th.Tensor, noise: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
    """a = tanh(mean + std * noise) and log pi(a) of the tanh-squashed Gaussian (SB3's 1e-6 in the correction)."""
    pre_tanh = mean + log_std.exp() * noise
    action = th.tanh(pre_tanh)
    gaussian = th.distributions.Normal(mean, log_std.exp()).log_prob(pre_tanh)
    return action, (gaussian - th.log(1.0 - action**2 + 1e-6)).sum(dim=-1)


def loop_objective(policy, actor, batch: RepresentationBatch, ent_coef: th.Tensor, i: int, z: th.Tensor):
    """J_SAC(theta, phi, T_i) = -mean(beta_i log pi(a|s,z) - min_j Q_ij(s, a)) on task i's slice, a = tanh(m + s*eps).

    ``actor`` is any callable from (state, z) to the actor's raw output (a module, or a closure over parameters).
    """
    state = batch.obs[i][:, : policy.state_dim]
    mean, log_std = loop_split(actor(th.cat([state, z], dim=-1)))
    action, log_prob = loop_log_prob(mean, log_std, batch.action_noise[i])
    q_values = [
        loop_q(policy, i * policy.n_critics + j, th.cat([state, action], dim=-1)) for j in range(policy.n_critics)
    ]
    min_q = th.stack(q_values).min(dim=0).values
    return -(ent_coef[i] * log_prob - min_q).mean()


def stepped_actor(policy, batch, ent_coef, k: int, z: list[th.Tensor], step_size: float) -> Callable:
    """The raw output (``dist_params``) of a copy of the actor moved to theta^k = theta + alpha * grad_theta J_k
    (Eq. 4); any actor architecture."""
    params = list(policy.actor.parameters())
    grads = th.autograd.grad(loop_objective(policy, policy.actor.dist_params, batch, ent_coef, k, z[k]), params)
    actor_k = copy.deepcopy(policy.actor)
    with th.no_grad():
        for param, g in zip(actor_k.parameters(), grads, strict=True):
            param.add_(step_size * g)
    return actor_k.dist_params


def loop_transfer(policy, batch, ent_coef, step_size: float) -> tuple[th.Tensor, th.Tensor]:
    """J_i(theta) and the N x N matrix [k, i] = J_i(theta^k) - J_i(theta), with two plain loops."""
    n = policy.n_tasks
    z = [loop_embedding(policy, batch, i)[0].detach() for i in range(n)]
    actor = policy.actor.dist_params
    before = th.stack([loop_objective(policy, actor, batch, ent_coef, i, z[i]) for i in range(n)]).detach()
    matrix = th.zeros(n, n, dtype=before.dtype)
    for k in range(n):
        actor_k = stepped_actor(policy, batch, ent_coef, k, z, step_size)
        for i in range(n):
            matrix[k, i] = loop_objective(policy, actor_k, batch, ent_coef, i, z[i]).detach() - before[i]
    return before, matrix


@fused_relu_mlp(False)  # second derivatives: the layer-by-layer graph
def loop_task_gradients(policy, batch, ent_coef, z: list[th.Tensor], create_graph: bool = False) -> list[th.Tensor]:
    """grad_theta J_i, flattened, for every task i."""
    params = list(policy.actor.parameters())
    grads = []
    for i in range(policy.n_tasks):
        value = loop_objective(policy, policy.actor.net, batch, ent_coef, i, z[i])
        grads.append(th.cat([g.flatten() for g in th.autograd.grad(value, params, create_graph=create_graph)]))
    return grads


def loop_nt_objective(policy, batch, ent_coef, harmful: list[int], step_size: float) -> float:
    """J-hat^NT (Eq. 10-12): mean over harmful k of mean over all i of J_i(theta^k)."""
    n = policy.n_tasks
    z = [loop_embedding(policy, batch, i)[0].detach() for i in range(n)]
    rows = []
    for k in harmful:
        actor_k = stepped_actor(policy, batch, ent_coef, k, z, step_size)
        rows.append(
            sum(float(loop_objective(policy, actor_k, batch, ent_coef, i, z[i]).detach()) for i in range(n)) / n
        )
    return sum(rows) / len(rows)


def loop_vae_objective(policy, batch) -> th.Tensor:
    """J^VAE (Eq. 13): mean over every sample of ||D(z, onehot) - s||^2 + KL(N(m, s^2) || N(0, I))."""
    terms = []
    for i in range(policy.n_tasks):
        z, mean, log_std = loop_embedding(policy, batch, i)
        state, one_hot = batch.obs[i][:, : policy.state_dim], batch.obs[i][:, policy.state_dim :]
        reconstruction = policy.decoder(th.cat([z, one_hot], dim=-1))
        for b in range(state.shape[0]):
            squared_error = ((reconstruction[b] - state[b]) ** 2).sum()
            kl = 0.5 * (mean[b] ** 2 + th.exp(2 * log_std[b]) - 1.0 - 2 * log_std[b]).sum()
            terms.append(squared_error + kl)
    return th.stack(terms).mean()


@fused_relu_mlp(False)  # second derivatives: the layer-by-layer graph
def loop_rep_gradients(
    policy,
    batch,
    ent_coef,
    harmful: list[int],
    step_size: float,
    c_vae: float,
    use_vae: bool = True,
    estimator: str = "virtual_step",
) -> tuple[th.Tensor, list[th.Tensor], list[th.Tensor]]:
    """-J^rep (Eq. 14) and its gradients w.r.t. the encoder and decoder parameters, by plain autograd.

    ``virtual_step``: J^NT = mean_{k in harmful} mean_i J_i(theta + alpha grad_theta J_k(theta, z(phi)), z(phi)), the
    inner gradient taken with ``create_graph=True`` so that d g_k / d phi is part of the result. ``gradient_dot``:
    its first-order expansion mean_i J_i + alpha (mean_i g_i) . (mean_{k in harmful} g_k), differentiated likewise.
    """
    n = policy.n_tasks
    theta = list(policy.actor.parameters())
    z = [loop_embedding(policy, batch, i)[0] for i in range(n)]
    j_nt = th.zeros((), dtype=z[0].dtype)
    if harmful and estimator == "virtual_step":
        rows = []
        for k in harmful:
            j_k = loop_objective(policy, policy.actor.net, batch, ent_coef, k, z[k])
            g_k = th.autograd.grad(j_k, theta, create_graph=True)
            theta_k = [p + step_size * g for p, g in zip(theta, g_k, strict=True)]

            def actor_k(x, theta_k=theta_k):
                return loop_mlp(theta_k, x, policy.actor.net[1])

            rows.append(sum(loop_objective(policy, actor_k, batch, ent_coef, i, z[i]) for i in range(n)) / n)
        j_nt = sum(rows) / len(rows)
    elif harmful:
        values = [loop_objective(policy, policy.actor.net, batch, ent_coef, i, z[i]) for i in range(n)]
        grads = loop_task_gradients(policy, batch, ent_coef, z, create_graph=True)
        mean_grad = sum(grads) / n
        harmful_grad = sum(grads[k] for k in harmful) / len(harmful)
        j_nt = sum(values) / n + step_size * (mean_grad * harmful_grad).sum()
    j_vae = loop_vae_objective(policy, batch) if use_vae else th.zeros((), dtype=j_nt.dtype)
    loss = -(j_nt - c_vae * j_vae)
    encoder, decoder = list(policy.encoder.parameters()), list(policy.decoder.parameters())
    grads = (
        th.autograd.grad(loss, encoder + decoder, allow_unused=True)
        if loss.requires_grad
        else [None] * len(encoder + decoder)
    )
    grads = [th.zeros_like(p) if g is None else g for p, g in zip(encoder + decoder, grads, strict=True)]
    return loss.detach(), grads[: len(encoder)], grads[len(encoder) :]


def kappa_benign_set(mu, n_select: int) -> set[int]:
    """Eq. 7 by its definition: kappa(1), ..., kappa(M) picked one at a time as an argmin of mu over the tasks not
    picked yet, then C_s = {j | mu_j <= mu_kappa(M)}."""
    mu = [int(v) for v in mu]
    chosen: list[int] = []
    for _ in range(n_select):
        remaining = [k for k in range(len(mu)) if k not in chosen]
        best = remaining[0]
        for k in remaining:
            if mu[k] < mu[best]:
                best = k
        chosen.append(best)
    return {j for j in range(len(mu)) if mu[j] <= mu[chosen[-1]]}


def fixed_randn_like(monkeypatch, seed: int = 0):
    """Make ``th.randn_like`` return the same standard normal draw at every call of a given shape (so the noise of
    a reparameterised sample is known); return the function ``draw(shape, dtype)`` that reproduces it."""

    def draw(shape, dtype) -> th.Tensor:
        return th.randn(tuple(shape), generator=th.Generator().manual_seed(seed), dtype=dtype)

    monkeypatch.setattr(th, "randn_like", lambda x, **kwargs: draw(x.shape, x.dtype).to(x.device))
    return draw


def disable_representation_updates(model, monkeypatch) -> None:
    """The next train() calls run SAC updates only (no J^rep step, no recomputation of mu, C_s and w)."""
    monkeypatch.setattr(model, "update_representation", lambda batch_size: None)


# ----------------------------------------------------------------------------------------- environments
def episode_reward(task: int, episode: int, step: int) -> float:
    """Reward of step ``step`` of episode ``episode`` of task ``task``: a multiple of 1/4 (exact in float32)."""
    return ((5 * episode + 3 * task + 2 * step) % 7) * 0.25


def episode_return(task: int, episode: int, length: int) -> float:
    return sum(episode_reward(task, episode, t) for t in range(length))


class EpisodeEnv(gym.Env):
    """Sub-env ``task`` of a multi-task env whose rewards depend only on (task, episode, step), not on the action.

    Observation: (task, step, episode) followed by a one-hot of size ``one_hot_size`` (default ``n_tasks``).
    Episodes are truncated after ``episode_length`` steps.
    """

    def __init__(self, task: int, n_tasks: int, episode_length: int = 5, one_hot_size: int | None = None) -> None:
        self.task, self.episode_length = task, episode_length
        size = n_tasks if one_hot_size is None else one_hot_size
        self.one_hot = np.zeros(size, dtype=np.float32)
        self.one_hot[task] = 1.0
        self.observation_space = spaces.Box(-np.inf, np.inf, shape=(3 + size,), dtype=np.float32)
        self.action_space = spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)
        self.episode, self.t = -1, 0
        self.task_name = f"episode-task-{task}"

    def _obs(self) -> np.ndarray:
        return np.concatenate([np.array([self.task, self.t, self.episode], dtype=np.float32), self.one_hot])

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        self.episode += 1
        self.t = 0
        return self._obs(), {}

    def step(self, action):
        reward = episode_reward(self.task, self.episode, self.t)
        self.t += 1
        truncated = self.t >= self.episode_length
        return self._obs(), reward, False, truncated, {"is_success": False, "task_index": self.task}


def make_episode_env(n_tasks: int = 4, n_envs: int | None = None, **kwargs: Any) -> DummyVecEnv:
    """DummyVecEnv of ``n_envs`` (default ``n_tasks``) :class:`EpisodeEnv`, sub-env i being task i."""
    n_envs = n_tasks if n_envs is None else n_envs
    return DummyVecEnv([lambda i=i: EpisodeEnv(i, n_tasks, **kwargs) for i in range(n_envs)])


@pytest.fixture
def toy_env():
    """The 4-task toy-conflict env (seed 0)."""
    from sb3_mtte import make_mt_env

    env = make_mt_env("toy-conflict", seed=0)
    yield env
    env.close()


def small_model_kwargs(**overrides: Any) -> dict[str, Any]:
    """Keyword arguments of a small, fast MTSACTE on CPU."""
    kwargs: dict[str, Any] = {
        "learning_starts": 40,
        "batch_size": 8,
        "buffer_size": 4_000,
        "top_k": 3,
        "iteration_length": 10,
        "rep_gradient_steps": 2,
        "policy_kwargs": {"net_arch": [16, 16], "z_dim": 3},
        "seed": 0,
        "device": "cpu",
    }
    kwargs.update(overrides)
    return kwargs


def all_parameters(model) -> dict[str, th.Tensor]:
    """Every trainable tensor of a model: policy state dict (encoder, decoder, actor, critics, targets), beta."""
    params = {f"policy.{k}": v.detach().clone() for k, v in model.policy.state_dict().items()}
    if model.log_ent_coef is not None:
        params["log_ent_coef"] = model.log_ent_coef.detach().clone()
    return params


def assert_state_equal(a: Any, b: Any, path: str = "") -> None:
    """Recursive exact equality of nested dicts / lists / tensors / arrays (optimizer state dicts, ...)."""
    if isinstance(a, th.Tensor):
        assert isinstance(b, th.Tensor), path
        assert a.dtype == b.dtype and a.shape == b.shape, path
        assert th.equal(a, b), path
    elif isinstance(a, np.ndarray):
        np.testing.assert_array_equal(a, b, err_msg=path)
    elif isinstance(a, dict):
        assert set(a) == set(b), path
        for key in a:
            assert_state_equal(a[key], b[key], f"{path}.{key}")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            assert_state_equal(x, y, f"{path}[{i}]")
    else:
        assert a == b, path


# ---------------------------------------------------------------------------------------------------- zoo
CUDA = pytest.mark.skipif(not th.cuda.is_available(), reason="needs a CUDA GPU")
ENV = "toy-conflict"
# CPU: on a GPU the resumed runs below would mix eager updates with graph replays, equal only within float tolerance
QUIET_CPU = ["--no-progress", "--verbose", "0", "--device", "cpu"]
TINY = [*QUIET_CPU, "--seed", "3"]


def tiny_train(log_dir: Path, algo: str = "mtsacte", *extra: str, steps: int = 400) -> Path:
    """Train ``algo`` on the 4-task toy for ``steps`` env steps with the zoo; return the run folder."""
    from sb3_mtte.zoo import main

    main(
        [
            "train",
            "--algo",
            algo,
            "--env",
            ENV,
            "-f",
            str(log_dir),
            "-n",
            str(steps),
            "--eval-freq",
            "200",
            "--eval-episodes",
            "2",
            *TINY,
            *extra,
        ]
    )
    runs = sorted((log_dir / algo).glob(f"{ENV}_*"), key=lambda p: int(p.name.rsplit("_", 1)[1]))
    return runs[-1]
