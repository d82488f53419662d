"""Unit tests of the paper's equations as pure functions (sb3_mtte.mtsacte.objectives), Eq. 1 and 4-14."""

from __future__ import annotations

import itertools
import math

import pytest
import torch as th

from sb3_mtte.common.losses import per_task_actor_loss
from sb3_mtte.mtsacte.objectives import (
    gaussian_kl_to_standard_normal,
    negative_transfer_measure,
    negative_transfer_objective,
    policy_objective,
    representation_objective,
    sac_task_objective,
    select_benign_tasks,
    task_weights,
    vae_objective,
    virtual_step,
)


# ------------------------------------------------------------------------------------ J_SAC (Eq. 1 negated)
def test_sac_task_objective_sign_and_value():
    # Task 0: beta=0.5, log pi = [1, 3], min Q = [2, 4] -> -mean(0.5*1 - 2, 0.5*3 - 4) = -mean(-1.5, -2.5) = 2.
    # Task 1: beta=2.0, log pi = [0, -1], min Q = [1, 1] -> -mean(0 - 1, -2 - 1) = -mean(-1, -3) = 2.
    log_prob = th.tensor([[1.0, 3.0], [0.0, -1.0]])
    min_q = th.tensor([[2.0, 4.0], [1.0, 1.0]])
    ent_coef = th.tensor([0.5, 2.0])
    objective = sac_task_objective(log_prob, min_q, ent_coef)
    assert objective.shape == (2,)
    th.testing.assert_close(objective, th.tensor([2.0, 2.0]))


def test_sac_task_objective_is_maximised_by_q_and_entropy():
    """J_SAC is an objective: larger Q raises it, larger log-probability (less entropy) lowers it."""
    gen = th.Generator().manual_seed(0)
    log_prob, min_q = th.randn(3, 5, generator=gen), th.randn(3, 5, generator=gen)
    ent_coef = th.tensor([0.1, 0.2, 0.3])
    base = sac_task_objective(log_prob, min_q, ent_coef)
    assert (sac_task_objective(log_prob, min_q + 1.0, ent_coef) > base).all()
    assert (sac_task_objective(log_prob + 1.0, min_q, ent_coef) < base).all()
    th.testing.assert_close(sac_task_objective(log_prob, min_q + 1.0, ent_coef) - base, th.ones(3))
    th.testing.assert_close(base - sac_task_objective(log_prob + 1.0, min_q, ent_coef), ent_coef)


def test_sac_task_objective_leading_dims_and_actor_loss():
    """Batched over leading dims (one row per theta^k), and the actor loss of Eq. 1 is exactly -J_SAC."""
    gen = th.Generator().manual_seed(1)
    log_prob, min_q = th.randn(4, 3, 6, generator=gen), th.randn(4, 3, 6, generator=gen)
    ent_coef = th.tensor([0.1, 0.2, 0.3])
    objective = sac_task_objective(log_prob, min_q, ent_coef)
    assert objective.shape == (4, 3)
    for k, i in itertools.product(range(4), range(3)):
        expected = -(ent_coef[i] * log_prob[k, i] - min_q[k, i]).mean()
        th.testing.assert_close(objective[k, i], expected)
        th.testing.assert_close(per_task_actor_loss(log_prob[k], min_q[k], ent_coef)[i], -expected)


# ------------------------------------------------------------------------------------- virtual step (Eq. 4)
def test_virtual_step_values():
    theta = th.tensor([1.0, -2.0, 0.5])
    grad = th.tensor([0.5, 1.0, -4.0])
    th.testing.assert_close(virtual_step(theta, grad, 0.1), th.tensor([1.05, -1.9, 0.1]))
    assert th.equal(virtual_step(theta, grad, 0.0), theta)


def test_virtual_step_is_gradient_ascent():
    """theta^k = theta + alpha * grad J increases J for a small alpha (Eq. 4 is ascent, not descent)."""
    center = th.tensor([1.0, 2.0, -1.0])
    theta = th.zeros(3, requires_grad=True)

    def objective(x: th.Tensor) -> th.Tensor:
        return -((x - center) ** 2).sum()

    (grad,) = th.autograd.grad(objective(theta), theta)
    stepped = virtual_step(theta.detach(), grad, 0.1)
    assert objective(stepped) > objective(theta.detach())
    # A descent step would have lowered it.
    assert objective(theta.detach() - 0.1 * grad) < objective(theta.detach())


def test_virtual_step_broadcasts_over_stacked_gradients():
    theta = th.tensor([[1.0, 2.0]])
    grads = th.tensor([[1.0, 0.0], [0.0, 1.0], [-1.0, -1.0]])
    th.testing.assert_close(virtual_step(theta, grads, 2.0), th.tensor([[3.0, 2.0], [1.0, 4.0], [-1.0, 0.0]]))


