"""Faults of the Python API: ``time/episodes`` counts every finished episode of every sub-env, a damaged checkpoint
fails with one line, and an env that breaks the multi-task layout is refused at construction."""

from __future__ import annotations

import csv

import gymnasium as gym
import numpy as np
import pytest
from conftest import make_episode_env, small_model_kwargs
from stable_baselines3.common.logger import configure
from stable_baselines3.common.vec_env import DummyVecEnv

from sb3_mtte import MTSAC, MTSACTE, make_mt_env
from sb3_mtte.envs import make_env_fns

MTSAC_KWARGS = {"learning_starts": 40, "batch_size": 8, "buffer_size": 1_000, "policy_kwargs": {"net_arch": [8]}}
ALGORITHMS = {"MTSAC": (MTSAC, {**MTSAC_KWARGS, "device": "cpu"}), "MTSACTE": (MTSACTE, small_model_kwargs())}


# ========================================================================================== time/episodes
def monitor_episodes_by_step(env: DummyVecEnv, step: int) -> int:
    """The episodes that the sub-envs' own Monitors saw end within the first ``step`` vector steps."""
    ends = [np.cumsum(sub_env.get_episode_lengths()) for sub_env in env.envs]
    return int(sum(np.count_nonzero(sub_env_ends <= step) for sub_env_ends in ends))


@pytest.mark.parametrize("log_interval", [1, 4])
def test_time_episodes_counts_every_episode_of_every_sub_env(tmp_path, log_interval):
    """5 sub-envs end their episodes at the same steps: each dump counts all 5, as the Monitors do."""
    n_tasks, length, episodes = 5, 6, 7
    env = make_mt_env(f"toy-conflict-{n_tasks}", seed=0, max_episode_steps=length)
    model = MTSAC("MlpPolicy", env, **{**ALGORITHMS["MTSAC"][1], "learning_starts": n_tasks * length})
    model.set_logger(configure(str(tmp_path), ["csv"]))
    model.learn(n_tasks * length * episodes, log_interval=log_interval)
    with open(tmp_path / "progress.csv") as file:
        rows = list(csv.DictReader(file))
    assert len(rows) == episodes  # one dump per step; each step ends 5 episodes, at least one a multiple of 4
    for row in rows:
        step = int(row["time/total_timesteps"]) // n_tasks
        assert int(row["time/episodes"]) == monitor_episodes_by_step(env, step), row
    assert int(rows[-1]["time/episodes"]) == n_tasks * episodes == monitor_episodes_by_step(env, length * episodes)


