"""Unit tests of the paper's equations as pure functions (sb3_mtte.mtsacte.objectives and the clipped Q loss), Eq. 1,
4-14 and 16, and of the weighted policy loss (Eq. 9) that trains theta."""

from __future__ import annotations

import copy
import itertools
import math

import pytest
import torch as th
from conftest import disable_representation_updates, fixed_randn_like, small_model_kwargs
from references import kappa_benign_set, loop_log_prob, loop_q, loop_split

from sb3_mtte import MTSACTE, make_mt_env
from sb3_mtte.common.losses import clipped_sample_fraction, clipped_soft_q_loss, sac_task_objective
from sb3_mtte.mtsacte.objectives import (
    gaussian_kl_to_standard_normal,
    negative_transfer_measure,
    negative_transfer_objective,
    representation_objective,
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
        th.testing.assert_close(-sac_task_objective(log_prob[k], min_q[k], ent_coef)[i], -expected)


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


@pytest.mark.parametrize(
    ("mu", "n_select", "expected"),
    [
        # kappa(1) = 3 (mu 0), kappa(2) = 1 or 2 (mu 1): the threshold is 1 and both tasks with mu 1 are benign.
        ([2, 1, 1, 0], 2, [1, 2, 3]),
        # All equal: every task is benign, C \ C_s is empty.
        ([1, 1, 1, 1, 1], 3, [0, 1, 2, 3, 4]),
        ([0, 0, 0, 0], 1, [0, 1, 2, 3]),
        # Ties straddling the M-th value: sorted mu = 0, 1, 2, 2, 2, 3; the 3rd smallest is 2, shared by 3 tasks.
        ([3, 1, 2, 2, 0, 2], 3, [1, 2, 3, 4, 5]),
        ([3, 1, 2, 2, 0, 2], 2, [1, 4]),
        # M = 1 with a tie at the minimum: both minimisers.
        ([1, 0, 3, 0], 1, [1, 3]),
        ([2, 0, 1], 1, [1]),
        # The M-th value ends a run of ties exactly: no extra task; one more and all four tasks with mu 2 join.
        ([2, 2, 0, 2, 0, 1, 1, 2], 4, [2, 4, 5, 6]),
        ([2, 2, 0, 2, 0, 1, 1, 2], 5, list(range(8))),
        ([4, 3, 4, 1], 3, [0, 1, 2, 3]),
    ],
)
def test_select_benign_tasks_keeps_every_task_tied_with_the_mth_value(mu, n_select, expected):
    """Eq. 7: C_s = {T_j | mu(T_j) <= mu(T_kappa(M))}, so |C_s| can exceed M."""
    mask = select_benign_tasks(th.tensor(mu), n_select)
    assert th.nonzero(mask).flatten().tolist() == expected
    assert kappa_benign_set(mu, n_select) == set(expected)


def test_select_benign_tasks_matches_kappa_definition():
    """Against the definition written as a loop (kappa(i) = argmin over the tasks not picked yet), random mu."""
    gen = th.Generator().manual_seed(3)
    larger_than_m = 0
    for _ in range(200):
        n = int(th.randint(2, 9, (1,), generator=gen))
        mu = th.randint(0, n + 1, (n,), generator=gen)
        m = int(th.randint(1, n + 1, (1,), generator=gen))
        expected = kappa_benign_set(mu.tolist(), m)
        mask = select_benign_tasks(mu, m)
        assert set(th.nonzero(mask).flatten().tolist()) == expected, (mu.tolist(), m)
        larger_than_m += len(expected) > m
    assert larger_than_m > 20  # ties at the M-th value were exercised


def test_select_benign_tasks_rejects_m_outside_1_to_n():
    for n_select in (0, 5):
        with pytest.raises(ValueError, match=r"n_select \(M\)"):
            select_benign_tasks(th.tensor([0, 1, 2, 3]), n_select)


# ----------------------------------------------------------------------------------------- weights (Eq. 8)
def test_task_weights_hand_example():
    # N = 3, mu = [0, 1, 3]: w ∝ exp(3 - 0), exp(3 - 1), exp(3 - 3) = e^3, e^2, 1 (sum 28.4746...).
    weights = task_weights(th.tensor([0, 1, 3]))
    expected = th.tensor([0.7053845126982411, 0.2594964603424191, 0.03511902695933972])
    th.testing.assert_close(weights, expected.to(weights.dtype), rtol=1e-6, atol=1e-7)
    # N = 4, mu = [2, 1, 1, 0]: w ∝ e^2, e^3, e^3, e^4.
    expected4 = th.tensor([0.07232948812851327, 0.19661193324148185, 0.19661193324148185, 0.534446645388523])
    th.testing.assert_close(task_weights(th.tensor([2, 1, 1, 0])), expected4.float(), rtol=1e-6, atol=1e-7)


def test_task_weights_dtype():
    """Computed in the requested dtype (float32 by default), from integer or floating mu."""
    expected = [0.07232948812851327, 0.19661193324148185, 0.19661193324148185, 0.534446645388523]
    for mu in (th.tensor([2, 1, 1, 0]), th.tensor([2.0, 1.0, 1.0, 0.0], dtype=th.float64)):
        assert task_weights(mu).dtype == th.float32
        weights = task_weights(mu, th.float64)
        assert weights.dtype == th.float64
        th.testing.assert_close(weights, th.tensor(expected, dtype=th.float64), rtol=1e-12, atol=0)


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


# ------------------------------------------------------------------------------- J^policy (Eq. 9) in training
def test_actor_loss_is_the_weighted_sum_of_task_losses(monkeypatch):
    """The loss that trains theta is sum_i w_i (-J_SAC,i) with the model's w (Eq. 8-9): with w = [0.1, 0.2, 0.3,
    0.4] the actor's gradient in a training step equals the gradient of a plain per-sample loop over the same batch
    and noise, where z ~ E_phi (detached), a = tanh(m + s eps), the min is over task i's twin critics (after their
    update in the same step) and beta_i is task i's coefficient."""
    model = MTSACTE("MlpPolicy", make_mt_env("toy-conflict", seed=0), **small_model_kwargs())
    model.learn(200)
    disable_representation_updates(model, monkeypatch)
    weights = [0.1, 0.2, 0.3, 0.4]
    model.task_weights = th.tensor(weights, dtype=th.float32)
    with th.no_grad():
        model.log_ent_coef.copy_(th.log(th.tensor([0.02, 0.05, 0.1, 0.2])))
    beta = model.entropy_coefficients.clone()
    monkeypatch.setattr(model.ent_coef_optimizer, "step", lambda *args, **kwargs: None)  # beta_i fixed
    draw = fixed_randn_like(monkeypatch)
    captured = {}
    original_sample, original_step = model.replay_buffer.sample, model.actor.optimizer.step

    def sample(*args, **kwargs):
        captured["batch"] = original_sample(*args, **kwargs)
        return captured["batch"]

    def step(*args, **kwargs):
        captured["grads"] = [p.grad.detach().clone() for p in model.actor.parameters()]
        return original_step(*args, **kwargs)

    monkeypatch.setattr(model.replay_buffer, "sample", sample)
    monkeypatch.setattr(model.actor.optimizer, "step", step)
    actor_before = copy.deepcopy(model.actor.net)
    batch_size = 8
    model.train(1, batch_size)

    policy, obs = model.policy, captured["batch"].observations.flatten(0, 1)  # task-major rows
    n_rows, state_dim = obs.shape[0], policy.state_dim
    z_noise, action_noise = draw((n_rows, policy.z_dim), obs.dtype), draw((n_rows, policy.action_dim), obs.dtype)

    def reference_gradient(w):
        loss = th.zeros(())
        for row in range(n_rows):
            task, state = row // batch_size, obs[row, :state_dim]
            with th.no_grad():
                mean_z, log_std_z = loop_split(policy.encoder(obs[row]))
            z = mean_z + log_std_z.exp() * z_noise[row]
            action, log_prob = loop_log_prob(*loop_split(actor_before(th.cat([state, z]))), action_noise[row])
            q = [loop_q(policy, task * policy.n_critics + j, th.cat([state, action])) for j in range(policy.n_critics)]
            loss = loss + w[task] / batch_size * (beta[task] * log_prob - th.stack(q).min())
        return th.autograd.grad(loss, list(actor_before.parameters()))

    expected = reference_gradient(weights)
    for applied, reference in zip(captured["grads"], expected, strict=True):
        th.testing.assert_close(applied, reference, rtol=1e-4, atol=1e-6)
    # Uniform weights give a clearly different gradient: the comparison sees the weights.
    uniform = th.cat([g.flatten() for g in reference_gradient([0.25] * 4)])
    flat = th.cat([g.flatten() for g in expected])
    assert (uniform - flat).norm() > 0.05 * flat.norm()


# -------------------------------------------------------------------------------- J^NT (Eq. 10-12)
def test_negative_transfer_objective_is_double_mean():
    # Two harmful tasks k (rows), N = 3 tasks i (columns): 1/|C\C_s| sum_k 1/N sum_i J_i(theta^k).
    after = th.tensor([[1.0, 2.0, 3.0], [4.0, 5.0, 9.0]])
    th.testing.assert_close(negative_transfer_objective(after), th.tensor((2.0 + 6.0) / 2))
    gen = th.Generator().manual_seed(5)
    after = th.randn(3, 5, generator=gen)
    loop = sum(sum(after[k, i] for i in range(5)) / 5 for k in range(3)) / 3
    th.testing.assert_close(negative_transfer_objective(after), loop)


# ------------------------------------------------------------------------------ clipped Q loss (Eq. 15-16)
def test_clipped_soft_q_loss_matches_loop_and_zeroes_large_samples():
    gen = th.Generator().manual_seed(0)
    n_critics, n, batch = 2, 3, 6
    q_values = (3 * th.randn(n_critics, n, batch, generator=gen, dtype=th.float64)).requires_grad_()
    target = 3 * th.randn(n, batch, generator=gen, dtype=th.float64)
    clip = 2.0
    loss = clipped_soft_q_loss(q_values, target, clip)
    plain = clipped_soft_q_loss(q_values, target, None)
    expected, expected_plain = th.zeros(n, dtype=th.float64), th.zeros(n, dtype=th.float64)
    n_clipped = 0
    for i in range(n):
        for c in range(n_critics):
            for b in range(batch):
                sample = 0.5 * float(q_values[c, i, b].detach() - target[i, b]) ** 2
                n_clipped += sample > clip
                expected[i] += min(sample, clip) / batch
                expected_plain[i] += sample / batch
    assert 0 < n_clipped < n_critics * n * batch  # both regimes occur
    th.testing.assert_close(loss.detach(), expected)
    th.testing.assert_close(plain.detach(), expected_plain)
    (gradient,) = th.autograd.grad(loss.sum(), q_values)
    delta = (q_values - target).detach()
    above = 0.5 * delta**2 > clip
    assert th.equal(gradient[above], th.zeros_like(gradient[above]))
    th.testing.assert_close(gradient[~above], delta[~above] / batch)
    # q_loss_clip=None is the plain loss (Eq. 15), and a huge clip changes nothing.
    th.testing.assert_close(clipped_soft_q_loss(q_values, target, 1e12), plain)


def test_clipped_sample_fraction_counts_the_samples_eq16_drops_per_task():
    gen = th.Generator().manual_seed(1)
    n_critics, n, batch, clip = 2, 4, 5, 2.0
    q_values = 3 * th.randn(n_critics, n, batch, generator=gen, dtype=th.float64)
    target = 3 * th.randn(n, batch, generator=gen, dtype=th.float64)
    expected = th.zeros(n, dtype=th.float64)
    for i in range(n):
        for c in range(n_critics):
            for b in range(batch):
                expected[i] += (0.5 * float(q_values[c, i, b] - target[i, b]) ** 2 > clip) / (n_critics * batch)
    assert len(set(expected.tolist())) > 1  # the tasks differ, so a mean over the wrong axis fails
    th.testing.assert_close(clipped_sample_fraction(q_values, target, clip), expected.float())
    # A loss exactly at V_clip still passes its gradient (clamp), so it is not counted; one just above is.
    at_and_above = th.tensor([[[2.0, 2.001]]], dtype=th.float64)  # 0.5 * 2^2 = V_clip, then just above
    th.testing.assert_close(
        clipped_sample_fraction(at_and_above, th.zeros(1, 2, dtype=th.float64), 2.0), th.tensor([0.5])
    )


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
