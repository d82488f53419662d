"""MTSACTE's schedule of Algorithm 1, its settings' validation, dtypes, the iteration-averaged measure option and the
probe of the task information in z."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch as th
from conftest import small_model_kwargs
from stable_baselines3.common.logger import configure

import sb3_mtte.mtsacte.mtsacte as mtsacte_module
from sb3_mtte import MTSACTE, make_mt_env
from sb3_mtte.mtsacte import NegativeTransferLogCallback
from sb3_mtte.mtsacte.objectives import significant_negative_transfer_measure, task_weights
from sb3_mtte.mtsacte.probe import task_probe_accuracy
from sb3_mtte.mtsacte.transfer import TransferStatistics

N_TASKS = 4


@pytest.fixture
def toy_env():
    env = make_mt_env("toy-conflict", seed=0)
    yield env
    env.close()


def recorded_iteration_starts(model) -> list[int]:
    calls: list[int] = []
    original = model.update_representation

    def update_representation(batch_size):
        calls.append(model.num_timesteps // N_TASKS)
        original(batch_size)

    model.update_representation = update_representation
    return calls


def test_iterations_start_at_multiples_of_h_when_train_freq_does_not_divide_it(toy_env):
    """H = 5 vector steps, an update every 3: train() runs at vector steps 3, 6, 9, ...; iteration k (steps 5k+1 ..
    5k+5) opens before the first of its steps that starts a rollout, or before its first update if that comes
    first: the very first update (3), then k = 1..5 at steps 6, 12, 15 (the rollout of steps 16-18), 21 and 27. Step
    30 is the run's last, so iteration 6 never opens."""
    model = MTSACTE("MlpPolicy", toy_env, **small_model_kwargs(learning_starts=8, iteration_length=5, train_freq=3))
    calls = recorded_iteration_starts(model)
    model.learn(30 * N_TASKS)
    assert calls == [3, 6, 12, 15, 21, 27]


def test_a_resumed_learn_keeps_the_iteration_grid(toy_env):
    model = MTSACTE("MlpPolicy", toy_env, **small_model_kwargs(learning_starts=8, iteration_length=5, train_freq=3))
    calls = recorded_iteration_starts(model)
    model.learn(15 * N_TASKS)
    model.learn(15 * N_TASKS, reset_num_timesteps=False)
    assert calls == [3, 6, 12, 15, 21, 27]  # as in one learn call of 30 steps


def test_rep_learning_rate_has_one_place(toy_env):
    with pytest.raises(ValueError, match="rep_learning_rate is an argument of MTSACTE"):
        MTSACTE("MlpPolicy", toy_env, **small_model_kwargs(policy_kwargs={"net_arch": [8], "rep_learning_rate": 1e-2}))
    model = MTSACTE("MlpPolicy", toy_env, **small_model_kwargs(rep_learning_rate=1e-2))
    assert [group["lr"] for group in model.policy.rep_optimizer.param_groups] == [1e-2]


def test_mtsacte_needs_two_tasks():
    one_task = make_mt_env(["reach-v3"], seed=0)
    try:
        with pytest.raises(ValueError, match="needs at least 2 tasks"):
            MTSACTE("MlpPolicy", one_task, **small_model_kwargs())
    finally:
        one_task.close()


def test_task_weights_follow_the_given_dtype():
    mu = th.tensor([0, 1, 3])
    weights = task_weights(mu)
    assert weights.dtype == th.float32
    expected = np.exp(3 - np.array([0.0, 1.0, 3.0]))
    np.testing.assert_allclose(weights.numpy(), expected / expected.sum(), rtol=1e-6)
    assert task_weights(mu, th.float64).dtype == th.float64


def test_model_task_weights_are_float32_like_the_actor(toy_env):
    model = MTSACTE("MlpPolicy", toy_env, **small_model_kwargs())
    model.learn(60 * N_TASKS)
    assert model.task_weights.dtype == th.float32
    assert model._actor_weights().dtype == next(model.actor.parameters()).dtype


