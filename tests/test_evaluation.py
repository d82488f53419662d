"""Tests of the success-rate evaluation and its callback, against scripted controllers."""

from __future__ import annotations

import json

import numpy as np
import pytest
from stable_baselines3 import SAC
from stable_baselines3.common.logger import KVWriter, Logger

from sb3_mtte.evaluation import MultiTaskEvalCallback, SuccessResult, evaluate_success
from sb3_mtte.common.utils import task_log_key
from sb3_mtte.envs import MT10_TASKS, MetaWorldExpertPolicy, ToyOraclePolicy, get_task_names, make_mt_env


class DoNothing:
    """Zero actions: the toy point stays near the origin, far from every goal."""

    def predict(self, observation, state=None, episode_start=None, deterministic=True):
        return np.zeros((len(observation), 2), dtype=np.float32), None


class EveryOtherEpisode:
    """The oracle on even-numbered episodes of each sub-env, zero actions on odd ones (tracks episode_start)."""

    def __init__(self, oracle: ToyOraclePolicy, env) -> None:
        self.oracle = oracle
        self.env = env
        self.episode = None
        self.goals_seen: list[list[int]] = []

    def predict(self, observation, state=None, episode_start=None, deterministic=True):
        if self.episode is None:
            self.episode = np.full(len(observation), -1)
        self.episode += episode_start
        if episode_start.any():
            goals = self.env.get_attr("goal_index")
            self.goals_seen.append([g if s else -1 for g, s in zip(goals, episode_start, strict=True)])
        actions, _ = self.oracle.predict(observation)
        actions[self.episode % 2 == 1] = 0.0
        return actions, None


class Capture(KVWriter):
    """Logger output that keeps every dumped key/value dict."""

    def __init__(self) -> None:
        self.dumps: list[dict] = []

    def write(self, key_values, key_excluded, step=0):
        self.dumps.append(dict(key_values))

    def close(self):
        pass


@pytest.fixture(scope="module")
def mt10():
    env = make_mt_env("MT10", seed=0)
    yield env
    env.close()


def test_metaworld_experts_succeed(mt10):
    result = evaluate_success(MetaWorldExpertPolicy(get_task_names(mt10)), mt10, episodes_per_task=10)
    assert result.task_names == MT10_TASKS
    assert result.success_rate.shape == (10,)
    assert result.mean >= 0.95, result.as_dict()
    assert result.success_rate.min() >= 0.7, result.as_dict()
    assert mt10.get_attr("eval_mode") == [False] * 10
    assert mt10.get_attr("terminate_on_success") == [False] * 10


@pytest.mark.slow
def test_metaworld_experts_full_protocol(mt10):
    result = evaluate_success(MetaWorldExpertPolicy(MT10_TASKS), mt10, episodes_per_task=50)
    assert result.mean >= 0.95, result.as_dict()


def test_oracle_and_do_nothing_on_toy():
    env = make_mt_env("toy-conflict", n_tasks=4, seed=0)
    perfect = evaluate_success(ToyOraclePolicy("toy-conflict", 4), env, episodes_per_task=50)
    assert perfect.success_rate.shape == (4,)
    np.testing.assert_array_equal(perfect.success_rate, 1.0)
    assert perfect.mean == 1.0 and perfect.task_names == ["agree-0", "agree-1", "agree-2", "conflict"]
    idle = evaluate_success(DoNothing(), env, episodes_per_task=5)
    np.testing.assert_array_equal(idle.success_rate, 0.0)
    assert idle.mean == 0.0
    as_dict = json.loads(json.dumps(perfect.as_dict()))
    assert as_dict == {"mean": 1.0, "per_task": {"agree-0": 1.0, "agree-1": 1.0, "agree-2": 1.0, "conflict": 1.0}}


