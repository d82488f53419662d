"""Plain-loop references: the paper's equations written out one task (or one sample) at a time with ordinary
modules and autograd, without the package's vectorised functions; the vectorised code is compared with them."""

from __future__ import annotations

import copy
from collections.abc import Callable

import torch as th
from torch import nn

from sb3_mtte.common.relu_mlp import fused_relu_mlp
from sb3_mtte.mtsacte.transfer import RepresentationBatch


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


def loop_transfer(
    policy, batch, ent_coef, step_size: float, z: list[th.Tensor] | None = None
) -> tuple[th.Tensor, th.Tensor]:
    """J_i(theta) and the N x N matrix [k, i] = J_i(theta^k) - J_i(theta), with two plain loops.

    ``z``: each task's embedding (default: drawn from ``policy``'s encoder with the batch's noise).
    """
    n = policy.n_tasks
    if z is None:
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