# ============================================================================================ checkpoints
@pytest.mark.parametrize("name", sorted(ALGORITHMS))
def test_a_truncated_checkpoint_fails_with_one_line(tmp_path, toy_env, name):
    cls, kwargs = ALGORITHMS[name]
    cls("MlpPolicy", toy_env, **kwargs).save(tmp_path / "model.zip")
    data = (tmp_path / "model.zip").read_bytes()
    (tmp_path / "truncated.zip").write_bytes(data[: len(data) // 2])
    for path in (tmp_path / "truncated.zip", str(tmp_path / "truncated.zip")):
        with pytest.raises(ValueError, match=r"truncated\.zip is not a complete SB3 checkpoint \(") as refused:
            cls.load(path)
        assert "\n" not in str(refused.value) and "save the model again" in str(refused.value)
    with open(tmp_path / "truncated.zip", "rb") as file, pytest.raises(ValueError, match="not a complete SB3"):
        cls.load(file)


def test_a_zip_without_the_data_of_a_checkpoint_fails_with_one_line(tmp_path):
    import zipfile

    with zipfile.ZipFile(tmp_path / "other.zip", "w") as archive:
        archive.writestr("notes.txt", "not a model")
    with pytest.raises(ValueError, match=r"other\.zip is not a complete SB3 checkpoint \(.*'data'"):
        MTSACTE.load(tmp_path / "other.zip")


# =================================================================================== the env, at construction
@pytest.mark.parametrize("name", sorted(ALGORITHMS))
def test_too_few_sub_envs_are_refused_at_construction(name):
    """3 sub-envs of the 4-task toy: each declares its task of 4, so no reset is needed to see it."""
    cls, kwargs = ALGORITHMS[name]
    env = DummyVecEnv(make_env_fns("toy-conflict")[:3])
    with pytest.raises(ValueError, match=r"^Sub-env 0 observes the one-hot of task 0 of 4, but sub-env i must .*N = 3"):
        cls("MlpPolicy", env, **kwargs)


@pytest.mark.parametrize("name", sorted(ALGORITHMS))
def test_sub_envs_out_of_task_order_are_refused_at_construction(toy_env, name):
    cls, kwargs = ALGORITHMS[name]
    fns = make_env_fns("toy-conflict")
    with pytest.raises(ValueError, match=r"^Sub-env 0 observes the one-hot of task 1 of 4, but sub-env i must"):
        cls("MlpPolicy", DummyVecEnv([fns[1], fns[0], *fns[2:]]), **kwargs)
    model = cls("MlpPolicy", toy_env, **kwargs)
    with pytest.raises(ValueError, match=r"^Sub-env 0 observes the one-hot of task 3 of 4"):
        model.set_env(DummyVecEnv(fns[::-1]))


@pytest.mark.parametrize("name", sorted(ALGORITHMS))
def test_an_env_without_declared_tasks_is_checked_at_construction(name):
    """Sub-envs that do not declare their tasks: their first observations are read at construction."""
    cls, kwargs = ALGORITHMS[name]
    with pytest.raises(ValueError, match=r"identity matrix: build the env with make_mt_env"):
        cls("MlpPolicy", make_episode_env(n_tasks=4, n_envs=3), **kwargs)


def test_a_plain_pendulum_is_refused_at_construction():
    for env in (gym.make("Pendulum-v1"), DummyVecEnv([lambda: gym.make("Pendulum-v1")])):
        with pytest.raises(ValueError, match=r"one-hot.*make_mt_env.*OneHotTaskWrapper"):
            MTSAC("MlpPolicy", env, **ALGORITHMS["MTSAC"][1])


def test_the_first_learn_starts_from_the_reset_made_at_construction():
    """The env read at construction is not reset again by learn: its first episode is episode 0."""
    env = make_episode_env(n_tasks=3, episode_length=5)
    model = MTSAC("MlpPolicy", env, **{**ALGORITHMS["MTSAC"][1], "learning_starts": 9})
    assert env.get_attr("episode") == [0, 0, 0]
    model.learn(3 * 7)
    assert env.get_attr("episode") == [1, 1, 1]
    first_rows = model.replay_buffer.observations[:5, :, :3]  # (task, step, episode) of every task's first steps
    np.testing.assert_array_equal(first_rows[:, :, 2], 0)
    np.testing.assert_array_equal(first_rows[:, :, 1], np.arange(5)[:, None].repeat(3, axis=1))


def test_a_model_built_on_declared_tasks_does_not_reset_the_env(toy_env, monkeypatch):
    resets = []
    monkeypatch.setattr(toy_env, "reset", lambda: resets.append(1) or DummyVecEnv.reset(toy_env))
    model = MTSAC("MlpPolicy", toy_env, **{**ALGORITHMS["MTSAC"][1], "learning_starts": 4})
    assert resets == []
    model.learn(8)
    assert resets == [1]


@pytest.mark.parametrize("cls", [MTSAC, MTSACTE])
def test_predict_takes_float64_lists_and_single_observations_as_sb3_does(toy_env, cls):
    """SB3 casts observations to float32: float64 arrays, lists and one observation act as the float32 batch does."""
    kwargs = {"policy_kwargs": {"net_arch": [16, 16]}, "learning_starts": 40, "seed": 0, "device": "cpu"}
    model = cls("MlpPolicy", toy_env, **kwargs)
    obs = toy_env.reset()
    expected, _ = model.predict(obs, deterministic=True)
    for given in (obs.astype(np.float64), obs.tolist()):
        actions, _ = model.predict(given, deterministic=True)
        np.testing.assert_array_equal(actions, expected)
    for row in range(len(obs)):
        for given in (obs[row].astype(np.float64), obs[row].tolist(), obs[row]):
            action, _ = model.predict(given, deterministic=True)
            assert action.shape == expected[row].shape
            np.testing.assert_allclose(action, expected[row], rtol=1e-5, atol=1e-6)  # a batch of one: other rounding
