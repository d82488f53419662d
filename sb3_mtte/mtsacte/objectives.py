"""The paper's equations as pure functions (Section 3). Every tensor is task-major; N = number of tasks.

Sign convention: J_SAC,i is an objective to maximise (Eq. 1 negated), J_SAC,i = -mean(beta_i log pi - min_j Q_ij).
"""

from __future__ import annotations

import torch as th


def sac_task_objective(log_prob: th.Tensor, min_q: th.Tensor, ent_coef: th.Tensor) -> th.Tensor:
    """J_SAC(theta, phi, T_i) for every task, the negative of Eq. 1 on task i's mini-batch.

    :param log_prob: ``(..., N, L)`` log pi(a|s, z) of reparameterised actions.
    :param min_q: ``(..., N, L)`` min over twin critics Q_i at those actions.
    :param ent_coef: ``(N,)`` beta_i.
    :return: ``(..., N)``.
    """
    return -(ent_coef[:, None] * log_prob - min_q).mean(dim=-1)


def virtual_step(theta: th.Tensor, grad: th.Tensor, step_size: float) -> th.Tensor:
    """Eq. 4: theta^k = theta + alpha * grad_theta J_SAC(theta, phi, T_k) (gradient ascent)."""
    return theta + step_size * grad


def negative_transfer_measure(transfer_matrix: th.Tensor) -> th.Tensor:
    """Eq. 6: mu(T_k) = |{i : J_i(theta^k) < J_i(theta)}|, counted over all N tasks i (k included).

    :param transfer_matrix: ``(N, N)``, entry [k, i] = J_i(theta^k) - J_i(theta).
    :return: ``(N,)`` integer counts.
    """
    return (transfer_matrix < 0).sum(dim=1)


def select_benign_tasks(mu: th.Tensor, n_select: int) -> th.Tensor:
    """Eq. 7: C_s = {T_j | mu(T_j) <= mu(T_kappa(M))}, kappa(M) being the task with the M-th smallest mu.

    Every task tied with the M-th smallest value belongs to C_s, so |C_s| >= M, and C \\ C_s is empty when all mu
    are equal.

    :return: ``(N,)`` boolean mask of C_s.
    """
    if not 1 <= n_select <= mu.shape[-1]:
        raise ValueError(f"n_select (M) must be in [1, N = {mu.shape[-1]}], got {n_select}.")
    threshold = th.sort(mu, dim=-1).values[..., n_select - 1 : n_select]
    return mu <= threshold


def task_weights(mu: th.Tensor, dtype: th.dtype = th.float32) -> th.Tensor:
    """Eq. 8: w_i = exp(N - mu_i) / sum_j exp(N - mu_j), in ``dtype`` (the model's)."""
    n_tasks = mu.shape[-1]
    return th.softmax(n_tasks - mu.to(dtype), dim=-1)


def policy_objective(task_objectives: th.Tensor, weights: th.Tensor) -> th.Tensor:
    """Eq. 9: J^policy(theta) = sum_i w_i J_SAC(theta, phi, T_i)."""
    return (weights * task_objectives).sum(dim=-1)


def negative_transfer_objective(objectives_after_step: th.Tensor) -> th.Tensor:
    """Eq. 10-12: J-hat^NT = 1/|C \\ C_s| sum_{k in C \\ C_s} 1/N sum_i J_SAC(theta^k, phi, T_i).

    :param objectives_after_step: ``(|C \\ C_s|, N)``, row k holds J_i(theta^k) for every task i.
    """
    return objectives_after_step.mean(dim=1).mean(dim=0)


def gaussian_kl_to_standard_normal(mean: th.Tensor, log_std: th.Tensor) -> th.Tensor:
    """KL(N(mean, diag(exp(log_std)^2)) || N(0, I)), summed over the last dimension."""
    return 0.5 * (mean.pow(2) + (2 * log_std).exp() - 1.0 - 2 * log_std).sum(dim=-1)


def vae_objective(reconstruction: th.Tensor, state: th.Tensor, mean: th.Tensor, log_std: th.Tensor) -> th.Tensor:
    """Eq. 13: J^VAE = E[ ||D(z, z_T) - s||^2 + KL(E_phi(.|s, z_T) || N(0, I)) ] (a loss: minimised).

    :param reconstruction: ``(..., state_dim)`` decoder output D(z, one-hot).
    :param state: ``(..., state_dim)``.
    :param mean: ``(..., z_dim)`` encoder mean.
    :param log_std: ``(..., z_dim)`` encoder log-std.
    """
    squared_error = (reconstruction - state).pow(2).sum(dim=-1)
    return (squared_error + gaussian_kl_to_standard_normal(mean, log_std)).mean()


def representation_objective(nt_objective: th.Tensor, vae_loss: th.Tensor, c_vae: float) -> th.Tensor:
    """Eq. 14: J^rep(phi, varphi) = J-hat^NT(phi) - c_vae * J^VAE(phi, varphi) (maximised)."""
    return nt_objective - c_vae * vae_loss