# ================================================================== nt_measure (beyond the paper when not per_batch)
# Three batches of an iteration, as [k, i] = J_i(theta^k) - J_i(theta). In the first two, task 3 lowers the
# objective of the three others; in the third, batch noise flips that row and makes task 0 look harmful instead.
ALL_UP = [1.0, 1.0, 1.0, 1.0]
SCRIPTED_MATRICES = [
    th.tensor([ALL_UP, ALL_UP, ALL_UP, [-1.0, -1.0, -1.0, 1.0]]),
    th.tensor([ALL_UP, ALL_UP, ALL_UP, [-1.0, -1.0, -1.0, 1.0]]),
    th.tensor([[-0.5, -0.5, 1.0, -0.5], ALL_UP, ALL_UP, [0.5, 0.5, 0.5, 1.0]]),
]


def scripted_update(model, monkeypatch) -> list[list[int]]:
    """Run one iteration's J^rep steps with the scripted matrices; return the harmful set given to each step."""
    matrices = iter(SCRIPTED_MATRICES)
    monkeypatch.setattr(mtsacte_module, "transfer_matrix", lambda *args, **kwargs: next(matrices).clone())
    harmful_sets: list[list[int]] = []
    original = mtsacte_module.representation_gradients

    def representation_gradients(objectives, harmful_tasks, **kwargs):
        harmful_sets.append(harmful_tasks.tolist())
        return original(objectives, harmful_tasks, **kwargs)

    monkeypatch.setattr(mtsacte_module, "representation_gradients", representation_gradients)
    model.update_representation(8)
    return harmful_sets


def model_for_scripted_update(env, measure: str) -> MTSACTE:
    kwargs = small_model_kwargs(rep_gradient_steps=3, n_select=3, nt_measure=measure, iteration_length=10**6)
    model = MTSACTE("MlpPolicy", env, **kwargs)
    model.learn(60 * N_TASKS)
    return model


def test_per_batch_measure_is_the_papers(toy_env, monkeypatch):
    model = model_for_scripted_update(toy_env, "per_batch")
    assert scripted_update(model, monkeypatch) == [[3], [3], [0]]
    assert model.mu.tolist() == [3, 0, 0, 0]
    assert model.selected_tasks.tolist() == [False, True, True, True]
    np.testing.assert_allclose(model.transfer_matrix, SCRIPTED_MATRICES[2].numpy())


def test_iteration_averaged_measure(toy_env, monkeypatch):
    model = model_for_scripted_update(toy_env, "mean")
    # running means of the matrices: after the third batch, row 3 = (-0.5, -0.5, -0.5, 1) and row 0 = (0.5, 0.5, 1, 0.5)
    assert scripted_update(model, monkeypatch) == [[3], [3], [3]]
    assert model.mu.tolist() == [0, 0, 0, 3]
    assert model.selected_tasks.tolist() == [True, True, True, False]
    mean = [[0.5, 0.5, 1.0, 0.5], ALL_UP, ALL_UP, [-0.5, -0.5, -0.5, 1.0]]
    np.testing.assert_allclose(model.transfer_matrix, np.array(mean), rtol=1e-6)


# ================================================================================ task information in z (a probe)
def test_probe_of_separable_z_is_perfect():
    z = th.tensor([[-1.0], [-1.2], [-0.8], [-1.1]]).expand(2, 4, 1).clone()
    z[1] *= -1  # task 0 around -1, task 1 around +1
    assert task_probe_accuracy(z) == 1.0


def test_probe_of_task_free_z_is_at_chance():
    """Identical z for every task: the probe predicts the same task for all held-out samples, accuracy 1/N."""
    z = th.randn(1, 6, 3, generator=th.Generator().manual_seed(0)).expand(3, 6, 3)
    assert task_probe_accuracy(z) == pytest.approx(1 / 3)


def test_probe_needs_two_samples_per_task():
    assert np.isnan(task_probe_accuracy(th.zeros(3, 1, 2)))


def test_model_records_the_probe(toy_env, tmp_path):
    model = MTSACTE("MlpPolicy", toy_env, **small_model_kwargs())
    assert np.isnan(model.task_probe_accuracy)
    model.set_logger(configure(str(tmp_path), ["csv"]))
    model.learn(60 * N_TASKS)
    assert 0.0 <= model.task_probe_accuracy <= 1.0 and 0.0 <= model.task_probe_accuracy_of_mean <= 1.0
    records = [json.loads(line) for line in (tmp_path / "negative_transfer.jsonl").read_text().splitlines()]
    assert records and records[-1]["task_probe_accuracy"] == model.task_probe_accuracy
    assert records[-1]["task_probe_accuracy_of_mean"] == model.task_probe_accuracy_of_mean
    assert records[-1]["z_std"] == model.z_std


