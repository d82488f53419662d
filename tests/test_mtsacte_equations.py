"""MTSACTE's equations against plain references: the negative-transfer machinery of the representation update
(Eq. 4-14, vectorised functions and one recomputation of the algorithm), the soft-Q target and its clipped loss in
a training step (Eq. 15-16), and how z ~ E_phi is used when acting."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
import torch as th
from conftest import (
    disable_representation_updates,
    kappa_benign_set,
    loop_embedding,
    loop_nt_objective,
    loop_objective,
    loop_q,
    loop_rep_gradients,
    loop_split,
    loop_task_gradients,
    loop_transfer,
    loop_vae_objective,
    make_ent_coef,
    make_rep_batch,
    make_te_policy,
    small_model_kwargs,
)
from stable_baselines3.common.logger import Logger
from torch import nn
from torch.func import grad

import sb3_mtte.mtsac.mtsac as mtsac_module
from sb3_mtte import MTSACTE, make_mt_env
from sb3_mtte.mtsacte.objectives import (
    TaskSelection,
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
def _capture_applied_gradients(model, monkeypatch) -> dict:
    captured: dict = {}
    original_apply = model._apply_gradients

    def apply(enc, dec):
        captured["enc"], captured["dec"] = enc, dec
        return original_apply(enc, dec)

    monkeypatch.setattr(model, "_apply_gradients", apply)
    return captured


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
    captured = _capture_applied_gradients(model, monkeypatch)

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
    captured = _capture_applied_gradients(model, monkeypatch)
    model.update_representation(16)
    assert model.mu.tolist() == [0] * N_TASKS and model.selected_tasks.all()
    _assert_gradients_close(model, captured, expected_enc, expected_dec)


# ====================================================================== soft-Q target (Eq. 15) and its clip (Eq. 16)
def _fill_buffer(model, rows) -> None:
    """Add transitions to the model's buffer, one row per call: (state, next_state, rewards, dones, truncated), the
    states shared by every task and the per-task entries as lists."""
    one_hot = np.eye(N_TASKS, dtype=np.float32)
    actions = np.random.default_rng(0).uniform(-1, 1, size=(len(rows), N_TASKS, 2)).astype(np.float32)
    for row, (state, next_state, rewards, dones, truncated) in enumerate(rows):
        obs = np.concatenate([np.tile(np.float32(state), (N_TASKS, 1)), one_hot], axis=1)
        next_obs = np.concatenate([np.tile(np.float32(next_state), (N_TASKS, 1)), one_hot], axis=1)
        infos = [{"TimeLimit.truncated": bool(t)} for t in truncated]
        model.replay_buffer.add(obs, next_obs, actions[row], np.array(rewards), np.array(dones), infos)


def _capture(monkeypatch, owner, name: str, store: dict, key: str, argument: int | None = None):
    """Wrap ``owner.name`` so that its result (or positional argument ``argument``) is stored under ``key``."""
    original = getattr(owner, name)

    def wrapped(*args, **kwargs):
        result = original(*args, **kwargs)
        store[key] = result if argument is None else args[argument]
        return result

    monkeypatch.setattr(owner, name, wrapped)


def _model_for_a_training_step(toy_env, monkeypatch, **overrides):
    model = MTSACTE("MlpPolicy", toy_env, **small_model_kwargs(**overrides))
    model.set_logger(Logger(folder=None, output_formats=[]))
    disable_representation_updates(model, monkeypatch)
    monkeypatch.setattr(model.ent_coef_optimizer, "step", lambda *args, **kwargs: None)  # beta_i fixed
    return model


def test_soft_q_target_on_a_hand_computed_batch(toy_env, monkeypatch):
    """y = r + gamma (1 - terminal) (min_j Qbar_ij(s', a') - beta_i log pi(a'|s', z')), z' ~ E_phi(.|s', one-hot).

    Controlled networks: E_phi has mean s'[:3] and std 0.5, the actor has mean z'[:2] and std 0.2, every noise draw
    of z is +1 and of a is -0.5, so a' = tanh(s'[:2] + 0.5 - 0.1). Target twins: Qbar_i0 = c0_i + a'_0 and
    Qbar_i1 = c1_i + a'_0. A time-limit truncation is bootstrapped, a termination is not."""
    gamma, beta = 0.9, [0.1, 0.2, 0.4, 0.8]
    twin_0, twin_1 = [1.0, 5.0, 2.0, 7.0], [3.0, 2.0, 6.0, 4.0]
    rewards = [[1.0, 2.0, 3.0, 4.0], [-1.0, -2.0, -3.0, -4.0]]
    dones = [[1, 1, 0, 0], [0, 0, 1, 1]]
    truncated = [[1, 0, 0, 0], [0, 0, 1, 0]]  # row 0: task 0 truncated, task 1 terminal; row 1: tasks 2, 3
    next_states = [[0.1, -0.4, 0.0, 0.0], [-0.4, 0.6, 0.0, 0.0]]
    model = _model_for_a_training_step(toy_env, monkeypatch, gamma=gamma, batch_size=16)
    _fill_buffer(model, [([0.3, 0.3, 0.0, 0.0], next_states[r], rewards[r], dones[r], truncated[r]) for r in range(2)])
    with th.no_grad():
        model.log_ent_coef.copy_(th.log(th.tensor(beta)))
    policy = model.policy
    monkeypatch.setattr(
        policy.encoder, "forward", lambda obs: th.cat([obs[..., :3], th.full_like(obs[..., :3], math.log(0.5))], -1)
    )
    keep_graph = policy.actor.net[0].bias  # the actor loss stays a function of theta (0 times it), as in training
    monkeypatch.setattr(
        policy.actor.net,
        "forward",
        lambda x: th.cat([x[..., 4:6], th.full_like(x[..., 4:6], math.log(0.2))], -1) + 0.0 * keep_graph.sum(),
    )

    def target_twins(obs, actions):
        a0 = actions[..., 0]
        return th.stack([th.tensor(twin_0)[:, None] + a0, th.tensor(twin_1)[:, None] + a0])

    monkeypatch.setattr(policy.critic_target, "forward", target_twins)
    monkeypatch.setattr(th, "randn_like", lambda x, **kwargs: th.full_like(x, 1.0 if x.shape[-1] == 3 else -0.5))
    captured: dict = {}
    _capture(monkeypatch, model.replay_buffer, "sample", captured, "batch")
    _capture(monkeypatch, mtsac_module, "clipped_soft_q_loss", captured, "target", argument=1)
    model.train(1, 16)

    def log_pi(pre_tanh):
        gaussian = -0.5 * 0.5**2 - math.log(0.2) - 0.5 * math.log(2 * math.pi)
        return sum(gaussian - math.log(1 - math.tanh(u) ** 2 + 1e-6) for u in pre_tanh)

    def expected(row, task):
        pre_tanh = [next_states[row][0] + 0.4, next_states[row][1] + 0.4]
        soft_value = min(twin_0[task], twin_1[task]) + math.tanh(pre_tanh[0]) - beta[task] * log_pi(pre_tanh)
        bootstrap = 0.0 if dones[row][task] and not truncated[row][task] else 1.0
        return rewards[row][task] + gamma * bootstrap * soft_value

    sampled = captured["batch"].rewards.view(N_TASKS, -1)
    target = captured["target"]
    for task in range(N_TASKS):
        rows = [0 if float(r) == rewards[0][task] else 1 for r in sampled[task]]
        assert set(rows) == {0, 1}
        for b, row in enumerate(rows):
            assert float(target[task, b]) == pytest.approx(expected(row, task), rel=1e-5, abs=1e-5), (task, row)


def test_q_loss_clip_is_per_sample(toy_env, monkeypatch):
    """Eq. 16 clamps each sample's 1/2 delta^2 to [0, V_clip] before the mean: with V_clip between the per-sample
    losses, the critics' gradient is that of the unclipped samples alone, which differs from clipping the batch mean.

    gamma = 0 makes the target the reward, so the reference is a plain loop over samples with the critic members."""
    clip = 10.0
    rewards = [[0.0, 0.0, 0.5, -0.5], [0.5, 1.0, -1.0, 0.0], [6.0, -5.0, 5.0, 7.0], [-7.0, 9.0, 0.0, -5.0]]
    model = _model_for_a_training_step(toy_env, monkeypatch, gamma=0.0, q_loss_clip=clip)
    _fill_buffer(
        model, [([0.1 * r, -0.2, 0.3, 0.0], [0.0] * 4, rewards[r], [0] * N_TASKS, [0] * N_TASKS) for r in range(4)]
    )
    reference = copy.deepcopy(model.policy)
    captured: dict = {}
    _capture(monkeypatch, model.replay_buffer, "sample", captured, "batch")
    original_step = model.critic.optimizer.step

    def step(*args, **kwargs):
        captured["grads"] = [p.grad.detach().clone() for p in model.critic.parameters()]
        return original_step(*args, **kwargs)

    monkeypatch.setattr(model.critic.optimizer, "step", step)
    batch_size = 8
    model.train(1, batch_size)

    members = reference.n_critics
    data = captured["batch"]  # task-major (N, L, ...): flattened to rows for the loop
    observations, actions, rewards = (x.flatten(0, 1) for x in (data.observations, data.actions, data.rewards))
    losses = []  # per task and twin: the L per-sample 1/2 (Q(s, a) - r)^2
    for task in range(N_TASKS):
        rows = range(task * batch_size, (task + 1) * batch_size)
        inputs = [th.cat([observations[r, :4], actions[r]]) for r in rows]
        for twin in range(members):
            q = th.stack([loop_q(reference, task * members + twin, x) for x in inputs])
            losses.append(0.5 * (q - rewards[rows.start : rows.stop]) ** 2)
    values = th.cat(losses).detach()
    assert (values - clip).abs().min() > 0.5
    assert (values > clip).sum() >= 8 and (values < clip).sum() >= 8  # both regimes
    params = list(reference.critic.parameters())
    per_sample = sum((sample * (sample.detach() <= clip)).sum() / batch_size for sample in losses)
    expected = th.autograd.grad(per_sample, params, retain_graph=True)
    for applied, reference_grad in zip(captured["grads"], expected, strict=True):
        th.testing.assert_close(applied, reference_grad, rtol=1e-4, atol=1e-6)
    # Clipping the batch mean instead gives another gradient.
    batch_mean = sum(sample.mean() * (sample.mean().detach() <= clip) for sample in losses)
    flat = th.cat([g.flatten() for g in expected])
    other = th.cat([g.flatten() for g in th.autograd.grad(batch_mean, params)])
    assert (other - flat).norm() > 0.1 * flat.norm()


# =========================================================================================== acting with z ~ E_phi
def test_stochastic_predict_samples_z_from_the_encoder(toy_env, monkeypatch):
    """predict(deterministic=False) feeds the actor z = mean + std * eps with the encoder's mean and std: over many
    copies of the same observations the z it uses has that mean and std, and two calls differ."""
    model = MTSACTE("MlpPolicy", toy_env, **small_model_kwargs())
    policy = model.policy
    with th.no_grad():  # an encoder std far from 1 and different per dimension
        policy.encoder[-1].bias[policy.z_dim :] = th.tensor([-1.0, 0.0, 0.5])
    fed: list[th.Tensor] = []
    policy.actor.net.register_forward_pre_hook(lambda module, args: fed.append(args[0][:, policy.state_dim :].detach()))
    obs = np.repeat(toy_env.reset(), 1000, axis=0)  # task-major: 1000 copies of each task's start observation
    first = model.predict(obs, deterministic=False)[0]
    second = model.predict(obs, deterministic=False)[0]
    assert not np.allclose(first, second)
    with th.no_grad():
        mean, log_std = loop_split(policy.encoder(th.as_tensor(obs)))
    assert len(fed) == 2  # one actor pass per predict
    for z in fed:
        eps = (z - mean) / log_std.exp()
        for task in range(N_TASKS):
            rows = eps[task * 1000 : (task + 1) * 1000]
            assert rows.mean(0).abs().max() < 0.15
            th.testing.assert_close(rows.std(0), th.ones(policy.z_dim), rtol=0.1, atol=0.0)


def test_deterministic_predict_uses_the_mean_z_and_action(toy_env):
    model = MTSACTE("MlpPolicy", toy_env, **small_model_kwargs())
    model.learn(200)
    obs = toy_env.reset()
    policy = model.policy
    with th.no_grad():
        x = th.as_tensor(obs)
        mean_z, _ = loop_split(policy.encoder(x))
        mean_a, _ = loop_split(policy.actor.net(th.cat([x[:, : policy.state_dim], mean_z], dim=1)))
    actions = model.predict(obs, deterministic=True)[0]
    np.testing.assert_allclose(actions, th.tanh(mean_a).numpy(), rtol=1e-6, atol=1e-7)
    np.testing.assert_array_equal(model.predict(obs, deterministic=True)[0], actions)


def test_collected_actions_use_a_sampled_z(toy_env, monkeypatch):
    """While collecting experience after learning_starts, the acting z is a fresh draw of E_phi(.|s, one-hot): the
    standardised noise (z - mean) / std of every acting step is standard normal over the run."""
    model = MTSACTE("MlpPolicy", toy_env, **small_model_kwargs(learning_starts=40))
    policy, acting, pairs = model.policy, {"on": False}, []
    original_sample_action = model._sample_action

    def sample_action(*args, **kwargs):
        acting["on"] = True
        try:
            return original_sample_action(*args, **kwargs)
        finally:
            acting["on"] = False

    def record_encoder(module, args, output):
        if acting["on"]:
            pairs.append([output.detach()])

    def record_actor(module, args):
        if acting["on"]:
            pairs[-1].append(args[0][:, policy.state_dim :].detach())

    monkeypatch.setattr(model, "_sample_action", sample_action)
    policy.encoder.register_forward_hook(record_encoder)
    policy.actor.net.register_forward_pre_hook(record_actor)
    model.learn(600)
    assert len(pairs) == 600 // N_TASKS - 40 // N_TASKS  # one policy action per vector step after learning_starts
    eps = []
    for output, z in pairs:
        mean, log_std = loop_split(output)
        eps.append((z - mean) / log_std.exp())
    eps = th.cat(eps)
    assert float(eps.mean().abs()) < 0.1
    assert 0.9 < float(eps.std()) < 1.1


def test_no_step_when_j_rep_has_no_term(toy_env, monkeypatch):
    """alpha = 0 makes every mu 0, so C \\ C_s is empty; without the VAE term J^rep has no term: phi, the decoder
    and the Adam state stay exactly as they were (Adam with momentum would move phi on zero gradients)."""
    model = MTSACTE("MlpPolicy", toy_env, **small_model_kwargs(rep_gradient_steps=3, nt_step_size=0.0, use_vae=False))
    model.learn(200)
    before = {k: v.clone() for k, v in [*model.encoder.state_dict().items(), *model.decoder.state_dict().items()]}
    steps = []
    monkeypatch.setattr(model.policy.rep_optimizer, "step", lambda *a, **k: steps.append(1))
    model.update_representation(8)
    assert model.selected_tasks.all() and not steps
    after = dict([*model.encoder.state_dict().items(), *model.decoder.state_dict().items()])
    for name, value in before.items():
        th.testing.assert_close(after[name], value, rtol=0, atol=0)


@pytest.mark.parametrize("use_vae, harmful", [(True, []), (False, [3])])
def test_a_step_whenever_j_rep_has_a_term(toy_env, monkeypatch, use_vae, harmful):
    """With the VAE term (C \\ C_s empty), or with a task outside C_s (no VAE term), every J^rep update steps."""
    model = MTSACTE("MlpPolicy", toy_env, **small_model_kwargs(rep_gradient_steps=3, use_vae=use_vae))
    model.learn(200)
    selected = th.tensor([task not in harmful for task in range(N_TASKS)])
    selection = TaskSelection(
        th.zeros(N_TASKS, N_TASKS), th.zeros(N_TASKS, dtype=th.long), selected, th.full((N_TASKS,), 1.0 / N_TASKS)
    )
    monkeypatch.setattr(model, "_select", lambda transfer, statistics: selection)
    steps = []
    monkeypatch.setattr(model.policy.rep_optimizer, "step", lambda *a, **k: steps.append(1))
    model.update_representation(8)
    assert len(steps) == 3


@pytest.mark.parametrize("estimator", ["virtual_step", "gradient_dot"])
@pytest.mark.parametrize("step_size", [1e-2, 0.0])
def test_the_encoder_learns_only_through_the_virtual_step(toy_env, monkeypatch, estimator, step_size):
    """With the actor blind to z at theta (its z-input weights zero) and no VAE term, mean_i J_i(theta, phi) does not
    depend on phi: phi can learn only because J^NT evaluates the tasks at theta^k = theta + alpha grad J_k (Eq. 11),
    whose z-input weights are not zero. With alpha = 0, J^NT is mean_i J_i(theta, phi) and phi's gradient is zero."""
    kwargs = small_model_kwargs(rep_gradient_steps=1, use_vae=False, nt_step_size=step_size, nt_estimator=estimator)
    model = MTSACTE("MlpPolicy", toy_env, **kwargs)
    model.learn(200)
    with th.no_grad():
        model.actor.net[0].weight[:, model.policy.state_dim :] = 0.0
    selection = TaskSelection(
        th.zeros(N_TASKS, N_TASKS),
        th.zeros(N_TASKS, dtype=th.long),
        th.tensor([True, True, True, False]),
        th.full((N_TASKS,), 1.0 / N_TASKS),
    )
    monkeypatch.setattr(model, "_select", lambda transfer, statistics: selection)
    captured = _capture_applied_gradients(model, monkeypatch)
    model.update_representation(16)
    gradients = [g.flatten() for g in captured["enc"].values() if g is not None]
    gradient_norm = th.cat(gradients).norm().item() if gradients else 0.0
    if step_size > 0:
        assert gradient_norm > 1e-6
    else:
        assert gradient_norm == 0.0


def test_initial_std_of_the_embedding(toy_env):
    """z_init_std sets E_phi's standard deviation at initialisation (every state and task), leaving its mean."""
    default = MTSACTE("MlpPolicy", toy_env, **small_model_kwargs())
    small = MTSACTE(
        "MlpPolicy", toy_env, **small_model_kwargs(policy_kwargs={"net_arch": [16, 16], "z_dim": 3, "z_init_std": 0.05})
    )
    obs = th.as_tensor(toy_env.reset())
    with th.no_grad():
        mean_default, log_std_default = loop_split(default.policy.encoder(obs))
        mean_small, log_std_small = loop_split(small.policy.encoder(obs))
    th.testing.assert_close(mean_small, mean_default)
    weights_part = log_std_default - default.policy.encoder[-1].bias[3:]
    th.testing.assert_close(log_std_small, weights_part + math.log(0.05))
    with pytest.raises(ValueError, match="z_init_std"):
        MTSACTE("MlpPolicy", toy_env, **small_model_kwargs(policy_kwargs={"z_init_std": 0.0}))


def test_mean_gain_of_the_embedding(toy_env):
    """z_mean_init_gain multiplies E_phi's initial mean (every state and task) and leaves its log-std; 50 by default
    (the README's one line gets the setting chosen on DEV6)."""
    assert MTSACTE("MlpPolicy", toy_env, **small_model_kwargs()).policy.z_mean_init_gain == 50.0
    kwargs = {"net_arch": [16, 16], "z_dim": 3}
    plain = MTSACTE("MlpPolicy", toy_env, **small_model_kwargs(policy_kwargs={**kwargs, "z_mean_init_gain": 1.0}))
    scaled = MTSACTE("MlpPolicy", toy_env, **small_model_kwargs(policy_kwargs={**kwargs, "z_mean_init_gain": 7.0}))
    obs = th.as_tensor(toy_env.reset())
    with th.no_grad():
        mean_plain, log_std_plain = loop_split(plain.policy.encoder(obs))
        mean_scaled, log_std_scaled = loop_split(scaled.policy.encoder(obs))
    th.testing.assert_close(mean_scaled, 7.0 * mean_plain)
    th.testing.assert_close(log_std_scaled, log_std_plain)
    with pytest.raises(ValueError, match="z_mean_init_gain"):
        MTSACTE("MlpPolicy", toy_env, **small_model_kwargs(policy_kwargs={"z_mean_init_gain": 0.0}))


def test_deterministic_predict_with_a_sampled_z(toy_env):
    """deterministic_z="sample": deterministic predict feeds the actor a sample of E_phi (as in training) and takes
    the mean action: over many copies of one observation the actions vary, and their z has E_phi's std."""
    kwargs = small_model_kwargs(policy_kwargs={"net_arch": [16, 16], "z_dim": 3, "deterministic_z": "sample"})
    model = MTSACTE("MlpPolicy", toy_env, **kwargs)
    policy = model.policy
    fed: list[th.Tensor] = []
    policy.actor.net.register_forward_pre_hook(lambda module, args: fed.append(args[0][:, policy.state_dim :].detach()))
    obs = np.repeat(toy_env.reset()[:1], 2000, axis=0)
    actions = model.predict(obs, deterministic=True)[0]
    assert actions.std(axis=0).min() > 0
    with th.no_grad():
        mean, log_std = loop_split(policy.encoder(th.as_tensor(obs[:1])))
    eps = (fed[-1] - mean) / log_std.exp()
    th.testing.assert_close(eps.std(0), th.ones(policy.z_dim, dtype=eps.dtype), rtol=0.1, atol=0.0)
    with pytest.raises(ValueError, match="deterministic_z"):
        MTSACTE("MlpPolicy", toy_env, **small_model_kwargs(policy_kwargs={"deterministic_z": "mode"}))