# -------------------------------------------------------------------------------------------- mu (Eq. 6)
def test_negative_transfer_measure_counts_rows_including_k_itself():
    # Row k: J_i(theta^k) - J_i(theta). Row 2 has a negative diagonal entry: a step on task 2 that harms task 2
    # itself counts too (mu counts over all N tasks i, k included).
    transfer = th.tensor(
        [
            [0.3, -0.1, 0.2, -0.4],
            [0.1, 0.2, 0.3, 0.4],
            [-0.1, -0.2, -0.3, 0.0],
            [-1.0, -1.0, -1.0, -1.0],
        ]
    )
    mu = negative_transfer_measure(transfer)
    assert mu.tolist() == [2, 0, 3, 4]
    assert not mu.is_floating_point()


def test_negative_transfer_measure_is_strict_and_agrees_with_loop():
    """Equality (no change) is not negative transfer; the count matches a plain double loop."""
    assert negative_transfer_measure(th.zeros(3, 3)).tolist() == [0, 0, 0]
    gen = th.Generator().manual_seed(2)
    transfer = th.randn(6, 6, generator=gen)
    expected = [sum(1 for i in range(6) if transfer[k, i] < 0) for k in range(6)]
    assert negative_transfer_measure(transfer).tolist() == expected


# ------------------------------------------------------------------------------------------- C_s (Eq. 7)
def test_select_benign_tasks_smallest_mu():
    mask = select_benign_tasks(th.tensor([3, 0, 2, 1, 4]), 2)
    assert mask.dtype == th.bool
    assert mask.tolist() == [False, True, False, True, False]


def test_select_benign_tasks_ties_go_to_lower_index():
    # mu = [2, 1, 1, 0], M = 2: kappa(1) = 3 (mu 0), kappa(2) = 1 (mu 1, tie with task 2 broken by index).
    assert th.nonzero(select_benign_tasks(th.tensor([2, 1, 1, 0]), 2)).flatten().tolist() == [1, 3]
    # All tied: the first M task indices.
    assert select_benign_tasks(th.tensor([1, 1, 1, 1, 1]), 3).tolist() == [True, True, True, False, False]
    # Repeated calls give the same answer (deterministic).
    mu = th.tensor([2, 2, 0, 2, 0, 1, 1, 2])
    masks = [select_benign_tasks(mu, 4) for _ in range(5)]
    assert all(th.equal(m, masks[0]) for m in masks)
    assert th.nonzero(masks[0]).flatten().tolist() == [2, 4, 5, 6]


def test_select_benign_tasks_matches_kappa_definition():
    """Eq. 7 written as the paper does: kappa(i) = argmin over the remaining tasks, lower index first."""
    gen = th.Generator().manual_seed(3)
    for _ in range(20):
        n = int(th.randint(2, 9, (1,), generator=gen))
        mu = th.randint(0, n + 1, (n,), generator=gen)
        m = int(th.randint(1, n, (1,), generator=gen))
        chosen: list[int] = []
        for _ in range(m):
            remaining = [k for k in range(n) if k not in chosen]
            chosen.append(min(remaining, key=lambda k: (int(mu[k]), k)))
        mask = select_benign_tasks(mu, m)
        assert int(mask.sum()) == m
        assert sorted(th.nonzero(mask).flatten().tolist()) == sorted(chosen)


# ----------------------------------------------------------------------------------------- weights (Eq. 8)
def test_task_weights_hand_example():
    # N = 3, mu = [0, 1, 3]: w ∝ exp(3 - 0), exp(3 - 1), exp(3 - 3) = e^3, e^2, 1 (sum 28.4746...).
    weights = task_weights(th.tensor([0, 1, 3]))
    expected = th.tensor([0.7053845126982411, 0.2594964603424191, 0.03511902695933972])
    th.testing.assert_close(weights, expected.to(weights.dtype), rtol=1e-6, atol=1e-7)
    # N = 4, mu = [2, 1, 1, 0]: w ∝ e^2, e^3, e^3, e^4.
    expected4 = th.tensor([0.07232948812851327, 0.19661193324148185, 0.19661193324148185, 0.534446645388523])
    th.testing.assert_close(task_weights(th.tensor([2, 1, 1, 0])), expected4.float(), rtol=1e-6, atol=1e-7)


def test_task_weights_keep_float64():
    expected = th.tensor(
        [0.07232948812851327, 0.19661193324148185, 0.19661193324148185, 0.534446645388523], dtype=th.float64
    )
    weights = task_weights(th.tensor([2.0, 1.0, 1.0, 0.0], dtype=th.float64))
    assert weights.dtype == th.float64
    th.testing.assert_close(weights, expected.double(), rtol=1e-12, atol=0)


