"""Meta-World stepped through EnvPool (``backend="envpool"``): the package's env contract, Meta-World's experts,
seeding, the goal ranges, and the protocol it records. Tests that step EnvPool skip when it is not installed."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest
from gymnasium import ActionWrapper
from stable_baselines3.common.vec_env import DummyVecEnv

from sb3_mtte.evaluation import evaluate_success
from sb3_mtte.envs import (
    MT10_TASKS,
    EnvPoolVecEnv,
    MetaWorldExpertPolicy,
    check_env_kwargs,
    env_protocol,
    make_env_fns,
    make_mt_env,
    official_env_kwargs,
    reward_function_version,
)
from sb3_mtte.envs.envpool_envs import make_envpool_env_fns, make_envpool_task_env

PAIR = ["reach-v3", "push-v3"]


@pytest.fixture(scope="module")
def envpool():
    return pytest.importorskip("envpool", reason="EnvPool is not installed (pip install 'sb3-mtte[envpool]')")


@pytest.fixture(scope="module")
def mt10(envpool):
    env = make_mt_env("MT10", seed=0, backend="envpool")
    yield env
    env.close()


def expert_success(env, episodes_per_task: int) -> np.ndarray:
    """Each task's success fraction over its first ``episodes_per_task`` episodes of Meta-World's experts, each
    ending at its first success."""
    env.env_method("set_terminate_on_success", True)
    expert = MetaWorldExpertPolicy(env.get_attr("task_name"))
    done_count, success_count = np.zeros(env.num_envs, int), np.zeros(env.num_envs, int)
    obs = env.reset()
    while (done_count < episodes_per_task).any():
        obs, _, dones, infos = env.step(expert.predict(obs)[0])
        for i in np.flatnonzero(dones & (done_count < episodes_per_task)):
            done_count[i] += 1
            success_count[i] += infos[i]["is_success"]
    env.env_method("set_terminate_on_success", False)
    return success_count / episodes_per_task


def test_experts_succeed_through_envpool(mt10):
    rates = expert_success(mt10, 10)
    assert rates.mean() >= 0.95, dict(zip(MT10_TASKS, rates, strict=True))
    assert rates.min() >= 0.7, dict(zip(MT10_TASKS, rates, strict=True))


@pytest.mark.slow
def test_experts_succeed_through_envpool_50_episodes(mt10):
    rates = expert_success(mt10, 50)
    assert rates.mean() >= 0.95, dict(zip(MT10_TASKS, rates, strict=True))


def test_spaces_and_infos_are_those_of_metaworld_envs(envpool):
    native, reference = make_mt_env(PAIR, seed=0, backend="envpool"), make_mt_env(PAIR, seed=0)
    assert isinstance(native, EnvPoolVecEnv) and type(reference) is DummyVecEnv
    assert native.observation_space == reference.observation_space
    assert native.observation_space.dtype == np.float32 and native.observation_space.shape == (41,)
    assert native.action_space == reference.action_space
    assert native.get_attr("task_name") == PAIR and native.get_attr("task_index") == [0, 1]
    obs = native.reset()
    assert obs.dtype == np.float32
    np.testing.assert_array_equal(obs[:, -2:], np.eye(2))
    assert np.all(obs[:, 36:39] != 0.0), "the goal is observed"
    reference.reset()
    actions = np.zeros((2, 4), dtype=np.float32)
    (_, _, _, native_infos), (_, _, _, reference_infos) = native.step(actions), reference.step(actions)
    for native_info, reference_info in zip(native_infos, reference_infos, strict=True):
        assert native_info.keys() == reference_info.keys()
        assert type(native_info["success"]) is float and native_info["is_success"] is False
    native.close()
    reference.close()


def test_truncation_at_500_and_is_success_as_the_wrappers_give_it(envpool):
    env = make_mt_env(["reach-v3"], seed=0, backend="envpool")
    assert env.get_attr("_max_episode_steps") == [500]
    expert, obs, successes = MetaWorldExpertPolicy(["reach-v3"]), env.reset(), []
    for step in range(1, 501):
        obs, _, dones, infos = env.step(expert.predict(obs)[0])
        successes.append(infos[0]["success"])
        assert infos[0]["is_success"] == (max(successes) == 1.0)
        assert dones[0] == (step == 500)
    assert infos[0]["TimeLimit.truncated"] and infos[0]["episode"]["l"] == 500 and infos[0]["is_success"]
    assert infos[0]["terminal_observation"].shape == (40,)
    env.close()


def rollout(env, n_steps: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    rows = [env.reset()]
    for _ in range(n_steps):
        obs, rewards, dones, _ = env.step(rng.uniform(-1, 1, (env.num_envs, 4)).astype(np.float32))
        rows.append(np.column_stack([obs, rewards, dones]))
    return np.concatenate(rows[1:])


def test_the_same_seed_gives_the_same_episodes(envpool):
    envs = [make_mt_env(PAIR, seed=seed, backend="envpool", max_episode_steps=40) for seed in (3, 3, 4)]
    first, again, other = (rollout(env, 90) for env in envs)
    np.testing.assert_array_equal(first, again)
    assert not np.array_equal(first[:, 36:39], other[:, 36:39])
    envs[2].seed(11)
    reseeded = envs[2].reset()
    envs[2].seed(11)
    np.testing.assert_array_equal(envs[2].reset(), reseeded)
    for env in envs:
        env.close()


def test_sending_before_receiving_steps_as_one_after_another(envpool):
    fns = make_envpool_env_fns(PAIR, seed=5, max_episode_steps=30)
    overlapped, sequential = EnvPoolVecEnv(fns), DummyVecEnv(fns)
    np.testing.assert_array_equal(rollout(overlapped, 70), rollout(sequential, 70))
    overlapped.close()
    sequential.close()


class Halve(ActionWrapper):
    def action(self, action):
        return action / 2


def test_a_wrapper_that_changes_the_sent_action_is_refused(envpool):
    env = EnvPoolVecEnv([lambda fn=fn: Halve(fn()) for fn in make_envpool_env_fns(PAIR)])
    env.reset()
    with pytest.raises(RuntimeError, match="changed the action"):
        env.step(np.ones((2, 4), dtype=np.float32))
    env.close()


def test_metaworld_sub_envs_step_in_an_envpool_vec_env_as_in_a_dummy_vec_env():
    envs = [EnvPoolVecEnv(make_env_fns(PAIR, seed=2)), DummyVecEnv(make_env_fns(PAIR, seed=2))]
    np.testing.assert_array_equal(*(rollout(env, 20) for env in envs))
    for env in envs:
        env.close()


def test_drawn_goals_lie_in_the_task_range_and_are_fresh(mt10):
    from metaworld.env_dict import ALL_V3_ENVIRONMENTS

    goals = np.stack([mt10.reset()[:, 36:39] for _ in range(20)], axis=1)  # (task, reset, 3)
    for task_goals, name in zip(goals, MT10_TASKS, strict=True):
        space = ALL_V3_ENVIRONMENTS[name]().goal_space
        assert np.all(task_goals >= space.low - 1e-6) and np.all(task_goals <= space.high + 1e-6), name
        if np.any(space.high > space.low):
            assert len(np.unique(task_goals, axis=0)) == 20, f"{name}: each reset draws a new goal"
    assert mt10.get_attr("goal_index") == [-1] * 10


def test_the_official_evaluation_refuses_envpool_envs(mt10):
    with pytest.raises(ValueError, match="training only"):
        evaluate_success(MetaWorldExpertPolicy(MT10_TASKS), mt10, episodes_per_task=1)


def test_v1_rewards_and_rendering_are_refused_with_envpool():
    kwargs = {"backend": "envpool", "reward_function_version": "v1"}
    for call in (lambda: check_env_kwargs("MT10", kwargs), lambda: make_mt_env(PAIR, **kwargs)):
        with pytest.raises(ValueError, match="'v2' reward functions only"):
            call()
    with pytest.raises(ValueError, match="'v2' reward functions only"):
        reward_function_version("MT10", kwargs)
    with pytest.raises(ValueError, match="'v2' reward functions only"):
        make_envpool_task_env("reach-v3", 0, 1, reward_function_version="v1")
    assert reward_function_version("MT10", {"backend": "envpool"}) == "v2"
    assert reward_function_version("MT10", {"reward_function_version": "v1"}) == "v1"
    with pytest.raises(TypeError, match="render_mode is not an env keyword argument of 'MT10' with backend"):
        check_env_kwargs("MT10", {"backend": "envpool", "render_mode": "rgb_array"})
    with pytest.raises(ValueError, match="is not a backend"):
        make_mt_env(PAIR, backend="mujoco")
    with pytest.raises(ValueError, match="leave it out for 'toy-conflict'"):
        check_env_kwargs("toy-conflict", {"backend": "envpool"})
    check_env_kwargs("MT10", {"backend": "metaworld", "render_mode": "rgb_array"})


def test_a_missing_envpool_names_the_install(monkeypatch):
    for name in [name for name in sys.modules if name.split(".")[0] == "envpool"] + ["envpool"]:
        monkeypatch.setitem(sys.modules, name, None)
    with pytest.raises(ImportError, match=r"sb3-mtte\[envpool\]"):
        make_env_fns(PAIR, backend="envpool")


def test_env_protocol_names_the_three_differences():
    benchmark, native = env_protocol("MT10"), env_protocol("MT10", {"backend": "envpool", "max_episode_steps": 500})
    assert benchmark["benchmark_protocol"] and benchmark["official_evaluation"] and benchmark["differences"] == []
    assert benchmark["reward_functions"] == ["v2", "v1"] and benchmark["label"] == "Meta-World"
    assert not native["benchmark_protocol"] and not native["official_evaluation"]
    assert native["reward_functions"] == ["v2"] and "fresh" in native["goals"]
    assert native["source"].startswith("Meta-World v3.0.0") and len(native["differences"]) == 3
    assert "EnvPool" in native["label"]
    assert json.loads(json.dumps(native)) == native
    assert env_protocol("toy-conflict") is None
    assert official_env_kwargs({"backend": "envpool", "max_episode_steps": 20}) == {"max_episode_steps": 20}
