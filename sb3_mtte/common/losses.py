"""Per-task SAC losses on task-major tensors of shape (N, L) (the paper's Eq. 1-3 and 15-16)."""

from __future__ import annotations

import torch as th


def soft_bellman_sample_loss(q_values: th.Tensor, target_q: th.Tensor) -> th.Tensor:
    """J^Q = 1/2 (Q(s,a) - y)^2 of every critic and sample (Eq. 15).

    :param q_values: ``(n_critics, N, L)`` current Q-values.
    :param target_q: ``(N, L)`` soft targets y (no gradient).
    :return: ``(n_critics, N, L)``.
    """
    return 0.5 * (q_values - target_q.unsqueeze(0)).pow(2)


def clipped_soft_q_loss(q_values: th.Tensor, target_q: th.Tensor, clip: float | None) -> th.Tensor:
    """Per-task clipped soft Bellman loss, Eq. 15-16.

    Per sample and critic, J^Q = 1/2 (Q(s,a) - y)^2 (Eq. 15); Eq. 16 clamps it to [0, V_clip] before the mean over
    the mini-batch, so a sample whose loss exceeds V_clip contributes no gradient. ``clip=None`` is the plain loss.

    :param q_values: ``(n_critics, N, L)`` current Q-values.
    :param target_q: ``(N, L)`` soft targets y (no gradient).
    :param clip: V_clip, or None.
    :return: ``(N,)`` loss of each task, summed over the twin critics.
    """
    per_sample = soft_bellman_sample_loss(q_values, target_q)
    if clip is not None:  # a non-finite loss stays non-finite, so the finiteness check still stops training
        per_sample = th.where(th.isfinite(per_sample), per_sample.clamp(0.0, clip), per_sample)
    return per_sample.mean(dim=-1).sum(dim=0)


def clipped_sample_fraction(q_values: th.Tensor, target_q: th.Tensor, clip: float) -> th.Tensor:
    """Share of task i's samples, over the twin critics and the mini-batch, whose Eq. 15 loss exceeds V_clip: the
    samples Eq. 16 gives no gradient.

    :param q_values: ``(n_critics, N, L)`` current Q-values.
    :param target_q: ``(N, L)`` soft targets y.
    :param clip: V_clip.
    :return: ``(N,)`` in [0, 1].
    """
    with th.no_grad():
        return (soft_bellman_sample_loss(q_values, target_q) > clip).float().mean(dim=(0, -1))


def sac_task_objective(log_prob: th.Tensor, min_q: th.Tensor, ent_coef: th.Tensor) -> th.Tensor:
    """J_SAC(theta, phi, T_i) of every task: Eq. 1 negated, -mean over task i's batch of (beta_i log pi - min_j Q_ij).

    An objective to maximise; the per-task policy loss is its negative, and the policy objective of Eq. 9 is
    sum_i w_i J_SAC,i. Training (the actor step) and the negative-transfer evaluation (Eq. 4-6, 11) both use it.

    :param log_prob: ``(..., N, L)`` log pi(a|s) of reparameterised actions.
    :param min_q: ``(..., N, L)`` minimum over task i's twin critics at those actions.
    :param ent_coef: ``(N,)`` beta_i.
    :return: ``(..., N)``.
    """
    return -(ent_coef[:, None] * log_prob - min_q).mean(dim=-1)


def per_task_entropy_loss(log_ent_coef: th.Tensor, log_prob: th.Tensor, target_entropy: float) -> th.Tensor:
    """Per-task temperature loss, Eq. 3 with beta_i = exp(log beta_i): only task i's samples move beta_i.

    :param log_ent_coef: ``(N,)`` log beta_i (trainable).
    :param log_prob: ``(N, L)`` log-probabilities (detached).
    :param target_entropy: H-bar.
    :return: ``(N,)``.
    """
    return -(log_ent_coef[:, None] * (log_prob + target_entropy)).mean(dim=1)
