"""Tests of the MTSACTE algorithm (multi-task SAC with a task embedding network): what a recomputation stores, the
Algorithm-1 schedule, which parameters each loss trains, top-K replay, save/load/resume, input validation, numerical
guards, reproducibility and learning. The equations themselves are checked in test_mtsacte_equations.py."""

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
    disable_representation_updates,
    episode_return,
    kappa_benign_set,
    make_episode_env,
    small_model_kwargs,
)
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.save_util import load_from_zip_file
from stable_baselines3.common.vec_env import DummyVecEnv

import sb3_mtte.mtsacte.mtsacte as mtsacte_module
from sb3_mtte import MTSACTE, make_mt_env
from sb3_mtte.mtsacte.objectives import negative_transfer_measure, task_weights
from sb3_mtte.mtsacte.transfer import RepresentationBatch, TaskObjectives, transfer_matrix

N_TASKS = 4


# ======================================================================================= the algorithm (Algorithm 1)
def test_initial_negative_transfer_state(toy_env):
    model = MTSACTE("MlpPolicy", toy_env, **small_model_kwargs())
    assert model.n_select == N_TASKS // 2
    assert model.mu.tolist() == [0] * N_TASKS
    np.testing.assert_allclose(model.task_weights, np.full(N_TASKS, 1 / N_TASKS))
    th.testing.assert_close(model._actor_weights(), th.full((N_TASKS,), 1 / N_TASKS))


def test_attributes_after_recomputation(toy_env):
    """mu, C_s and w stored by every recomputation agree with the stored transfer matrix through Eq. 6-8 written as
    loops (M = 3 of N = 4: C_s has 3 or 4 tasks)."""
    model = MTSACTE("MlpPolicy", toy_env, **small_model_kwargs(n_select=3))
    model.learn(200)
    seen_mu = set()
    for _ in range(6):
        model.update_representation(16)
        matrix = model.transfer_matrix
        assert matrix.shape == (N_TASKS, N_TASKS) and model.mu.shape == (N_TASKS,)
        mu = [sum(1 for i in range(N_TASKS) if matrix[k, i] < 0) for k in range(N_TASKS)]
        assert model.mu.tolist() == mu and model.mu.dtype == th.long
        assert model.selected_tasks.dtype == th.bool
        assert set(np.flatnonzero(model.selected_tasks).tolist()) == kappa_benign_set(mu, 3)
        numerators = [math.exp(N_TASKS - m) for m in mu]
        np.testing.assert_allclose(model.task_weights, [v / sum(numerators) for v in numerators], rtol=1e-6)
        assert model.task_weights.dtype == th.float32
        np.testing.assert_array_equal(model._actor_weights().numpy(), model.task_weights)
        seen_mu.add(tuple(mu))
    assert len(seen_mu) > 1  # not one constant answer


