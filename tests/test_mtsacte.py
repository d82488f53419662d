"""Tests of the MTSACTE algorithm (multi-task SAC with a task embedding network): what a recomputation stores, the
Algorithm-1 schedule, which parameters each loss trains, top-K replay, save/load/resume and reproducibility. The
equations are checked in test_mtsacte_equations.py and test_mtsacte_training_step.py, bad input and the numerical
guards in test_mtsacte_guards.py, learning in test_mtsacte_learning.py."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
import torch as th
from conftest import (
    all_parameters,
    assert_state_equal,
    disable_representation_updates,
    episode_return,
    make_episode_env,
    small_model_kwargs,
)
from references import kappa_benign_set
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.save_util import load_from_zip_file

import sb3_mtte.mtsacte.mtsacte as mtsacte_module
from sb3_mtte import MTSACTE, make_mt_env

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


def test_update_representation_runs_on_a_freshly_loaded_model(tmp_path, toy_env):
    """Without a learn since loading there is no logger: the update runs and sets mu, C_s and w all the same."""
    model = MTSACTE("MlpPolicy", toy_env, **small_model_kwargs())
    model.learn(200)
    model.save(tmp_path / "model.zip")
    model.save_replay_buffer(tmp_path / "buffer.pkl")
    loaded = MTSACTE.load(tmp_path / "model.zip", env=toy_env)
    loaded.load_replay_buffer(tmp_path / "buffer.pkl")
    loaded.mu.fill_(-1)
    loaded.update_representation()  # the model's batch_size
    assert loaded.mu.min() >= 0 and loaded.selected_tasks.any()
    assert float(loaded.task_weights.sum()) == pytest.approx(1.0)
