"""Vectorised evaluation of the per-task objectives, the negative-transfer matrix and the J^rep gradient.

Everything is a pure function of the parameters (``torch.func``): per-task gradients are one ``vmap(grad)``
over the task axis, the N x N evaluation plain batched matmuls with the stacked virtual parameters theta^k (the
actor's K weight sets on all rows, each task's critics on the K actions of its rows), and the meta-gradient of J^NT
w.r.t. phi differentiates through the inner gradient (second order). Batches are
task-major ``(N, L, ...)`` and every comparison uses the same batch and the same noise (common random numbers).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch as th
from torch.func import functional_call, grad, vjp, vmap

from sb3_mtte.common.distributions import gaussian_sample, split_mean_log_std
from sb3_mtte.common.losses import sac_task_objective
from sb3_mtte.mtsacte.objectives import (
    negative_transfer_objective,
    representation_objective,
    vae_objective,
    virtual_step,
)
from sb3_mtte.mtsacte.policies import MTSACTEPolicy

Params = dict[str, th.Tensor]
ESTIMATORS = ("virtual_step", "gradient_dot")


@dataclass
class RepresentationBatch:
    """A task-major mini-batch with the noise that every objective evaluation shares.

    :param obs: ``(N, L, state_dim + N)`` observations (state + one-hot).
    :param z_noise: ``(N, L, z_dim)`` standard normal noise of z ~ E_phi.
    :param action_noise: ``(N, L, action_dim)`` standard normal noise of a ~ pi_theta.
    """

    obs: th.Tensor
    z_noise: th.Tensor
    action_noise: th.Tensor

    def to(self, dtype: th.dtype) -> RepresentationBatch:
        """The same batch and noise in ``dtype``."""
        return RepresentationBatch(self.obs.to(dtype), self.z_noise.to(dtype), self.action_noise.to(dtype))

    @classmethod
    def draw(cls, obs: th.Tensor, z_dim: int, action_dim: int) -> RepresentationBatch:
        """The batch of task-major observations ``(N, L, obs_dim)`` with fresh noise."""
        shape = obs.shape[:2]
        return cls(obs, th.randn(*shape, z_dim, device=obs.device), th.randn(*shape, action_dim, device=obs.device))


class TaskObjectives:
    """J_SAC(theta, phi, T_i) of every task on a fixed batch, as pure functions of theta and z.

    Critics and beta are held fixed (detached) while theta and phi vary.

    :param policy: the MTSACTE policy (its actor, encoder and critics are read, never modified).
    :param batch: the shared batch and noise.
    :param ent_coef: ``(N,)`` beta_i.
    :param chunk_size: theta^k per batched pass of :meth:`after_virtual_steps` (None: all at once).
    :param dtype: the dtype of every evaluation (the batch's when None); theta, the critics, beta and the batch are
        cast to it.
    """

    def __init__(
        self,
        policy: MTSACTEPolicy,
        batch: RepresentationBatch,
        ent_coef: th.Tensor,
        chunk_size: int | None = None,
        dtype: th.dtype | None = None,
    ) -> None:
        self.dtype = batch.obs.dtype if dtype is None else dtype
        self.policy, self.batch, self.chunk_size = policy, batch.to(self.dtype), chunk_size
        self.state = self.batch.obs[..., : policy.state_dim]
        self.q_params = {k: v.detach().to(self.dtype) for k, v in policy.critic.task_parameters().items()}
        self.ent_coef = ent_coef.detach().to(self.dtype)

    def in_dtype(self, dtype: th.dtype) -> TaskObjectives:
        """The same objectives on the same batch and noise, evaluated in ``dtype``."""
        return TaskObjectives(self.policy, self.batch, self.ent_coef, self.chunk_size, dtype)

    def theta(self) -> Params:
        return {k: v.detach().to(self.dtype) for k, v in self.policy.actor.named_parameters()}

    def phi(self) -> tuple[Params, Params]:
        encoder = {k: v.detach() for k, v in self.policy.encoder.named_parameters()}
        decoder = {k: v.detach() for k, v in self.policy.decoder.named_parameters()}
        return encoder, decoder

    def embedding(self, encoder_params: Params) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
        """z = mean + std * noise from E_phi, with its mean and log-std, each ``(N, L, ...)``."""
        mean, log_std = split_mean_log_std(functional_call(self.policy.encoder, encoder_params, (self.batch.obs,)))
        return gaussian_sample(mean, log_std, self.batch.z_noise), mean, log_std

    def _single(self, theta: Params, q_params: Params, obs: th.Tensor, z: th.Tensor, noise: th.Tensor, beta):
        """J_SAC of one task from its ``(L, ...)`` slice of the batch, through the actor's training forward pass."""
        policy = self.policy
        action_input = policy.actor_input(obs[..., : policy.state_dim], z)
        action, log_prob = functional_call(policy.actor, theta, (action_input, noise))
        one_task = {k: v.unsqueeze(0) for k, v in q_params.items()}
        min_q = policy.critic.forward_stacked(one_task, obs.unsqueeze(0), action.unsqueeze(0))[0].min(dim=0).values
        return sac_task_objective(log_prob.unsqueeze(0), min_q.unsqueeze(0), beta.unsqueeze(0)).squeeze(0)

    def _task_args(self, z: th.Tensor, tasks: th.Tensor | None):
        args = (self.q_params, self.batch.obs, z, self.batch.action_noise, self.ent_coef)
        if tasks is None:
            return args
        q_params, *rest = args
        return ({k: v[tasks] for k, v in q_params.items()}, *(x[tasks] for x in rest))

    def all_tasks(self, theta: Params, z: th.Tensor) -> th.Tensor:
        """``(N,)``: J_i(theta) for every task i (the same arithmetic as one row of :meth:`after_virtual_steps`)."""
        return self._stacked_objectives({k: v.unsqueeze(0) for k, v in theta.items()}, z)[0]

    def gradients(self, theta: Params, z: th.Tensor, tasks: th.Tensor | None = None) -> Params:
        """grad_theta J_k(theta) for every task k (or the given ones), stacked on a leading axis."""
        return vmap(grad(self._single), in_dims=(None, 0, 0, 0, 0, 0))(theta, *self._task_args(z, tasks))

    def after_virtual_steps(self, thetas: Params, z: th.Tensor) -> th.Tensor:
        """``(K, N)``: row k holds J_i(theta^k) for every task i, for stacked parameters theta^k, evaluated
        ``chunk_size`` theta^k at a time (all at once for None)."""
        n_sets = next(iter(thetas.values())).shape[0]
        size = n_sets if self.chunk_size is None else self.chunk_size
        chunks = [{k: v[start : start + size] for k, v in thetas.items()} for start in range(0, n_sets, size)]
        return th.cat([self._stacked_objectives(chunk, z) for chunk in chunks])

    def _stacked_objectives(self, thetas: Params, z: th.Tensor) -> th.Tensor:
        """``(K, N)`` J_i(theta^k) in batched passes: the actor with its K parameter sets on all N x L rows, then
        each task's critics on the K actions of its rows."""
        policy, obs, (n, length) = self.policy, self.batch.obs, self.state.shape[:2]
        action_input = policy.actor_input(self.state, z)
        action, log_prob = policy.actor.forward_stacked(thetas, action_input, self.batch.action_noise)
        n_sets = action.shape[0]
        obs_rows = obs.unsqueeze(1).expand(n, n_sets, length, -1).reshape(n, n_sets * length, -1)
        action_rows = action.transpose(0, 1).reshape(n, n_sets * length, -1)
        q = policy.critic.forward_stacked(self.q_params, obs_rows, action_rows).view(n, -1, n_sets, length)
        return sac_task_objective(log_prob, q.min(dim=1).values.transpose(0, 1), self.ent_coef)


def virtual_parameters(theta: Params, grads: Params, step_size: float) -> Params:
    """Eq. 4 for every stacked gradient: theta^k = theta + alpha * g_k."""
    return {k: virtual_step(theta[k].unsqueeze(0), grads[k], step_size) for k in theta}


def transfer_matrix(
    objectives: TaskObjectives,
    z: th.Tensor,
    step_size: float,
    estimator: str = "virtual_step",
    dtype: th.dtype = th.float64,
) -> th.Tensor:
    """``(N, N)`` matrix [k, i] = J_i(theta^k) - J_i(theta) (Eq. 4-5), the input of mu (Eq. 6), in ``dtype``.

    ``virtual_step`` evaluates it exactly; ``gradient_dot`` uses its first-order expansion alpha * g_k . g_i.

    Each entry is a small difference of two means of Q-sized values. In float32 its rounding error grows with |Q|
    and decides signs at Meta-World's Q near 1000, so the gradients, theta^k and both evaluations run in ``dtype``,
    float64 by default (``docs/paper_silent.md``, "mu in float64").
    """
    if estimator not in ESTIMATORS:
        raise ValueError(f"nt_estimator must be one of {ESTIMATORS}, got {estimator!r}.")
    objectives, z = objectives.in_dtype(dtype), z.to(dtype)
    theta = objectives.theta()
    grads = objectives.gradients(theta, z)
    if estimator == "gradient_dot":
        flat = th.cat([g.flatten(1) for g in grads.values()], dim=1)
        return step_size * flat @ flat.T
    # theta itself is evaluated in the same stacked pass as the theta^k, so that alpha = 0 gives exactly 0.
    thetas = {k: th.cat([theta[k].unsqueeze(0), v]) for k, v in virtual_parameters(theta, grads, step_size).items()}
    values = objectives.after_virtual_steps(thetas, z)
    return values[1:] - values[:1]


def exact_nt_objective(objectives: TaskObjectives, theta: Params, z: th.Tensor, harmful: th.Tensor, step_size: float):
    """Eq. 11-12 exactly: the mean over k in C \\ C_s of mean_i J_i(theta + alpha grad_theta J_k(theta, phi), phi)."""
    grads = objectives.gradients(theta, z, harmful)
    after = objectives.after_virtual_steps(virtual_parameters(theta, grads, step_size), z)
    return negative_transfer_objective(after)


def first_order_nt_objective(
    objectives: TaskObjectives, theta: Params, z: th.Tensor, harmful: th.Tensor, step_size: float
):
    """Eq. 11-12 to first order in alpha, linear in N: mean_i J_i(theta) + alpha * g_C . g_H, where g_C and g_H
    are the mean task gradients over all tasks and over C \\ C_s (one forward pass, two backward passes)."""
    values, pullback = vjp(lambda t: objectives.all_tasks(t, z), theta)
    n_tasks = values.shape[0]
    (mean_grad,) = pullback(th.full_like(values, 1.0 / n_tasks))
    harmful_weights = th.zeros_like(values).index_fill(0, harmful, 1.0 / harmful.numel())
    (harmful_grad,) = pullback(harmful_weights)
    dot = sum((mean_grad[k] * harmful_grad[k]).sum() for k in theta)
    return values.mean() + step_size * dot


def representation_loss(
    objectives: TaskObjectives,
    encoder_params: Params,
    decoder_params: Params,
    harmful_tasks: th.Tensor,
    step_size: float,
    c_vae: float,
    use_vae: bool = True,
    estimator: str = "virtual_step",
) -> th.Tensor:
    """-J^rep (Eq. 14) as a function of phi (encoder) and varphi (decoder); minimise it.

    J^NT (Eq. 11-12) differentiates through theta^k = theta + alpha grad_theta J_k(theta, phi) (second order),
    exactly (``virtual_step``) or to first order in alpha (``gradient_dot``).
    """
    z, mean, log_std = objectives.embedding(encoder_params)
    theta = objectives.theta()
    if harmful_tasks.numel() == 0:
        j_nt = z.new_zeros(())
    elif estimator == "gradient_dot":
        j_nt = first_order_nt_objective(objectives, theta, z, harmful_tasks, step_size)
    else:
        j_nt = exact_nt_objective(objectives, theta, z, harmful_tasks, step_size)
    if use_vae:
        one_hot = objectives.batch.obs[..., objectives.state.shape[-1] :]
        reconstruction = functional_call(objectives.policy.decoder, decoder_params, (th.cat([z, one_hot], dim=-1),))
        j_vae = vae_objective(reconstruction, objectives.state, mean, log_std)
    else:
        j_vae = z.new_zeros(())
    return -representation_objective(j_nt, j_vae, c_vae)


def representation_gradients(
    objectives: TaskObjectives, harmful_tasks: th.Tensor, **kwargs
) -> tuple[th.Tensor, Params, Params]:
    """Loss -J^rep and its gradients w.r.t. the encoder and decoder parameters."""
    encoder_params, decoder_params = objectives.phi()

    def loss_with_aux(enc: Params, dec: Params):
        loss = representation_loss(objectives, enc, dec, harmful_tasks, **kwargs)
        return loss, loss

    (enc_grads, dec_grads), loss = grad(loss_with_aux, argnums=(0, 1), has_aux=True)(encoder_params, decoder_params)
    return loss, enc_grads, dec_grads


class TransferStatistics:
    """Running mean and standard error of the transfer matrices measured on an iteration's batches."""

    def __init__(self) -> None:
        self.count = 0
        self.total: th.Tensor | None = None
        self.total_squares: th.Tensor | None = None

    def add(self, matrix: th.Tensor) -> None:
        self.count += 1
        self.total = matrix.clone() if self.total is None else self.total + matrix
        squares = matrix.pow(2)
        self.total_squares = squares if self.total_squares is None else self.total_squares + squares

    @property
    def mean(self) -> th.Tensor:
        return self.total / self.count  # type: ignore[operator]

    @property
    def standard_error(self) -> th.Tensor:
        """Standard error of the mean (zero after a single batch)."""
        if self.count < 2:
            return th.zeros_like(self.total)  # type: ignore[arg-type]
        variance = (self.total_squares / self.count - self.mean.pow(2)).clamp_min(0) * self.count / (self.count - 1)
        return (variance / self.count).sqrt()