@pytest.mark.parametrize(
    "last_step, opened_after", [(60, [14, 21, 28, 35, 42, 49, 56]), (56, [14, 21, 28, 35, 42, 49])]
)
def test_representation_schedule(toy_env, monkeypatch, last_step, opened_after):
    """Algorithm 1: iteration k opens with rep_gradient_steps J^rep updates, then takes vector steps kH+1 .. (k+1)H,
    each followed by its update. The run's first update opens its iteration before itself; iteration k opens
    before step kH+1 is taken, so after the update of step kH, and never after the run's last step. Every J^rep
    update recomputes mu on a top-K batch; every policy update uses the w of the latest recomputation."""
    learning_starts, horizon, rep_steps = 40, 7, 3
    model = MTSACTE(
        "MlpPolicy",
        toy_env,
        **small_model_kwargs(learning_starts=learning_starts, iteration_length=horizon, rep_gradient_steps=rep_steps),
    )
    events, counts = [], {"transfer": 0, "apply": 0, "top_k": 0, "sample": 0}
    original_update = model.update_representation

    def update_representation(batch_size):
        original_update(batch_size)
        events.append(("rep", model.num_timesteps // N_TASKS, model.task_weights.clone()))

    original_weights = model._actor_weights

    def actor_weights():
        weights = original_weights()
        events.append(("update", model.num_timesteps // N_TASKS, weights.clone()))
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
    monkeypatch.setattr(model, "_actor_weights", actor_weights)
    monkeypatch.setattr(model, "_apply_gradients", counting_apply)
    monkeypatch.setattr(mtsacte_module, "transfer_matrix", counting_transfer)
    model.learn(last_step * N_TASKS)

    # train() runs from vector step 11 (num_timesteps 44 > learning_starts), written out by hand:
    expected = [("rep", 11)]
    for step in range(11, last_step + 1):
        expected.append(("update", step))
        expected += [("rep", step)] if step in opened_after else []
    assert [(kind, step) for kind, step, _ in events] == expected
    n_reps = 1 + len(opened_after)
    assert counts["apply"] == counts["transfer"] == n_reps * rep_steps
    assert model._n_updates == last_step - 11 + 1  # one SAC update per vector step
    latest = None
    for kind, _, weights in events:  # every policy update uses the weights of the latest recomputation
        if kind == "rep":
            latest = weights
        else:
            th.testing.assert_close(weights, th.as_tensor(latest, dtype=th.float32))
    rep_params = list(model.policy.rep_optimizer.state.values())
    assert all(int(state["step"]) == n_reps * rep_steps for state in rep_params)
    buffer = model.replay_buffer
    original_top_k, original_sample = buffer.sample_top_k, buffer.sample

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
    assert first == [11, 14, 21, 28, 35, 42, 49, 56]  # as in test_representation_schedule (60 steps)
    calls.clear()
    model.learn(240)  # reset_num_timesteps=True: a new run, counted from 0 again
    assert calls == first


def test_policy_loss_does_not_train_the_encoder(toy_env, monkeypatch):
    """z is detached from phi in the policy and critic losses: without a J^rep step the encoder and decoder are
    unchanged and get no gradient, while the actor and critics move (Algorithm 1: phi is trained by J^rep only)."""
    model = MTSACTE("MlpPolicy", toy_env, **small_model_kwargs())
    model.learn(200)
    disable_representation_updates(model, monkeypatch)
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
        for mine, theirs in zip(buffer.top_k_episodes(task), other.replay_buffer.top_k_episodes(task), strict=True):
            assert_state_equal(mine, theirs, f"task {task}")
    # Representation batches from the loaded store only contain top-K transitions.
    batch = other.replay_buffer.sample_top_k(16)
    for task in range(n_tasks):
        best_ids = {int(e["observations"][0, 2]) for e in buffer.top_k_episodes(task)}
        rows = batch.observations[task].numpy()
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
        "mu": model.mu.clone(),
        "selected": model.selected_tasks.clone(),
        "weights": model.task_weights.clone(),
        "transfer": model.transfer_matrix.clone(),
    }


def test_save_load_restores_everything_and_resumes_exactly(tmp_path):
    kwargs = small_model_kwargs(learning_starts=80, iteration_length=15, top_k=3)
    model = MTSACTE("MlpPolicy", make_mt_env("toy-conflict", seed=0), **kwargs)
    model.learn(640)
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
        saved, restored = model.replay_buffer.top_k_episodes(task), loaded.replay_buffer.top_k_episodes(task)
        for mine, theirs in zip(saved, restored, strict=True):
            assert_state_equal(mine, theirs)
    np.testing.assert_array_equal(loaded.predict(obs, deterministic=True)[0], saved_actions)
    loaded.set_logger(Logger(folder=None, output_formats=[]))

    result_b = resume(loaded)
    for a, b, name in zip(result_a, result_b, ("params", "optimizers", "negative transfer"), strict=True):
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


def test_checkpoint_stores_the_task_selection_as_numpy(tmp_path):
    """mu, C_s, w and the transfer matrix go into the checkpoint as numpy arrays (so a model saved on a GPU loads
    on a CPU) and come back as tensors of the same dtype on the loading model's device, still equal."""
    model = MTSACTE("MlpPolicy", make_mt_env("toy-conflict", seed=0), **small_model_kwargs())
    model.learn(120)
    model.save(tmp_path / "model.zip")
    data, _, _ = load_from_zip_file(tmp_path / "model.zip", device="cpu")
    loaded = MTSACTE.load(tmp_path / "model.zip", device="cpu")
    for name in ("mu", "selected_tasks", "task_weights", "transfer_matrix"):
        assert isinstance(data[name], np.ndarray), name
        saved, restored = getattr(model, name), getattr(loaded, name)
        assert isinstance(restored, th.Tensor) and restored.device.type == "cpu", name
        assert restored.dtype == saved.dtype and th.equal(restored, saved), name
    assert isinstance(model.mu, th.Tensor)  # the saving model keeps its tensors


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
    with pytest.raises(ValueError, match="at least 2 tasks"):
        MTSACTE("MlpPolicy", DummyVecEnv([lambda: EpisodeEnv(0, 1)]), **small_model_kwargs())


@pytest.fixture
def trained_model(toy_env):
    model = MTSACTE("MlpPolicy", toy_env, **small_model_kwargs())
    model.learn(200)
    return model


def test_nan_critic_output_stops_training(trained_model, monkeypatch):
    model = trained_model
    disable_representation_updates(model, monkeypatch)
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
    disable_representation_updates(model, monkeypatch)
    assert model.q_loss_clip == 2000.0
    critic_before = copy.deepcopy(model.critic.state_dict())
    original = type(model.critic).forward
    monkeypatch.setattr(model.critic, "forward", lambda obs, act: original(model.critic, obs, act) + float("inf"))
    with pytest.raises(FloatingPointError, match="critic loss"):
        model.train(1, 8)
    assert_state_equal(model.critic.state_dict(), critic_before, "critic")


def test_nan_actor_loss_stops_training(trained_model, monkeypatch):
    model = trained_model
    disable_representation_updates(model, monkeypatch)
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
    disable_representation_updates(model, monkeypatch)
    model.replay_buffer.rewards[:] = np.nan
    with pytest.raises(FloatingPointError, match="critic loss"):
        model.train(1, 8)


def test_nan_entropy_coefficient_stops_training(trained_model, monkeypatch):
    model = trained_model
    disable_representation_updates(model, monkeypatch)
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
        with th.no_grad():
            z = objectives.embedding(objectives.phi()[0])[0]
        matrix = transfer_matrix(objectives, z, model.nt_step_size)
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


# ========================================================================================================== learning
def _mean_selection_on_toy(seed: int, monkeypatch) -> tuple[np.ndarray, np.ndarray]:
    """mu and w averaged over every recomputation of 4k env steps of toy-conflict with the zoo's settings (18
    iterations of 10 recomputations, each on its own top-K batch; about 15 s on one CPU core)."""
    model = MTSACTE(
        "MlpPolicy",
        make_mt_env("toy-conflict", seed=seed),
        learning_rate=1e-3,
        buffer_size=40_000,
        learning_starts=400,
        batch_size=64,
        tau=0.01,
        gamma=0.95,
        n_select=2,
        top_k=10,
        iteration_length=50,
        rep_gradient_steps=10,
        rep_learning_rate=1e-3,
        policy_kwargs={"net_arch": [64, 64]},
        seed=seed,
        device="cpu",
    )
    mus, weights = [], []
    original_store = model._set_selection

    def store(*args):
        original_store(*args)
        mus.append(model.mu.numpy().copy())
        weights.append(model.task_weights.numpy().copy())

    monkeypatch.setattr(model, "_set_selection", store)
    model.learn(4000)
    assert len(mus) == 18 * 10
    return np.mean(mus, axis=0), np.mean(weights, axis=0)


def _assert_conflict_singled_out(mean_mu: np.ndarray, mean_weights: np.ndarray) -> None:
    conflict = N_TASKS - 1
    assert mean_mu[conflict] > mean_mu[:conflict].max(), mean_mu
    assert mean_weights[conflict] < mean_weights[:conflict].min(), mean_weights


@pytest.mark.slow
def test_training_singles_out_the_conflicting_task_over_seeds(monkeypatch):
    """Over seeds 0..5 pooled (each seed's run-average, then their mean), mu is largest and w smallest for the
    conflicting task (measured mean mu [1.40, 1.39, 1.40, 1.46]). A single seed does not: four of the six single it
    out (0, 2, 4, 5) and two do not (1: [1.45, 1.48, 1.41, 1.40], 3: [1.29, 1.29, 1.35, 1.33]), and another CPU's
    kernels change a run's trajectory as another seed would. The mechanism on one batch, with margins that do not
    depend on training: test_conflicting_task_has_largest_mu_and_smallest_weight."""
    runs = [_mean_selection_on_toy(seed, monkeypatch) for seed in range(6)]
    _assert_conflict_singled_out(np.mean([mu for mu, _ in runs], axis=0), np.mean([w for _, w in runs], axis=0))


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
    """A few hundred MT10 env steps with default networks, including three J^rep updates."""
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
        model.learn(350)
        # train() from num_timesteps 210 (vector step 21: iteration 4 opens before its update); iterations 5 and 6
        # open after the updates of steps 25 and 30; step 35 is the run's last, so nothing opens after it.
        assert calls == [210, 250, 300]
        assert set(np.flatnonzero(model.selected_tasks).tolist()) == kappa_benign_set(model.mu, 5)
        assert np.isfinite(model.transfer_matrix).all()
        assert all(th.isfinite(v).all() for v in all_parameters(model).values())
    finally:
        env.close()


def _toy_probes(total_timesteps: int, **overrides) -> list[tuple[int, float, float]]:
    """(env steps, probe of sampled z, E_phi's std) after every J^rep recomputation of a toy-conflict run with the
    settings of _learn_toy (J^rep every 50 vector steps)."""
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
        "seed": 0,
        "device": "cpu",
    }
    kwargs.update(overrides)
    model = MTSACTE("MlpPolicy", make_mt_env("toy-conflict", seed=0), **kwargs)
    probes = []
    update = model.update_representation

    def recorded(batch_size: int) -> None:
        update(batch_size)
        probes.append((model.num_timesteps, model.task_probe_accuracy, model.z_std))

    model.update_representation = recorded  # type: ignore[method-assign]
    model.learn(total_timesteps)
    return probes


def test_default_schedule_gives_z_the_task_from_the_start_and_keeps_it():
    """With the defaults (E_phi at std 0.01, its mean head x 50, c_vae 1e-4), the probe of sampled z (chance 0.25)
    is >= 0.5 at every one of the 26 recomputations of the first 6,000 env steps (1,500 per task) and 0.8 on average
    (measured: 0.83 to 1.0, mean 0.94; with the mean head at PyTorch's scale 0.58 to 0.95, mean 0.84); with the former
    defaults (std ~1 at the start, c_vae 1e-2) it starts near chance (measured 0.19, 0.21, 0.30 at the first three,
    std 0.96-0.98)."""
    probes = [probe for _, probe, _ in _toy_probes(6_000)]
    assert len(probes) == 26 and min(probes) >= 0.5 and np.mean(probes) >= 0.8, probes
    former = {"net_arch": [64, 64], "z_init_std": None, "z_mean_init_gain": 1.0}
    former = _toy_probes(1_200, c_vae=1e-2, policy_kwargs=former)
    assert max(probe for _, probe, _ in former) < 0.45 and min(std for _, _, std in former) > 0.5, former
