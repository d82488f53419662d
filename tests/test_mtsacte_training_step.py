"""MTSACTE's training step and acting against plain references: the soft-Q target and its clipped loss (Eq.
15-16), how z ~ E_phi is used when acting, when the J^rep update steps and what trains the encoder, and E_phi's
initialisation."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
import torch as th
from conftest import capture_applied_gradients, disable_representation_updates, small_model_kwargs
from references import loop_q, loop_split
from stable_baselines3.common.logger import Logger

import sb3_mtte.mtsac.mtsac as mtsac_module
from sb3_mtte import MTSACTE
from sb3_mtte.mtsacte.objectives import (
    TaskSelection,
)

N_TASKS = 4


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
    captured = capture_applied_gradients(model, monkeypatch)
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
