"""MTSACTE's equations against plain references: the negative-transfer machinery of the representation update
(Eq. 4-14, vectorised functions and one recomputation of the algorithm). The training step's equations (Eq. 15-16)
and acting with z are checked in test_mtsacte_training_step.py."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
import torch as th
from conftest import capture_applied_gradients, make_ent_coef, make_rep_batch, make_te_policy, small_model_kwargs
from references import (
    kappa_benign_set,
    loop_embedding,
    loop_nt_objective,
    loop_objective,
    loop_rep_gradients,
    loop_task_gradients,
    loop_transfer,
    loop_vae_objective,
)
from torch import nn
from torch.func import grad

from sb3_mtte import MTSACTE, make_mt_env
from sb3_mtte.mtsacte.objectives import (
    negative_transfer_measure,
    negative_transfer_objective,
    select_benign_tasks,
    task_weights,
)
from sb3_mtte.mtsacte.transfer import (
    RepresentationBatch,
    TaskObjectives,
    representation_gradients,
    representation_loss,
    transfer_matrix,
    virtual_parameters,
)

N_TASKS = 4


def vector_z(objectives: TaskObjectives) -> th.Tensor:
    with th.no_grad():
        return objectives.embedding(objectives.phi()[0])[0]


# ========================================================================= vectorised mu, C_s, w, J^NT == plain loop
STEP = 1e-2


def test_transfer_matrix_matches_plain_loop(small_setup):
    policy, batch, ent_coef, objectives = small_setup
    before, expected = loop_transfer(policy, batch, ent_coef, STEP)
    z = vector_z(objectives)
    th.testing.assert_close(objectives.all_tasks(objectives.theta(), z), before, rtol=1e-9, atol=1e-10)
    matrix = transfer_matrix(objectives, z, STEP)
    assert matrix.shape == (N_TASKS, N_TASKS)
    th.testing.assert_close(matrix, expected, rtol=1e-7, atol=1e-10)
    # Far from the tolerance: the sign of every entry (hence mu) is unambiguous.
    assert expected.abs().min() > 1e-5
    # chunked evaluation over theta^k gives the same matrix (chunks of 3 of the 5 parameter sets: 3 and 2).
    for chunk_size in (1, 3):
        chunked = TaskObjectives(policy, batch, ent_coef, chunk_size=chunk_size)
        th.testing.assert_close(transfer_matrix(chunked, z, STEP), expected, rtol=1e-7, atol=1e-10)


def test_mu_benign_set_and_weights_match_plain_loop(small_setup):
    policy, batch, ent_coef, objectives = small_setup
    _, expected_matrix = loop_transfer(policy, batch, ent_coef, STEP)
    expected_mu = [sum(1 for i in range(N_TASKS) if float(expected_matrix[k, i]) < 0) for k in range(N_TASKS)]
    assert expected_mu == [2, 3, 1, 2]  # the fixture's conflicts: not trivial, with a tie (tasks 0 and 3)

    mu = negative_transfer_measure(transfer_matrix(objectives, vector_z(objectives), STEP))
    assert mu.tolist() == expected_mu

    # Eq. 7 with M = 2: sorted mu = 1, 2, 2, 3, so mu(T_kappa(2)) = 2 and both tasks with mu 2 are benign.
    assert kappa_benign_set(expected_mu, 2) == {0, 2, 3}
    assert th.nonzero(select_benign_tasks(mu, 2)).flatten().tolist() == [0, 2, 3]

    numerators = [math.exp(N_TASKS - v) for v in expected_mu]
    expected_weights = th.tensor([v / sum(numerators) for v in numerators])
    th.testing.assert_close(task_weights(mu), expected_weights, rtol=1e-6, atol=1e-7)


def test_negative_transfer_objective_matches_plain_loop(small_setup):
    """representation_loss with use_vae=False is -J^NT (Eq. 12) over the harmful set C \\ C_s; c_vae is irrelevant."""
    policy, batch, ent_coef, objectives = small_setup
    mu = negative_transfer_measure(transfer_matrix(objectives, vector_z(objectives), STEP))
    harmful = th.nonzero(~select_benign_tasks(mu, 2)).flatten()
    assert harmful.tolist() == [1]  # mu = [2, 3, 1, 2]: C_s = {0, 2, 3}
    expected = loop_nt_objective(policy, batch, ent_coef, harmful.tolist(), STEP)
    encoder, decoder = objectives.phi()
    for c_vae in (0.0, 1.0, 7.5):
        loss = representation_loss(objectives, encoder, decoder, harmful, STEP, c_vae, use_vae=False)
        assert float(loss) == pytest.approx(-expected, rel=1e-9, abs=1e-10)
    # With every task harmful the same function averages over all k.
    all_tasks = th.arange(N_TASKS)
    loss = representation_loss(objectives, encoder, decoder, all_tasks, STEP, 1.0, use_vae=False)
    assert float(loss) == pytest.approx(
        -loop_nt_objective(policy, batch, ent_coef, list(range(N_TASKS)), STEP), rel=1e-9
    )


# =================================================================== dJ^NT/dphi is second order (finite differences)
def _fd_setup():
    """Tanh networks (smooth everywhere) so central differences are accurate."""
    policy = make_te_policy(seed=6, activation_fn=nn.Tanh)
    batch = make_rep_batch(policy, seed=106)
    return policy, batch, TaskObjectives(policy, batch, make_ent_coef(N_TASKS))


FD_STEP_SIZE = 0.5  # a large alpha makes the second-order part of the meta-gradient large
FD_ENTRIES = [
    ("0.weight", 0),
    ("0.weight", 17),
    ("0.bias", 3),
    ("2.weight", 5),
    ("2.bias", 0),
    ("4.weight", 7),
    ("4.bias", 1),
]


def test_representation_gradient_matches_finite_differences_and_is_second_order():
    _, _, objectives = _fd_setup()
    harmful = th.tensor([1, 3])
    _, enc_grads, dec_grads = representation_gradients(
        objectives, harmful, step_size=FD_STEP_SIZE, c_vae=0.3, use_vae=False
    )
    encoder, decoder = objectives.phi()

    def loss(enc):
        return float(representation_loss(objectives, enc, decoder, harmful, FD_STEP_SIZE, 0.3, use_vae=False))

    # First-order variant: the inner gradient grad_theta J_k is computed with z detached (no d g_k / d phi).
    def first_order_loss(enc):
        z = objectives.embedding(enc)[0]
        theta = objectives.theta()
        grads = objectives.gradients(theta, z.detach(), harmful)
        return -negative_transfer_objective(
            objectives.after_virtual_steps(virtual_parameters(theta, grads, FD_STEP_SIZE), z)
        )

    first_order = grad(first_order_loss)(encoder)

    eps = 1e-6
    analytic, numeric, first = [], [], []
    for name, index in FD_ENTRIES:
        plus = {k: v.clone() for k, v in encoder.items()}
        minus = {k: v.clone() for k, v in encoder.items()}
        plus[name].view(-1)[index] += eps
        minus[name].view(-1)[index] -= eps
        numeric.append((loss(plus) - loss(minus)) / (2 * eps))
        analytic.append(float(enc_grads[name].view(-1)[index]))
        first.append(float(first_order[name].view(-1)[index]))
    np.testing.assert_allclose(analytic, numeric, rtol=1e-4, atol=1e-9)
    # The first-order gradient is measurably different: the test would catch a detached inner gradient.
    assert np.abs(np.array(first) - np.array(numeric)).max() > 100 * 1e-4 * np.abs(numeric).max()
    full = th.cat([g.flatten() for g in enc_grads.values()])
    full_first = th.cat([g.flatten() for g in first_order.values()])
    assert (full - full_first).norm() > 0.1 * full.norm()
    # Without the VAE term the decoder gets no gradient; theta is never a variable of J^rep.
    assert all(float(g.abs().max()) == 0.0 for g in dec_grads.values())


@pytest.mark.parametrize("estimator", ["virtual_step", "gradient_dot"])
@pytest.mark.parametrize("harmful", [[1], [1, 3], [0, 1, 2, 3], []])
def test_representation_gradients_match_plain_autograd(small_setup, estimator, harmful):
    """-J^rep and its encoder / decoder gradients against plain autograd (create_graph=True for the inner step), with
    and without the VAE term; alpha = 0.3 makes the second-order part large."""
    policy, batch, ent_coef, objectives = small_setup
    for use_vae, chunk_size in ((False, None), (True, None), (False, 3)):
        kwargs = {"step_size": 0.3, "c_vae": 0.7, "use_vae": use_vae, "estimator": estimator}
        objectives = TaskObjectives(policy, batch, ent_coef, chunk_size=chunk_size)
        loss, enc_grads, dec_grads = representation_gradients(objectives, th.tensor(harmful, dtype=th.long), **kwargs)
        expected_loss, expected_enc, expected_dec = loop_rep_gradients(policy, batch, ent_coef, harmful, **kwargs)
        assert float(loss) == pytest.approx(float(expected_loss), rel=1e-10, abs=1e-12)
        for grads, expected, module in (
            (enc_grads, expected_enc, policy.encoder),
            (dec_grads, expected_dec, policy.decoder),
        ):
            for (name, _), reference in zip(module.named_parameters(), expected, strict=True):
                th.testing.assert_close(grads[name], reference, rtol=1e-8, atol=1e-12)
        if harmful and not use_vae:
            assert float(th.cat([g.flatten() for g in expected_enc]).norm()) > 1e-3  # J^NT does move phi


# ========================================================================== alpha = 0: common random numbers, mu = 0
@pytest.mark.parametrize("double", [True, False])
def test_zero_step_size_gives_zero_mu(double):
    policy = make_te_policy(seed=6, double=double)
    batch = make_rep_batch(policy, seed=106)
    ent_coef = make_ent_coef(N_TASKS, th.float64 if double else th.float32)
    for chunk_size in (None, 1):
        objectives = TaskObjectives(policy, batch, ent_coef, chunk_size=chunk_size)
        matrix = transfer_matrix(objectives, vector_z(objectives), 0.0)
        assert th.equal(matrix, th.zeros_like(matrix))
        assert negative_transfer_measure(matrix).tolist() == [0] * N_TASKS


def test_zero_step_size_in_the_algorithm():
    """With nt_step_size=0 the recorded mu is 0 at every recomputation (float32, z and noise drawn inside)."""
    model = MTSACTE("MlpPolicy", make_mt_env("toy-conflict", seed=0), **small_model_kwargs(nt_step_size=0.0))
    model.learn(160)
    for _ in range(3):
        model.update_representation(16)
        assert model.mu.tolist() == [0] * N_TASKS
        assert np.array_equal(model.transfer_matrix, np.zeros((N_TASKS, N_TASKS)))
        np.testing.assert_allclose(model.task_weights, np.full(N_TASKS, 0.25), rtol=1e-6)


# ======================================================================= gradient_dot == virtual_step to first order
def test_gradient_dot_agrees_with_virtual_step(small_setup):
    _, _, _, objectives = small_setup
    z = vector_z(objectives)
    deviations = []
    for step in (1e-4, 1e-5):
        exact = transfer_matrix(objectives, z, step, "virtual_step")
        linear = transfer_matrix(objectives, z, step, "gradient_dot")
        assert negative_transfer_measure(exact).tolist() == negative_transfer_measure(linear).tolist()
        ratio = exact / linear
        assert float((ratio - 1).abs().max()) < 1e-2
        deviations.append(float((exact - linear).abs().max()))
    # The difference is second order in alpha: 10x smaller alpha, ~100x smaller difference (~10x in ratio).
    assert 50 < deviations[0] / deviations[1] < 200
    linear = transfer_matrix(objectives, z, 1e-4, "gradient_dot")
    th.testing.assert_close(linear, linear.T)  # alpha g_k . g_i is symmetric, positive on the diagonal
    assert (th.diagonal(linear) > 0).all()
    with pytest.raises(ValueError, match="nt_estimator"):
        transfer_matrix(objectives, z, 1e-4, "bogus")


def loop_first_order_nt_objective(policy, batch, ent_coef, harmful: list[int], step_size: float) -> float:
    """J^NT to first order in alpha: mean_i J_i(theta) + alpha * (mean_i g_i) . (mean_{k in harmful} g_k)."""
    n = policy.n_tasks
    z = [loop_embedding(policy, batch, i)[0].detach() for i in range(n)]
    params = list(policy.actor.parameters())
    values, grads = [], []
    for i in range(n):
        value = loop_objective(policy, policy.actor.net, batch, ent_coef, i, z[i])
        values.append(float(value.detach()))
        grads.append(th.cat([g.flatten() for g in th.autograd.grad(value, params)]))
    mean_grad = th.stack(grads).mean(0)
    harmful_grad = th.stack([grads[k] for k in harmful]).mean(0)
    return sum(values) / n + step_size * float(mean_grad @ harmful_grad)


def test_first_order_nt_objective_of_gradient_dot(small_setup):
    """estimator="gradient_dot": J^NT is its first-order expansion (value against a loop), which agrees with the
    exact Eq. 11-12 up to O(alpha^2), and its phi-gradient (through the task gradients) matches finite differences."""
    policy, batch, ent_coef, objectives = small_setup
    encoder, decoder = objectives.phi()
    harmful = th.tensor([1, 3])
    for step in (1e-2, 0.3):
        loss = representation_loss(
            objectives, encoder, decoder, harmful, step, 1.0, use_vae=False, estimator="gradient_dot"
        )
        expected = loop_first_order_nt_objective(policy, batch, ent_coef, [1, 3], step)
        assert float(loss) == pytest.approx(-expected, rel=1e-9, abs=1e-12)
    _, _, fd_objectives = _fd_setup()  # tanh networks: smooth, so the expansion error is a clean alpha^2
    fd_encoder, fd_decoder = fd_objectives.phi()
    gaps = []
    for step in (1e-3, 1e-4):
        exact = representation_loss(fd_objectives, fd_encoder, fd_decoder, harmful, step, 1.0, use_vae=False)
        linear = representation_loss(
            fd_objectives, fd_encoder, fd_decoder, harmful, step, 1.0, use_vae=False, estimator="gradient_dot"
        )
        gaps.append(abs(float(exact - linear)))
    assert 50 < gaps[0] / gaps[1] < 200  # second order in alpha

    kwargs = {"step_size": FD_STEP_SIZE, "c_vae": 0.3, "use_vae": False, "estimator": "gradient_dot"}
    _, enc_grads, dec_grads = representation_gradients(fd_objectives, harmful, **kwargs)

    def loss_of(enc):
        return float(representation_loss(fd_objectives, enc, fd_decoder, harmful, **kwargs))

    eps = 1e-6
    for name, index in FD_ENTRIES:
        plus = {k: v.clone() for k, v in fd_encoder.items()}
        minus = {k: v.clone() for k, v in fd_encoder.items()}
        plus[name].view(-1)[index] += eps
        minus[name].view(-1)[index] -= eps
        numeric = (loss_of(plus) - loss_of(minus)) / (2 * eps)
        assert float(enc_grads[name].view(-1)[index]) == pytest.approx(numeric, rel=1e-4, abs=1e-9)
    assert all(float(g.abs().max()) == 0.0 for g in dec_grads.values())


# ================================================================================= VAE term (Eq. 13), J^rep (Eq. 14)
def test_vae_objective_and_representation_objective(small_setup):
    policy, batch, ent_coef, objectives = small_setup
    encoder, decoder = objectives.phi()
    harmful = th.tensor([1, 3])
    expected_vae = loop_vae_objective(policy, batch)
    vae_value = float(expected_vae.detach())
    c_vae = 0.7
    with_vae = representation_loss(objectives, encoder, decoder, harmful, STEP, c_vae, use_vae=True)
    without_vae = representation_loss(objectives, encoder, decoder, harmful, STEP, c_vae, use_vae=False)
    j_nt = loop_nt_objective(policy, batch, ent_coef, [1, 3], STEP)
    # loss = -J^rep = -(J^NT - c_vae J^VAE)
    assert float(with_vae) == pytest.approx(-(j_nt - c_vae * vae_value), rel=1e-9)
    assert float(with_vae - without_vae) == pytest.approx(c_vae * vae_value, rel=1e-9)
    # An empty harmful set (all mu equal): J^rep is the VAE term alone.
    empty = representation_loss(objectives, encoder, decoder, th.tensor([], dtype=th.long), STEP, c_vae)
    assert float(empty) == pytest.approx(c_vae * vae_value, rel=1e-9)
    # The decoder gradient is c_vae * dJ^VAE/d(decoder); J^NT does not involve the decoder.
    _, _, dec_grads = representation_gradients(objectives, harmful, step_size=STEP, c_vae=c_vae, use_vae=True)
    expected_grads = th.autograd.grad(expected_vae, list(policy.decoder.parameters()))
    for (name, _), expected in zip(policy.decoder.named_parameters(), expected_grads, strict=True):
        th.testing.assert_close(dec_grads[name], c_vae * expected, rtol=1e-9, atol=1e-12)


# ================================================================== one recomputation of the algorithm (Eq. 4-14)
def _float64_reference(model, batch: RepresentationBatch):
    """A float64 copy of the model's networks, the batch and beta, for plain references."""
    batch64 = RepresentationBatch(batch.obs.double(), batch.z_noise.double(), batch.action_noise.double())
    return copy.deepcopy(model.policy).double(), batch64, model.entropy_coefficients.double()