def test_episode_counting_follows_goal_cycle():
    env = make_mt_env("toy-agree", n_tasks=3, seed=0)
    policy = EveryOtherEpisode(ToyOraclePolicy("toy-agree", 3), env)
    result = evaluate_success(policy, env, episodes_per_task=10, terminate_on_success=False)
    np.testing.assert_allclose(result.success_rate, 0.5)
    # every sub-env starts its episodes on goal variations 0, 1, 2, ... (episodes run in lock-step here)
    starts = np.array(policy.goals_seen)[:10]
    np.testing.assert_array_equal(starts, np.repeat(np.arange(10)[:, None], 3, axis=1))


def test_benchmark_spec_and_bad_episode_count():
    first = evaluate_success(DoNothing(), "toy-conflict-3", episodes_per_task=2, seed=5)
    assert isinstance(first, SuccessResult) and first.success_rate.shape == (3,)
    with pytest.raises(ValueError):
        evaluate_success(DoNothing(), "toy-conflict", episodes_per_task=0)


def test_a_model_of_another_benchmark_is_refused_with_the_fix():
    """A model trained on 3 toy tasks (observations of 4 + 3 numbers) is not run on 4 tasks."""
    model = SAC("MlpPolicy", make_mt_env("toy-conflict-3", seed=0), learning_starts=0)
    with pytest.raises(ValueError, match=r"shape \(7,\), this env gives \(8,\) \(4 tasks\): evaluate it on the bench"):
        evaluate_success(model, "toy-conflict-4", episodes_per_task=1)


def test_callback_logs_and_saves(tmp_path):
    env = make_mt_env("toy-conflict", n_tasks=4, seed=0)
    capture = Capture()
    model = SAC("MlpPolicy", env, policy_kwargs=dict(net_arch=[16, 16]), learning_starts=40, batch_size=32, seed=0)
    model.set_logger(Logger(folder=None, output_formats=[capture]))
    callback = MultiTaskEvalCallback(
        make_mt_env("toy-conflict", n_tasks=4, seed=1), eval_freq=25, episodes_per_task=2, log_path=tmp_path
    )
    model.learn(total_timesteps=200, callback=callback)  # 50 vector steps -> 2 evaluations
    names = ["agree-0", "agree-1", "agree-2", "conflict"]
    eval_dumps = [d for d in capture.dumps if "eval/success_rate" in d]
    assert len(eval_dumps) == 2
    for i, name in enumerate(names):
        assert task_log_key("eval/success", i, name) in eval_dumps[0]
    saved = np.load(tmp_path / "evaluations.npz")
    np.testing.assert_array_equal(saved["timesteps"], [100, 200])
    assert saved["success_rate"].shape == (2, 4)
    assert list(saved["task_names"]) == names
    assert callback.last_result is not None and callback.last_result.success_rate.shape == (4,)


class _ZeroActions:
    """A predictor that always acts 0."""

    def predict(self, obs, state=None, episode_start=None, deterministic=True):
        return np.zeros((len(obs), 1), dtype=np.float32), state


def test_tasks_of_one_name_keep_their_keys_and_a_missing_success_flag_is_said_once():
    import gymnasium as gym
    from stable_baselines3.common.vec_env import DummyVecEnv

    from sb3_mtte.envs.wrappers import OneHotTaskWrapper

    gravities = (9.8, 5.0)
    env = DummyVecEnv(
        [lambda i=i, g=g: OneHotTaskWrapper(gym.make("Pendulum-v1", g=g), i, 2) for i, g in enumerate(gravities)]
    )
    with pytest.warns(UserWarning) as warned:
        result = evaluate_success(_ZeroActions(), env, episodes_per_task=2)
    said = [str(w.message) for w in warned if "is_success" in str(w.message)]
    assert said == [
        "Tasks 0, 1 report no is_success at the end of their episodes: their success counts as 0. Wrap such an env "
        "so that its info holds is_success (OneHotTaskWrapper's success_key names the info key)."
    ]
    assert list(result.as_dict()["per_task"]) == ["Pendulum-v1 (task 0)", "Pendulum-v1 (task 1)"]
    env.close()
