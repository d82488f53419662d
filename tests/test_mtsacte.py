"""Tests of MTSACTE (multi-task SAC with a task embedding network): the negative-transfer machinery against plain
loop references (Eq. 4-12), the second-order meta-gradient, the VAE term (Eq. 13-14), the clipped Q loss (Eq. 16),
the Algorithm-1 schedule, top-K replay, save/load/resume, input validation, reproducibility and learning."""

from __future__ import annotations

import copy
import math
import time

import numpy as np
import pytest
import torch as th
from conftest import (
    EpisodeEnv,
    all_parameters,
    assert_state_equal,
    episode_return,
    make_ent_coef,
    make_episode_env,
    make_rep_batch,
    make_te_policy,
    small_model_kwargs,
)
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.vec_env import DummyVecEnv
from torch import nn
from torch.func import grad

import sb3_mtte.mtsac.mtsac as mtsac_module
import sb3_mtte.mtsacte.mtsacte as mtsacte_module
from sb3_mtte import MTSACTE, make_mt_env
from sb3_mtte.common.losses import clipped_soft_q_loss
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


# ================================================================================ plain-loop reference
def _split(out: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
    mean, log_std = out.chunk(2, dim=-1)
    return mean, log_std.clamp(-20.0, 2.0)


def loop_embedding(policy, batch: RepresentationBatch, i: int) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
    """z = mean + std * z_noise of task i's slice, from a plain call of the encoder."""
    mean, log_std = _split(policy.encoder(batch.obs[i]))
    return mean + log_std.exp() * batch.z_noise[i], mean, log_std


def loop_q(policy, member: int, x: th.Tensor) -> th.Tensor:
    """Critic ensemble member ``member`` applied to ``x`` with its own weights, layer by layer."""
    layers = policy.critic.q_net.layers
    for index, layer in enumerate(layers):
        x = x @ layer.weight[member] + layer.bias[member, 0]
        if index < len(layers) - 1:
            x = policy.critic.q_net.activation(x)
    return x.squeeze(-1)


def loop_objective(policy, actor: nn.Module, batch: RepresentationBatch, ent_coef: th.Tensor, i: int, z: th.Tensor):
    """J_SAC(theta, phi, T_i) = -mean(beta_i log pi(a|s,z) - min_j Q_ij(s, a)) on task i's slice, a = tanh(m + s*eps)."""
    state = batch.obs[i][:, : policy.state_dim]
    mean, log_std = _split(actor(th.cat([state, z], dim=-1)))
    noise = batch.action_noise[i]
    pre_tanh = mean + log_std.exp() * noise
    action = th.tanh(pre_tanh)
    gaussian = th.distributions.Normal(mean, log_std.exp()).log_prob(pre_tanh)
    log_prob = (gaussian - th.log(1.0 - action**2 + 1e-6)).sum(dim=-1)
    q_values = [
        loop_q(policy, i * policy.n_critics + j, th.cat([state, action], dim=-1)) for j in range(policy.n_critics)
    ]
    min_q = th.stack(q_values).min(dim=0).values
    return -(ent_coef[i] * log_prob - min_q).mean()


def stepped_actor(policy, batch, ent_coef, k: int, z: list[th.Tensor], step_size: float) -> nn.Module:
    """A copy of the actor moved to theta^k = theta + alpha * grad_theta J_k (Eq. 4)."""
    params = list(policy.actor.parameters())
    grads = th.autograd.grad(loop_objective(policy, policy.actor, batch, ent_coef, k, z[k]), params)
    actor_k = copy.deepcopy(policy.actor)
    with th.no_grad():
        for param, g in zip(actor_k.parameters(), grads):
            param.add_(step_size * g)
    return actor_k


def loop_transfer(policy, batch, ent_coef, step_size: float) -> tuple[th.Tensor, th.Tensor]:
    """J_i(theta) and the N x N matrix [k, i] = J_i(theta^k) - J_i(theta), with two plain loops."""
    n = policy.n_tasks
    z = [loop_embedding(policy, batch, i)[0].detach() for i in range(n)]
    before = th.stack([loop_objective(policy, policy.actor, batch, ent_coef, i, z[i]) for i in range(n)]).detach()
    matrix = th.zeros(n, n, dtype=before.dtype)
    for k in range(n):
        actor_k = stepped_actor(policy, batch, ent_coef, k, z, step_size)
        for i in range(n):
            matrix[k, i] = loop_objective(policy, actor_k, batch, ent_coef, i, z[i]).detach() - before[i]
    return before, matrix


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
    # chunked evaluation over theta^k gives the same matrix.
    chunked = TaskObjectives(policy, batch, ent_coef, chunk_size=1)
    th.testing.assert_close(transfer_matrix(chunked, z, STEP), expected, rtol=1e-7, atol=1e-10)


def test_mu_benign_set_and_weights_match_plain_loop(small_setup):
    policy, batch, ent_coef, objectives = small_setup
    _, expected_matrix = loop_transfer(policy, batch, ent_coef, STEP)
    expected_mu = [sum(1 for i in range(N_TASKS) if float(expected_matrix[k, i]) < 0) for k in range(N_TASKS)]
    assert expected_mu == [2, 3, 1, 2]  # the fixture's conflicts: not trivial, with a tie (tasks 0 and 3)

    mu = negative_transfer_measure(transfer_matrix(objectives, vector_z(objectives), STEP))
    assert mu.tolist() == expected_mu

    m = 2
    expected_selected = sorted(range(N_TASKS), key=lambda k: (expected_mu[k], k))[:m]  # {2, 0}: tie 0/3 -> 0
    assert expected_selected == [2, 0]
    assert th.nonzero(select_benign_tasks(mu, m)).flatten().tolist() == sorted(expected_selected)

    numerators = [math.exp(N_TASKS - v) for v in expected_mu]
    expected_weights = th.tensor([v / sum(numerators) for v in numerators])
    th.testing.assert_close(task_weights(mu), expected_weights.to(task_weights(mu).dtype), rtol=1e-6, atol=1e-7)


def test_negative_transfer_objective_matches_plain_loop(small_setup):
    """representation_loss with use_vae=False is -J^NT (Eq. 12) over the harmful set C \\ C_s; c_vae is irrelevant."""
    policy, batch, ent_coef, objectives = small_setup
    mu = negative_transfer_measure(transfer_matrix(objectives, vector_z(objectives), STEP))
    harmful = th.nonzero(~select_benign_tasks(mu, 2)).flatten()
    assert harmful.tolist() == [1, 3]
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
        value = loop_objective(policy, policy.actor, batch, ent_coef, i, z[i])
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


# ============================================================ the conflicting task of the toy env has the largest mu
def test_conflicting_task_has_largest_mu_and_smallest_weight():
    """toy-conflict: tasks 0..2 have goals at -30, 0, +30 degrees, task 3 at 180 degrees, all 0.7 from the start.

    Once the critics reflect the rewards, grad_theta J_k at start states pushes the mean action towards goal k, so
    (first order) J_i(theta^k) - J_i(theta) ~ alpha g_i . g_k has the sign of the cosine between the goal directions:
    positive between agreeing tasks (cos 30, cos 60 > 0) and negative between the conflicting task and each agreeing
    one (-cos 30, -1, -cos 30). Hence mu(agree) = 1 (only the conflicting task is harmed) and mu(conflict) = 3.

    The actor is kept at its initialisation while the critics learn (its optimizer step is disabled) and beta is a
    small constant, so that the policy gradient is driven by the critics rather than by the entropy term or by an
    actor that already moves along +x (then the agreeing tasks conflict with each other in y).
    """
    env = make_mt_env("toy-conflict", seed=0)
    model = MTSACTE(
        "MlpPolicy",
        env,
        learning_starts=400,
        batch_size=32,
        buffer_size=20_000,
        learning_rate=1e-3,
        ent_coef=0.01,
        iteration_length=50,
        rep_gradient_steps=1,
        top_k=5,
        policy_kwargs={"net_arch": [32, 32]},
        seed=0,
        device="cpu",
    )
    model.actor.optimizer.step = lambda *args, **kwargs: None
    model.learn(2000)

    gen = th.Generator().manual_seed(0)
    n, batch_size = N_TASKS, 32
    mus, weights, matrices = [], [], []
    for _ in range(10):  # start states (origin +- 0.05, zero velocity) of every task, fresh noise each time
        position = (th.rand(n, batch_size, 2, generator=gen) - 0.5) * 0.1
        obs = th.cat([position, th.zeros(n, batch_size, 2), th.eye(n)[:, None].expand(n, batch_size, n)], dim=-1)
        batch = RepresentationBatch(
            obs, th.randn(n, batch_size, model.policy.z_dim, generator=gen), th.randn(n, batch_size, 2, generator=gen)
        )
        objectives = TaskObjectives(model.policy, batch, model.entropy_coefficients, model._chunk_size())
        matrix = transfer_matrix(objectives, vector_z(objectives), model.nt_step_size)
        matrices.append(matrix)
        mus.append(negative_transfer_measure(matrix).double())
        weights.append(task_weights(mus[-1]))
    mean_mu = th.stack(mus).mean(0)
    mean_weights = th.stack(weights).mean(0)
    conflict = n - 1
    for agree in range(n - 1):
        assert mean_mu[conflict] > mean_mu[agree]
        assert mean_weights[conflict] < mean_weights[agree]
    assert int(th.argmin(task_weights(mean_mu))) == conflict
    # The geometric prediction itself, on the averaged transfer matrix.
    assert negative_transfer_measure(th.stack(matrices).mean(0)).tolist() == [1, 1, 1, 3]


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
    # The decoder gradient is c_vae * dJ^VAE/d(decoder); J^NT does not involve the decoder.
    _, _, dec_grads = representation_gradients(objectives, harmful, step_size=STEP, c_vae=c_vae, use_vae=True)
    expected_grads = th.autograd.grad(expected_vae, list(policy.decoder.parameters()))
    for (name, _), expected in zip(policy.decoder.named_parameters(), expected_grads):
        th.testing.assert_close(dec_grads[name], c_vae * expected, rtol=1e-9, atol=1e-12)


# ======================================================================================= the algorithm (Algorithm 1)
@pytest.fixture
def toy_env():
    env = make_mt_env("toy-conflict", seed=0)
    yield env
    env.close()


def test_initial_negative_transfer_state(toy_env):
    model = MTSACTE("MlpPolicy", toy_env, **small_model_kwargs())
    assert model.n_select == N_TASKS // 2
    assert model.mu.tolist() == [0] * N_TASKS
    np.testing.assert_allclose(model.task_weights, np.full(N_TASKS, 1 / N_TASKS))
    th.testing.assert_close(model.task_weights_for_policy(), th.full((N_TASKS,), 1 / N_TASKS))


def test_attributes_after_recomputation(toy_env):
    model = MTSACTE("MlpPolicy", toy_env, **small_model_kwargs(n_select=3))
    model.learn(200)
    for _ in range(3):
        model.update_representation(16)
        assert model.mu.shape == (N_TASKS,) and np.issubdtype(model.mu.dtype, np.integer)
        assert ((model.mu >= 0) & (model.mu <= N_TASKS)).all()
        assert model.selected_tasks.shape == (N_TASKS,) and model.selected_tasks.dtype == np.bool_
        assert int(model.selected_tasks.sum()) == 3
        expected_selected = np.zeros(N_TASKS, dtype=bool)
        expected_selected[np.argsort(model.mu, kind="stable")[:3]] = True
        assert np.array_equal(model.selected_tasks, expected_selected)
        assert model.task_weights.shape == (N_TASKS,)
        assert model.task_weights.sum() == pytest.approx(1.0, abs=1e-6)
        eq8 = np.exp(N_TASKS - model.mu) / np.exp(N_TASKS - model.mu).sum()
        np.testing.assert_allclose(model.task_weights, eq8, rtol=1e-6)
        assert model.transfer_matrix.shape == (N_TASKS, N_TASKS)
        assert np.array_equal(model.mu, (model.transfer_matrix < 0).sum(axis=1))
        th.testing.assert_close(
            model.task_weights_for_policy(), th.as_tensor(model.task_weights, dtype=th.float32), rtol=1e-6, atol=1e-7
        )


def test_representation_schedule(toy_env, monkeypatch):
    """J^rep updates at the first train call, then every iteration_length vector steps, rep_gradient_steps each;
    every one of them recomputes mu on a top-K batch; the last w holds for the whole iteration."""
    learning_starts, horizon, rep_steps, total = 40, 7, 3, 4 * 60
    model = MTSACTE(
        "MlpPolicy",
        toy_env,
        **small_model_kwargs(learning_starts=learning_starts, iteration_length=horizon, rep_gradient_steps=rep_steps),
    )
    calls, train_weights, counts = [], [], {"transfer": 0, "apply": 0, "top_k": 0, "sample": 0}
    original_update = model.update_representation

    def update_representation(batch_size):
        original_update(batch_size)
        calls.append((model.num_timesteps // N_TASKS, model.task_weights.copy()))

    original_weights = model.task_weights_for_policy

    def task_weights_for_policy():
        weights = original_weights()
        train_weights.append((model.num_timesteps // N_TASKS, weights.clone()))
        return weights

    original_transfer = mtsacte_module.transfer_matrix

    def counting_transfer(*args, **kwargs):
        counts["transfer"] += 1
        return original_transfer(*args, **kwargs)

    original_apply = model._apply_gradients

    def counting_apply(*args):
        counts["apply"] += 1
        return original_apply(*args)

    monkeypatch.setattr(model, "update_representation", update_representation)
    monkeypatch.setattr(model, "task_weights_for_policy", task_weights_for_policy)
    monkeypatch.setattr(model, "_apply_gradients", counting_apply)
    monkeypatch.setattr(mtsacte_module, "transfer_matrix", counting_transfer)
    model.learn(total)
    buffer = model.replay_buffer
    original_top_k, original_sample = buffer.sample_top_k, buffer.sample

    first_train = learning_starts // N_TASKS + 1  # train() runs once num_timesteps > learning_starts
    last_step = total // N_TASKS
    expected_steps = list(range(first_train, last_step + 1, horizon))
    assert [step for step, _ in calls] == expected_steps == [11, 18, 25, 32, 39, 46, 53, 60]
    assert counts["apply"] == counts["transfer"] == len(expected_steps) * rep_steps
    assert model._n_updates == last_step - first_train + 1  # one SAC update per vector step
    # Every policy update uses the weights of the latest recomputation.
    assert len(train_weights) == model._n_updates
    for step, weights in train_weights:
        latest = [w for s, w in calls if s <= step][-1]
        th.testing.assert_close(weights, th.as_tensor(latest, dtype=th.float32))
    rep_params = list(model.policy.rep_optimizer.state.values())
    assert all(int(state["step"]) == len(expected_steps) * rep_steps for state in rep_params)

    # Representation batches come from the top-K store (from the main buffer with use_topk=False).
    def count(name, fn):
        def wrapped(*args, **kwargs):
            counts[name] += 1
            return fn(*args, **kwargs)

        return wrapped

    monkeypatch.setattr(buffer, "sample_top_k", count("top_k", original_top_k))
    monkeypatch.setattr(buffer, "sample", count("sample", original_sample))
    original_update(8)
    assert counts["top_k"] == rep_steps and counts["sample"] == 0
    model.use_topk = False
    original_update(8)
    assert counts["top_k"] == rep_steps and counts["sample"] == rep_steps


def test_schedule_restarts_with_a_new_learn_call(toy_env, monkeypatch):
    model = MTSACTE("MlpPolicy", toy_env, **small_model_kwargs(learning_starts=40, iteration_length=7))
    calls = []
    original_update = model.update_representation

    def update_representation(batch_size):
        calls.append(model.num_timesteps // N_TASKS)
        original_update(batch_size)

    monkeypatch.setattr(model, "update_representation", update_representation)
    model.learn(240)
    first = list(calls)
    calls.clear()
    model.learn(240)  # reset_num_timesteps=True: a new run, counted from 0 again
    assert calls == first


@pytest.mark.parametrize("estimator", ["virtual_step", "gradient_dot"])
def test_update_representation_applies_the_equations(toy_env, monkeypatch, estimator):
    """One recomputation = transfer matrix on the top-K batch, mu, C_s (M smallest), w (Eq. 8), and a J^rep step with
    the gradients of representation_gradients over the harmful set C \\ C_s (nt_step_size, c_vae, use_vae and the
    estimator of the model)."""
    kwargs = small_model_kwargs(rep_gradient_steps=1, c_vae=0.5, nt_step_size=1e-2, nt_estimator=estimator)
    model = MTSACTE("MlpPolicy", toy_env, **kwargs)
    model.learn(200)
    batch = model._representation_batch(16)
    monkeypatch.setattr(model, "_representation_batch", lambda batch_size: batch)
    objectives = TaskObjectives(model.policy, batch, model.entropy_coefficients, model._chunk_size())
    expected_matrix = transfer_matrix(objectives, vector_z(objectives), 1e-2, estimator)
    mu = negative_transfer_measure(expected_matrix)
    selected = select_benign_tasks(mu, model.n_select)
    _, enc_grads, dec_grads = representation_gradients(
        objectives, th.nonzero(~selected).flatten(), step_size=1e-2, c_vae=0.5, use_vae=True, estimator=estimator
    )
    captured = {}
    original_apply = model._apply_gradients

    def apply(enc, dec):
        captured["enc"], captured["dec"] = enc, dec
        return original_apply(enc, dec)

    monkeypatch.setattr(model, "_apply_gradients", apply)
    model.update_representation(16)
    np.testing.assert_allclose(model.transfer_matrix, expected_matrix.double().numpy(), rtol=1e-6, atol=1e-9)
    assert model.mu.tolist() == mu.tolist()
    assert model.selected_tasks.tolist() == selected.tolist()
    np.testing.assert_allclose(model.task_weights, task_weights(mu).numpy(), rtol=1e-6)
    assert_state_equal(captured["enc"], enc_grads, "encoder gradients")
    assert_state_equal(captured["dec"], dec_grads, "decoder gradients")


def _no_rep_update(model, monkeypatch):
    """The next train() calls must not run a representation update."""
    model.iteration_length = 10**9

    def fail(*args, **kwargs):
        raise AssertionError("unexpected representation update")

    monkeypatch.setattr(model, "update_representation", fail)


def test_actor_loss_is_weighted_by_task_weights(toy_env, monkeypatch):
    """With w = e_t (one-hot) the actor's gradient is exactly the gradient of task t's policy loss."""
    model = MTSACTE("MlpPolicy", toy_env, **small_model_kwargs())
    model.learn(200)
    _no_rep_update(model, monkeypatch)
    target = 2
    one_hot = np.zeros(N_TASKS)
    one_hot[target] = 1.0
    model.task_weights = one_hot
    params = list(model.actor.parameters())
    captured: dict[str, list] = {}
    original_loss = mtsac_module.per_task_actor_loss

    def per_task_actor_loss(log_prob, min_q, ent_coef):
        losses = original_loss(log_prob, min_q, ent_coef)
        captured["per_task"] = [th.autograd.grad(losses[i], params, retain_graph=True) for i in range(N_TASKS)]
        return losses

    original_step = model.actor.optimizer.step

    def step(*args, **kwargs):
        captured["applied"] = [p.grad.detach().clone() for p in params]
        return original_step(*args, **kwargs)

    monkeypatch.setattr(mtsac_module, "per_task_actor_loss", per_task_actor_loss)
    monkeypatch.setattr(model.actor.optimizer, "step", step)
    before = [p.detach().clone() for p in params]
    model.train(1, 8)
    for applied, expected in zip(captured["applied"], captured["per_task"][target]):
        th.testing.assert_close(applied, expected, rtol=1e-5, atol=1e-7)
    # The other tasks do have non-zero gradients (they are excluded by the weights, not by accident).
    for task in range(N_TASKS):
        if task != target:
            assert max(float(g.abs().max()) for g in captured["per_task"][task]) > 1e-6
    assert any(not th.equal(b, p) for b, p in zip(before, params))


def test_policy_loss_does_not_train_the_encoder(toy_env, monkeypatch):
    """z is detached from phi in the policy and critic losses: without a J^rep step the encoder and decoder are
    unchanged and get no gradient, while the actor and critics move (Algorithm 1: phi is trained by J^rep only)."""
    model = MTSACTE("MlpPolicy", toy_env, **small_model_kwargs())
    model.learn(200)
    _no_rep_update(model, monkeypatch)
    modules = {"encoder": model.encoder, "decoder": model.decoder, "actor": model.actor, "critic": model.critic}
    before = {name: copy.deepcopy(module.state_dict()) for name, module in modules.items()}
    rep_state = copy.deepcopy(model.policy.rep_optimizer.state_dict())
    for p in [*model.encoder.parameters(), *model.decoder.parameters()]:
        p.grad = None
    model.train(3, 8)
    for name in ("encoder", "decoder"):
        assert_state_equal(modules[name].state_dict(), before[name], name)
    assert all(p.grad is None for p in [*model.encoder.parameters(), *model.decoder.parameters()])
    assert_state_equal(model.policy.rep_optimizer.state_dict(), rep_state, "rep_optimizer")
    for name in ("actor", "critic"):
        assert any(not th.equal(v, before[name][k]) for k, v in modules[name].state_dict().items()), name


def test_representation_update_trains_only_phi(toy_env):
    """A J^rep step moves the encoder and decoder, never the actor, critics or beta (theta is not updated by J^NT)."""
    model = MTSACTE("MlpPolicy", toy_env, **small_model_kwargs())
    model.learn(200)
    before = all_parameters(model)
    model.update_representation(16)
    after = all_parameters(model)
    changed = {k for k in before if not th.equal(before[k], after[k])}
    assert changed and all(k.startswith(("policy.encoder.", "policy.decoder.")) for k in changed)
    assert any(k.startswith("policy.encoder.") for k in changed)
    assert any(k.startswith("policy.decoder.") for k in changed)


# =========================================================================================== clipped Q loss (Eq. 16)
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


def test_tiny_q_loss_clip_freezes_the_critics(toy_env):
    """With V_clip below every per-sample loss, the critics get zero gradient and never move (Eq. 16)."""
    model = MTSACTE("MlpPolicy", toy_env, **small_model_kwargs(q_loss_clip=1e-12))
    critic_before = copy.deepcopy(model.critic.state_dict())
    actor_before = copy.deepcopy(model.actor.state_dict())
    model.learn(160)
    assert model._n_updates > 0
    assert_state_equal(model.critic.state_dict(), critic_before, "critic")
    assert any(not th.equal(v, actor_before[k]) for k, v in model.actor.state_dict().items())


# ====================================================================================================== top-K replay
def test_top_k_store_holds_the_k_best_episodes(tmp_path):
    n_tasks, top_k, length = 3, 4, 5
    env = make_episode_env(n_tasks, episode_length=length)
    # No training (learning_starts above the budget): random actions, the rewards do not depend on them.
    model = MTSACTE("MlpPolicy", env, **small_model_kwargs(learning_starts=10**6, top_k=top_k, buffer_size=3000))
    model.learn(n_tasks * 123)
    buffer = model.replay_buffer
    running = env.get_attr("episode")
    for task in range(n_tasks):
        completed = [episode_return(task, j, length) for j in range(running[task])]
        assert len(completed) == 24
        np.testing.assert_array_equal(buffer.episode_returns(task), completed)
        best = sorted(completed, reverse=True)[:top_k]
        np.testing.assert_array_equal(buffer.top_k_returns(task), best)
        for episode in buffer.top_k_episodes(task):
            obs = episode["observations"]
            j = int(obs[0, 2])
            assert np.all(obs[:, 0] == task) and np.all(obs[:, 2] == j)  # one whole episode of this task
            np.testing.assert_array_equal(obs[:, 1], np.arange(length))
            assert episode["return"] == episode_return(task, j, length) == pytest.approx(episode["rewards"].sum())
    path = tmp_path / "buffer.pkl"
    model.save_replay_buffer(path)
    other = MTSACTE("MlpPolicy", make_episode_env(n_tasks, episode_length=length), **small_model_kwargs(top_k=top_k))
    other.load_replay_buffer(path)
    for task in range(n_tasks):
        np.testing.assert_array_equal(other.replay_buffer.top_k_returns(task), buffer.top_k_returns(task))
        for mine, theirs in zip(buffer.top_k_episodes(task), other.replay_buffer.top_k_episodes(task)):
            assert_state_equal(mine, theirs, f"task {task}")
    # Representation batches from the loaded store only contain top-K transitions.
    batch = other.replay_buffer.sample_top_k(16)
    for task in range(n_tasks):
        best_ids = {int(e["observations"][0, 2]) for e in buffer.top_k_episodes(task)}
        rows = batch.observations[task * 16 : (task + 1) * 16].numpy()
        assert np.all(rows[:, 0] == task) and {int(v) for v in rows[:, 2]} <= best_ids


# ======================================================================================================= save / load
def _optimizers(model) -> dict:
    return {
        "actor": model.actor.optimizer.state_dict(),
        "critic": model.critic.optimizer.state_dict(),
        "rep": model.policy.rep_optimizer.state_dict(),
        "ent_coef": model.ent_coef_optimizer.state_dict(),
    }


def _nt_state(model) -> dict:
    return {
        "mu": model.mu.copy(),
        "selected": model.selected_tasks.copy(),
        "weights": model.task_weights.copy(),
        "transfer": model.transfer_matrix.copy(),
    }


def test_save_load_restores_everything_and_resumes_exactly(tmp_path):
    kwargs = small_model_kwargs(learning_starts=80, iteration_length=15, top_k=3)
    model = MTSACTE("MlpPolicy", make_mt_env("toy-conflict", seed=0), **kwargs)
    model.learn(600)
    assert model.replay_buffer.n_top_k_episodes.min() > 0 and model.mu.any()
    path, buffer_path = tmp_path / "model.zip", tmp_path / "buffer.pkl"
    model.save(path)
    model.save_replay_buffer(buffer_path)
    saved_params, saved_opt, saved_nt = all_parameters(model), copy.deepcopy(_optimizers(model)), _nt_state(model)
    obs = model.env.reset()
    saved_actions = model.predict(obs, deterministic=True)[0]

    # Run A goes on: a J^rep update, SAC updates, then more env steps on a fresh env.
    def resume(m):
        m.update_representation(8)
        m.train(3, 8)
        m.set_env(make_mt_env("toy-conflict", seed=0))
        m.env.seed(123)
        m.learn(100, reset_num_timesteps=False)
        return all_parameters(m), _optimizers(m), _nt_state(m)

    result_a = resume(model)

    loaded = MTSACTE.load(path, env=make_mt_env("toy-conflict", seed=0), device="cpu")
    loaded.load_replay_buffer(buffer_path)
    assert_state_equal(all_parameters(loaded), saved_params, "params")  # encoder, decoder, actor, critics, beta
    assert_state_equal(_optimizers(loaded), saved_opt, "optimizers")
    assert_state_equal(_nt_state(loaded), saved_nt, "negative transfer")
    for task in range(N_TASKS):
        np.testing.assert_array_equal(loaded.replay_buffer.top_k_returns(task), model.replay_buffer.top_k_returns(task))
        for mine, theirs in zip(model.replay_buffer.top_k_episodes(task), loaded.replay_buffer.top_k_episodes(task)):
            assert_state_equal(mine, theirs)
    np.testing.assert_array_equal(loaded.predict(obs, deterministic=True)[0], saved_actions)
    loaded.set_logger(Logger(folder=None, output_formats=[]))

    result_b = resume(loaded)
    for a, b, name in zip(result_a, result_b, ("params", "optimizers", "negative transfer")):
        assert_state_equal(a, b, name)
    # The comparison is not vacuous: the resumed runs moved away from the checkpoint.
    assert any(not th.equal(saved_params[k], result_a[0][k]) for k in saved_params)


def test_load_without_env_predicts(tmp_path):
    model = MTSACTE("MlpPolicy", make_mt_env("toy-conflict", seed=0), **small_model_kwargs())
    model.learn(120)
    obs = model.env.reset()
    expected = model.predict(obs, deterministic=True)[0]
    model.save(tmp_path / "model.zip")
    loaded = MTSACTE.load(tmp_path / "model.zip", device="cpu")
    assert loaded.replay_buffer is None
    np.testing.assert_array_equal(loaded.predict(obs, deterministic=True)[0], expected)


# ========================================================================================================= bad input
def test_invalid_hyperparameters(toy_env):
    with pytest.raises(ValueError, match=r"n_select \(M\) must satisfy 1 <= M < N = 4"):
        MTSACTE("MlpPolicy", toy_env, **small_model_kwargs(n_select=4))
    with pytest.raises(ValueError, match="n_select"):
        MTSACTE("MlpPolicy", toy_env, **small_model_kwargs(n_select=7))
    with pytest.raises(ValueError, match="n_select"):
        MTSACTE("MlpPolicy", toy_env, **small_model_kwargs(n_select=0))
    for top_k in (0, -3):
        with pytest.raises(ValueError, match=r"top_k \(K\) must be at least 1"):
            MTSACTE("MlpPolicy", toy_env, **small_model_kwargs(top_k=top_k))
    for clip in (0.0, -5.0, float("inf"), float("nan")):
        with pytest.raises(ValueError, match=r"q_loss_clip \(V_clip\) must be a positive number or None"):
            MTSACTE("MlpPolicy", toy_env, **small_model_kwargs(q_loss_clip=clip))
    with pytest.raises(ValueError, match="nt_estimator"):
        MTSACTE("MlpPolicy", toy_env, **small_model_kwargs(nt_estimator="exact"))
    with pytest.raises(ValueError, match="iteration_length"):
        MTSACTE("MlpPolicy", toy_env, **small_model_kwargs(iteration_length=0))
    for bad in ({"nt_step_size": -1e-3}, {"c_vae": -1.0}, {"rep_learning_rate": 0.0}):
        with pytest.raises(ValueError, match="nt_step_size and c_vae must be >= 0 and rep_learning_rate > 0"):
            MTSACTE("MlpPolicy", toy_env, **small_model_kwargs(**bad))


def test_env_without_one_sub_env_per_task():
    """3 sub-envs whose observations carry a 4-entry one-hot: rejected with a message naming the one-hot layout."""
    env = make_episode_env(n_tasks=4, n_envs=3)
    with pytest.raises(ValueError, match="one-hot"):
        MTSACTE("MlpPolicy", env, **small_model_kwargs()).learn(12)
    # A single sub-env is not a multi-task env.
    with pytest.raises(ValueError, match=r"at least 2 tasks \(one sub-env per task\)"):
        MTSACTE("MlpPolicy", DummyVecEnv([lambda: EpisodeEnv(0, 1)]), **small_model_kwargs())


@pytest.fixture
def trained_model(toy_env):
    model = MTSACTE("MlpPolicy", toy_env, **small_model_kwargs())
    model.learn(200)
    return model


def test_nan_critic_output_stops_training(trained_model, monkeypatch):
    model = trained_model
    _no_rep_update(model, monkeypatch)
    critic_before = copy.deepcopy(model.critic.state_dict())
    original = type(model.critic).forward
    # NaN Q-values, with and without the clip; +inf Q-values without the clip (with it, Eq. 16 clamps an infinite
    # per-sample loss to V_clip, and the infinite Q then shows up in the actor loss instead).
    for bad, clip in ((float("nan"), 2000.0), (float("nan"), None), (float("inf"), None)):
        model.q_loss_clip = clip
        monkeypatch.setattr(model.critic, "forward", lambda obs, act, bad=bad: original(model.critic, obs, act) + bad)
        with pytest.raises(FloatingPointError, match="critic loss"):
            model.train(1, 8)
    assert_state_equal(model.critic.state_dict(), critic_before, "critic")  # stopped before the optimizer step


def test_infinite_q_with_clip_stops_before_the_critic_step(trained_model, monkeypatch):
    model = trained_model
    _no_rep_update(model, monkeypatch)
    assert model.q_loss_clip == 2000.0
    critic_before = copy.deepcopy(model.critic.state_dict())
    original = type(model.critic).forward
    monkeypatch.setattr(model.critic, "forward", lambda obs, act: original(model.critic, obs, act) + float("inf"))
    with pytest.raises(FloatingPointError, match="critic loss"):
        model.train(1, 8)
    assert_state_equal(model.critic.state_dict(), critic_before, "critic")


def test_nan_actor_loss_stops_training(trained_model, monkeypatch):
    model = trained_model
    _no_rep_update(model, monkeypatch)
    original = type(model.critic).forward
    calls = {"n": 0}

    def forward(obs, actions):  # the 2nd critic call of an update evaluates Q at the policy's actions
        calls["n"] += 1
        out = original(model.critic, obs, actions)
        return out * float("nan") if calls["n"] % 2 == 0 else out

    monkeypatch.setattr(model.critic, "forward", forward)
    actor_before = copy.deepcopy(model.actor.state_dict())
    with pytest.raises(FloatingPointError, match="actor loss"):
        model.train(1, 8)
    assert_state_equal(model.actor.state_dict(), actor_before, "actor")


def test_nan_reward_stops_training(trained_model, monkeypatch):
    model = trained_model
    _no_rep_update(model, monkeypatch)
    model.replay_buffer.rewards[:] = np.nan
    with pytest.raises(FloatingPointError, match="critic loss"):
        model.train(1, 8)


def test_nan_entropy_coefficient_stops_training(trained_model, monkeypatch):
    model = trained_model
    _no_rep_update(model, monkeypatch)
    with th.no_grad():
        model.log_ent_coef[1] = float("nan")
    with pytest.raises(FloatingPointError, match="entropy coefficient loss"):
        model.train(1, 8)


def test_nan_representation_loss_stops_training(trained_model):
    model = trained_model
    encoder_before = copy.deepcopy(model.encoder.state_dict())
    with th.no_grad():
        model.decoder[0].weight[0, 0] = float("nan")
    with pytest.raises(FloatingPointError, match=r"J\^rep"):
        model.update_representation(8)
    assert_state_equal(model.encoder.state_dict(), encoder_before, "encoder")
    # A NaN in the top-K store's observations is caught the same way (VAE off, so only J^NT sees it).
    with th.no_grad():
        model.decoder[0].weight[0, 0] = 0.0
    model.use_vae = False
    model.replay_buffer._top_k[0].data["observations"][:] = np.nan
    with pytest.raises(FloatingPointError, match=r"J\^rep"):
        model.update_representation(8)


# =================================================================================================== reproducibility
def test_same_seed_same_run():
    def run():
        model = MTSACTE("MlpPolicy", make_mt_env("toy-conflict", seed=0), **small_model_kwargs())
        model.learn(300)
        return model

    a, b = run(), run()
    assert_state_equal(all_parameters(a), all_parameters(b), "params")
    assert_state_equal(_optimizers(a), _optimizers(b), "optimizers")
    assert_state_equal(_nt_state(a), _nt_state(b), "negative transfer")
    np.testing.assert_array_equal(a.replay_buffer.observations, b.replay_buffer.observations)
    c = MTSACTE("MlpPolicy", make_mt_env("toy-conflict", seed=0), **small_model_kwargs(seed=1))
    c.learn(300)
    assert any(not th.equal(v, all_parameters(c)[k]) for k, v in all_parameters(a).items())


# ========================================================================================================== learning
def _learn_toy(total_timesteps: int, seed: int, **overrides):
    from sb3_mtte import evaluate_success

    kwargs = {
        "learning_starts": 800,
        "batch_size": 64,
        "buffer_size": 50_000,
        "learning_rate": 1e-3,
        "top_k": 10,
        "iteration_length": 50,
        "rep_gradient_steps": 10,
        "rep_learning_rate": 1e-3,
        "policy_kwargs": {"net_arch": [64, 64]},
        "seed": seed,
        "device": "cpu",
    }
    kwargs.update(overrides)
    model = MTSACTE("MlpPolicy", make_mt_env("toy-conflict", seed=seed), **kwargs)
    start = time.perf_counter()
    model.learn(total_timesteps)
    elapsed = time.perf_counter() - start
    result = evaluate_success(model, make_mt_env("toy-conflict", seed=1000 + seed), episodes_per_task=50)
    return result, elapsed


def test_learns_toy_conflict():
    """The full method with its defaults for c_vae, nt_step_size, V_clip and M (small nets, L=64, H=50 vector steps,
    10 J^rep steps per iteration): 16k env steps (4k vector steps, ~45 s of one CPU core) reach a mean success
    >= 0.8 over 50 evaluation episodes per task (measured: 0.975, 1.0, 1.0 for seeds 0, 1, 2)."""
    result, _ = _learn_toy(16_000, seed=0)
    assert result.mean >= 0.8, result.as_dict()


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_learns_toy_conflict_longer(seed):
    """24k env steps (~70 s each): mean success >= 0.95 (measured 1.0 for seeds 0, 1, 2)."""
    result, _ = _learn_toy(24_000, seed=seed)
    assert result.mean >= 0.95, result.as_dict()


@pytest.mark.slow
def test_learns_toy_conflict_without_vae():
    """Ours-VAE ablation (use_vae=False): 12k env steps (~35 s), mean success >= 0.8 (measured 1.0, 1.0, 0.965)."""
    result, _ = _learn_toy(12_000, seed=0, use_vae=False)
    assert result.mean >= 0.8, result.as_dict()


def test_mt10_smoke():
    """A few hundred MT10 env steps with default networks, including two J^rep updates."""
    env = make_mt_env("MT10", seed=0)
    try:
        model = MTSACTE(
            "MlpPolicy",
            env,
            learning_starts=200,
            batch_size=16,
            iteration_length=5,
            rep_gradient_steps=2,
            seed=0,
            device="cpu",
        )
        calls = []
        original = model.update_representation
        model.update_representation = lambda batch_size: (calls.append(model.num_timesteps), original(batch_size))
        model.learn(300)
        assert len(calls) == 2
        assert model.mu.shape == (10,) and int(model.selected_tasks.sum()) == 5
        assert np.isfinite(model.transfer_matrix).all()
        assert all(th.isfinite(v).all() for v in all_parameters(model).values())
    finally:
        env.close()