def test_task_weights_properties():
    gen = th.Generator().manual_seed(4)
    mu = th.randint(0, 6, (6,), generator=gen)
    weights = task_weights(mu)
    assert weights.is_floating_point()
    th.testing.assert_close(weights.sum(), th.tensor(1.0))
    manual = th.tensor([math.exp(6 - int(m)) for m in mu])
    th.testing.assert_close(weights, manual / manual.sum())
    # Uniform mu -> uniform weights; a larger mu never gets a larger weight.
    th.testing.assert_close(task_weights(th.full((5,), 2)), th.full((5,), 0.2))
    for a, b in itertools.product(range(6), repeat=2):
        if mu[a] > mu[b]:
            assert weights[a] < weights[b]


# ------------------------------------------------------------------------------------ J^policy (Eq. 9)
def test_policy_objective_weighted_sum():
    objectives = th.tensor([[1.0, 2.0, 3.0], [0.0, -1.0, 4.0]])
    weights = th.tensor([0.5, 0.25, 0.25])
    th.testing.assert_close(policy_objective(objectives, weights), th.tensor([1.75, 0.75]))
    # One-hot weights select one task's objective.
    th.testing.assert_close(policy_objective(objectives, th.tensor([0.0, 0.0, 1.0])), th.tensor([3.0, 4.0]))


# -------------------------------------------------------------------------------- J^NT (Eq. 10-12)
def test_negative_transfer_objective_is_double_mean():
    # Two harmful tasks k (rows), N = 3 tasks i (columns): 1/|C\C_s| sum_k 1/N sum_i J_i(theta^k).
    after = th.tensor([[1.0, 2.0, 3.0], [4.0, 5.0, 9.0]])
    th.testing.assert_close(negative_transfer_objective(after), th.tensor((2.0 + 6.0) / 2))
    gen = th.Generator().manual_seed(5)
    after = th.randn(3, 5, generator=gen)
    loop = sum(sum(after[k, i] for i in range(5)) / 5 for k in range(3)) / 3
    th.testing.assert_close(negative_transfer_objective(after), loop)


# ------------------------------------------------------------------------------------ VAE (Eq. 13-14)
def test_gaussian_kl_to_standard_normal():
    assert float(gaussian_kl_to_standard_normal(th.zeros(4), th.zeros(4))) == 0.0
    # One dimension, mean 1, std 1: KL = 1/2 * mean^2 = 0.5. Mean 0, std e: 1/2 (e^2 - 1 - 2) .
    th.testing.assert_close(gaussian_kl_to_standard_normal(th.tensor([1.0]), th.tensor([0.0])), th.tensor(0.5))
    th.testing.assert_close(
        gaussian_kl_to_standard_normal(th.tensor([0.0]), th.tensor([1.0])), th.tensor(0.5 * (math.e**2 - 3.0))
    )
    gen = th.Generator().manual_seed(6)
    mean, log_std = (
        th.randn(7, 3, generator=gen, dtype=th.float64),
        0.5 * th.randn(7, 3, generator=gen, dtype=th.float64),
    )
    reference = th.distributions.kl_divergence(
        th.distributions.Independent(th.distributions.Normal(mean, log_std.exp()), 1),
        th.distributions.Independent(th.distributions.Normal(th.zeros_like(mean), th.ones_like(mean)), 1),
    )
    th.testing.assert_close(gaussian_kl_to_standard_normal(mean, log_std), reference)


def test_vae_objective_matches_loop():
    gen = th.Generator().manual_seed(7)
    n, batch, state_dim, z_dim = 3, 4, 5, 2
    reconstruction = th.randn(n, batch, state_dim, generator=gen, dtype=th.float64)
    state = th.randn(n, batch, state_dim, generator=gen, dtype=th.float64)
    mean = th.randn(n, batch, z_dim, generator=gen, dtype=th.float64)
    log_std = 0.3 * th.randn(n, batch, z_dim, generator=gen, dtype=th.float64)
    total = 0.0
    for i, b in itertools.product(range(n), range(batch)):
        squared_error = sum((float(reconstruction[i, b, d]) - float(state[i, b, d])) ** 2 for d in range(state_dim))
        kl = sum(
            0.5 * (float(mean[i, b, j]) ** 2 + math.exp(2 * float(log_std[i, b, j])) - 1 - 2 * float(log_std[i, b, j]))
            for j in range(z_dim)
        )
        total += squared_error + kl
    assert float(vae_objective(reconstruction, state, mean, log_std)) == pytest.approx(total / (n * batch), rel=1e-12)


def test_representation_objective_eq14():
    th.testing.assert_close(representation_objective(th.tensor(3.0), th.tensor(2.0), 0.25), th.tensor(2.5))
    th.testing.assert_close(representation_objective(th.tensor(3.0), th.tensor(2.0), 0.0), th.tensor(3.0))
    # Maximised: a larger VAE loss lowers J^rep, a larger J^NT raises it.
    assert representation_objective(th.tensor(1.0), th.tensor(5.0), 1.0) < representation_objective(
        th.tensor(1.0), th.tensor(4.0), 1.0
    )
