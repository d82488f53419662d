"""The paper's equations as pure functions (Section 3). Every tensor is task-major; N = number of tasks.

Sign convention: J_SAC,i (:func:`sb3_mtte.common.losses.sac_task_objective`) is an objective to maximise (Eq. 1
negated), J_SAC,i = -mean(beta_i log pi - min_j Q_ij). Eq. 9's weighted sum is the actor step of the algorithm.
"""

from __future__ import annotations

from typing import NamedTuple

import torch as th


def virtual_step(theta: th.Tensor, grad: th.Tensor, step_size: float) -> th.Tensor:
    """Eq. 4: theta^k = theta + alpha * grad_theta J_SAC(theta, phi, T_k) (gradient ascent)."""
    return theta + step_size * grad


def negative_transfer_measure(transfer_matrix: th.Tensor) -> th.Tensor:
    """Eq. 6: mu(T_k) = |{i : J_i(theta^k) < J_i(theta)}|, counted over all N tasks i (k included).

    :param transfer_matrix: ``(N, N)``, entry [k, i] = J_i(theta^k) - J_i(theta).
    :return: ``(N,)`` integer counts.
    """
    return (transfer_matrix < 0).sum(dim=1)


def significant_negative_transfer_measure(mean: th.Tensor, standard_error: th.Tensor, z: float = 2.0) -> th.Tensor:
    """mu counting only the entries [k, i] whose mean over batches is below zero by more than z standard errors."""
    return (mean + z * standard_error < 0).sum(dim=1)


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


class TaskSelection(NamedTuple):
    """mu, C_s and w of one recomputation, with the transfer matrix they were read from (tensors, one device).

    :param transfer_matrix: ``(N, N)``, entry [k, i] = J_i(theta^k) - J_i(theta).
    :param mu: ``(N,)`` long, Eq. 6.
    :param selected: ``(N,)`` bool mask of C_s, Eq. 7.
    :param weights: ``(N,)`` w, Eq. 8.
    """

    transfer_matrix: th.Tensor
    mu: th.Tensor
    selected: th.Tensor
    weights: th.Tensor


def select_tasks(
    transfer_matrix: th.Tensor, n_select: int, dtype: th.dtype, standard_error: th.Tensor | None = None
) -> TaskSelection:
    """Eq. 6-8 together: mu from the transfer matrix, the benign set C_s of the M least harmful tasks, and w.

    :param transfer_matrix: ``(N, N)``, entry [k, i] = J_i(theta^k) - J_i(theta) (or its mean over batches).
    :param n_select: M.
    :param dtype: dtype of w (the actor's).
    :param standard_error: ``(N, N)`` standard error of a mean matrix: mu then counts only the entries significantly
        below zero (:func:`significant_negative_transfer_measure`); None is Eq. 6.
    """
    if standard_error is None:
        mu = negative_transfer_measure(transfer_matrix)
    else:
        mu = significant_negative_transfer_measure(transfer_matrix, standard_error)
    return TaskSelection(transfer_matrix, mu, select_benign_tasks(mu, n_select), task_weights(mu, dtype))


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