def test_negative_transfer_log_is_written_by_its_callback(toy_env, tmp_path, monkeypatch):
    """learn() attaches the callback: one line per iteration (its last C_s and w), in the record format
    the tools read. update_representation only queues the record; the callback writes it."""
    model = MTSACTE("MlpPolicy", toy_env, **small_model_kwargs())
    model.set_logger(configure(str(tmp_path), ["csv"]))
    calls = []
    original_update = model.update_representation

    def update_representation(batch_size):
        original_update(batch_size)
        calls.append(model.num_timesteps)

    monkeypatch.setattr(model, "update_representation", update_representation)
    model.learn(60 * N_TASKS)
    path = tmp_path / "negative_transfer.jsonl"
    records = [json.loads(line) for line in path.read_text().splitlines()]
    assert [r["timesteps"] for r in records] == calls and len(calls) > 1 and not model.negative_transfer_records
    keys = {"timesteps", "mu", "selected", "weights", "transfer_matrix", "transfer_matrix_dtype", "task_probe_accuracy"}
    assert set(records[0]) == keys | {"task_probe_accuracy_of_mean", "z_std"}
    original_update(8)
    assert len(path.read_text().splitlines()) == len(records) and len(model.negative_transfer_records) == 1
    callback = NegativeTransferLogCallback()
    callback.init_callback(model)
    callback.on_training_end()
    last = json.loads(path.read_text().splitlines()[-1])
    assert len(path.read_text().splitlines()) == len(records) + 1 and not model.negative_transfer_records
    assert last["mu"] == model.mu.tolist() and last["weights"] == model.task_weights.tolist()
    assert last["selected"] == model.selected_tasks.int().tolist()
    assert last["transfer_matrix"] == model.transfer_matrix.double().tolist()


def test_probe_and_z_std_read_the_last_batch_before_its_update(toy_env, monkeypatch):
    model = MTSACTE("MlpPolicy", toy_env, **small_model_kwargs(rep_gradient_steps=1, iteration_length=10**6))
    model.learn(60 * N_TASKS)
    batch = model._representation_batch(8)
    monkeypatch.setattr(model, "_representation_batch", lambda batch_size: batch)
    with th.no_grad():
        mean, log_std = model.policy.embedding_params(batch.obs)
    model.update_representation(8)
    assert model.z_std == pytest.approx(float(log_std.exp().mean()), rel=1e-6)
    assert model.task_probe_accuracy_of_mean == task_probe_accuracy(mean)
    assert model.task_probe_accuracy == task_probe_accuracy(mean + log_std.exp() * batch.z_noise)


def test_significant_measure_counts_only_consistent_signs(toy_env, monkeypatch):
    """Over the three batches, row 3's entries are (-1, -1, 0.5) for i < 3: mean -0.5, standard error 0.5, not two
    standard errors below zero; row 0's entries (1, 1, -0.5) are never significantly negative either. With every mu
    equal, C_s is every task (Eq. 7) and the harmful set of the last J^rep step is empty."""
    model = model_for_scripted_update(toy_env, "significant")
    harmful = scripted_update(model, monkeypatch)
    # batch 1 alone: no spread, so the signs of batch 1 count; after two identical batches the spread is zero too
    assert harmful == [[3], [3], []]
    assert model.mu.tolist() == [0, 0, 0, 0]
    assert model.selected_tasks.tolist() == [True, True, True, True]


def test_transfer_statistics_against_numpy():
    matrices = [th.randn(3, 3, generator=th.Generator().manual_seed(i)) for i in range(5)]
    statistics = TransferStatistics()
    for matrix in matrices:
        statistics.add(matrix)
    stacked = np.stack([m.numpy() for m in matrices])
    np.testing.assert_allclose(statistics.mean.numpy(), stacked.mean(0), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(statistics.standard_error.numpy(), stacked.std(0, ddof=1) / np.sqrt(5), rtol=1e-4)
    mean, error = th.tensor([[-3.0, -1.0], [1.0, -0.1]]), th.tensor([[1.0, 1.0], [0.1, 0.01]])
    assert significant_negative_transfer_measure(mean, error).tolist() == [1, 1]


def test_unknown_nt_measure(toy_env):
    with pytest.raises(ValueError, match="nt_measure"):
        MTSACTE("MlpPolicy", toy_env, **small_model_kwargs(nt_measure="median"))