def _assert_gradients_close(model, captured: dict, expected_enc, expected_dec) -> None:
    for module, grads, expected in (
        (model.encoder, captured["enc"], expected_enc),
        (model.decoder, captured["dec"], expected_dec),
    ):
        for (name, _), reference in zip(module.named_parameters(), expected, strict=True):
            th.testing.assert_close(grads[name].double(), reference, rtol=1e-4, atol=1e-7)


@pytest.mark.parametrize("estimator", ["virtual_step", "gradient_dot"])
def test_update_representation_applies_the_equations(toy_env, monkeypatch, estimator):
    """One recomputation on a fixed top-K batch against plain float64 references: the transfer matrix (Eq. 4-5: a
    copied actor stepped by autograd, or alpha g_k . g_i), mu (Eq. 6), C_s (Eq. 7), w (Eq. 8) and the gradients of
    -J^rep applied to the encoder and decoder (Eq. 11-14, second order through the inner step)."""
    step, c_vae = 1e-2, 0.05
    kwargs = small_model_kwargs(rep_gradient_steps=1, c_vae=c_vae, nt_step_size=step, nt_estimator=estimator, seed=1)
    # z noisy (every sign unambiguous), E_phi's mean at PyTorch's scale: the case's conflicts were built on it
    kwargs["policy_kwargs"] = {**kwargs["policy_kwargs"], "z_init_std": None, "z_mean_init_gain": 1.0}
    model = MTSACTE("MlpPolicy", toy_env, **kwargs)
    model.learn(160)
    with th.no_grad():  # larger Q-values, so that the tasks' policy gradients conflict
        model.critic.q_net.layers[-1].weight.mul_(10.0)
    batch = model._representation_batch(16)
    monkeypatch.setattr(model, "_representation_batch", lambda batch_size: batch)
    policy, batch64, beta = _float64_reference(model, batch)
    if estimator == "virtual_step":
        _, matrix = loop_transfer(policy, batch64, beta, step)
    else:
        z = [loop_embedding(policy, batch64, i)[0].detach() for i in range(N_TASKS)]
        task_grads = loop_task_gradients(policy, batch64, beta, z)
        matrix = th.tensor(
            [[step * float(task_grads[k] @ task_grads[i]) for i in range(N_TASKS)] for k in range(N_TASKS)]
        )
    assert float(matrix.abs().min()) > 1e-4  # every sign is unambiguous in float32
    mu = [sum(1 for i in range(N_TASKS) if matrix[k, i] < 0) for k in range(N_TASKS)]
    benign = kappa_benign_set(mu, model.n_select)
    harmful = [k for k in range(N_TASKS) if k not in benign]
    assert 0 < len(harmful) < N_TASKS  # J^NT has terms and C_s is not everything (here mu = [1, 0, 0, 1])
    _, expected_enc, expected_dec = loop_rep_gradients(policy, batch64, beta, harmful, step, c_vae, True, estimator)
    captured = capture_applied_gradients(model, monkeypatch)

    model.update_representation(16)
    np.testing.assert_allclose(model.transfer_matrix, matrix.numpy(), rtol=1e-3, atol=1e-5)
    assert model.mu.tolist() == mu
    assert set(np.flatnonzero(model.selected_tasks).tolist()) == benign
    numerators = [math.exp(N_TASKS - m) for m in mu]
    np.testing.assert_allclose(model.task_weights, [v / sum(numerators) for v in numerators], rtol=1e-6)
    _assert_gradients_close(model, captured, expected_enc, expected_dec)


def test_equal_mu_leaves_only_the_vae_term(toy_env, monkeypatch):
    """alpha = 0: mu is 0 for every task, so C_s is every task, C \\ C_s is empty and the encoder and decoder follow
    the gradient of c_vae * J^VAE alone."""
    c_vae = 0.3
    model = MTSACTE("MlpPolicy", toy_env, **small_model_kwargs(rep_gradient_steps=1, c_vae=c_vae, nt_step_size=0.0))
    model.learn(200)
    batch = model._representation_batch(16)
    monkeypatch.setattr(model, "_representation_batch", lambda batch_size: batch)
    policy, batch64, beta = _float64_reference(model, batch)
    _, expected_enc, expected_dec = loop_rep_gradients(policy, batch64, beta, [], 0.0, c_vae)
    captured = capture_applied_gradients(model, monkeypatch)
    model.update_representation(16)
    assert model.mu.tolist() == [0] * N_TASKS and model.selected_tasks.all()
    _assert_gradients_close(model, captured, expected_enc, expected_dec)
