"""Tests of the multi-task envs: Meta-World layout, seeding, truncation, goal sampling, and the toy benchmarks."""

from __future__ import annotations

import time

import numpy as np
import pytest
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

from sb3_mtte.envs import (
    MT10_TASKS,
    MT20_TASKS,
    MT50_TASKS,
    TOY_BENCHMARKS,
    get_task_names,
    make_env_fns,
    make_mt_env,
)
from sb3_mtte.envs.toy import GOAL_DISTANCE, SUCCESS_RADIUS, parse_toy_name

PAIR = ["reach-v3", "push-v3"]

MT20_FROM_DESIGN = [
    "assembly", "basketball", "bin-picking", "box-close", "button-press-topdown", "button-press-topdown-wall",
    "button-press", "button-press-wall", "coffee-button", "coffee-pull", "coffee-push", "dial-turn",
    "disassemble", "door-close", "door-lock", "door-open", "door-unlock", "hand-insert", "drawer-close",
    "drawer-open",
]  # fmt: skip


@pytest.fixture(scope="module")
def mt10():
    env = make_mt_env("MT10", seed=0)
    yield env
    env.close()


def _rollout(env, n_steps: int, action_seed: int = 0) -> np.ndarray:
    """Observations of ``n_steps`` vector steps of seeded random actions, after a reset."""
    rng = np.random.default_rng(action_seed)
    low, high = env.action_space.low, env.action_space.high
    observations = [env.reset()]
    for _ in range(n_steps):
        obs, _, _, _ = env.step(rng.uniform(low, high, size=(env.num_envs, *low.shape)).astype(np.float32))
        observations.append(obs)
    return np.stack(observations)


# ----- Meta-World -----


def test_task_lists_match_metaworld():
    from metaworld.env_dict import ALL_V3_ENVIRONMENTS, MT10_V3

    assert MT10_TASKS == list(MT10_V3)
    assert MT50_TASKS == list(ALL_V3_ENVIRONMENTS)
    assert MT20_TASKS == MT50_TASKS[:20] == [f"{name}-v3" for name in MT20_FROM_DESIGN]
    assert "window-close-v3" in MT10_TASKS


def test_mt10_layout(mt10):
    assert mt10.num_envs == 10
    assert get_task_names(mt10) == MT10_TASKS
    assert mt10.get_attr("task_index") == list(range(10))
    space = mt10.observation_space
    assert space.shape == (49,) and space.dtype == np.float32
    np.testing.assert_array_equal(space.low[39:], 0.0)
    np.testing.assert_array_equal(space.high[39:], 1.0)
    obs = mt10.reset()
    assert obs.shape == (10, 49) and obs.dtype == np.float32
    np.testing.assert_array_equal(obs[:, 39:], np.eye(10, dtype=np.float32))
    assert all(space.contains(row) for row in obs)
    assert all(sub_space == mt10.get_attr("observation_space")[0] for sub_space in mt10.get_attr("observation_space"))
    assert np.abs(obs[:, 36:39]).sum(axis=1).min() > 0  # the goal is observed


def test_mt10_infos_and_truncation_at_500(mt10):
    mt10.reset()
    rng = np.random.default_rng(0)
    for t in range(1, 501):
        obs, _rewards, dones, infos = mt10.step(rng.uniform(-1, 1, size=(10, 4)).astype(np.float32))
        assert [info["task_index"] for info in infos] == list(range(10))
        assert all(isinstance(info["is_success"], bool) for info in infos)
        if t < 500:
            assert not dones.any(), f"episode ended early at step {t}"
    assert dones.all()
    for info in infos:
        assert info["TimeLimit.truncated"] is True  # truncated and not terminated
        assert info["terminal_observation"].shape == (49,)
        assert info["episode"]["l"] == 500
    np.testing.assert_array_equal(obs[:, 39:], np.eye(10, dtype=np.float32))


def test_gym_level_truncation_and_success_flag():
    env = make_env_fns(PAIR, seed=0, max_episode_steps=20)[0]()
    obs, info = env.reset()
    assert obs.shape == (41,) and info["task_index"] == 0
    for t in range(1, 21):
        obs, _reward, terminated, truncated, info = env.step(env.action_space.sample())
        assert terminated is False
        assert truncated is (t == 20)
    assert env.get_wrapper_attr("task_name") == "reach-v3"
    env.close()


def test_same_seed_same_episodes_and_new_goals():
    first = make_mt_env(PAIR, seed=3, max_episode_steps=10)
    second = make_mt_env(PAIR, seed=3, max_episode_steps=10)
    other = make_mt_env(PAIR, seed=4, max_episode_steps=10)
    run_a, run_b, run_c = (_rollout(env, 60) for env in (first, second, other))
    np.testing.assert_array_equal(run_a, run_b)
    assert not np.array_equal(run_a, run_c)
    # a new goal variation at every reset: episode starts are at steps 0, 10, 20, ...
    goals = run_a[::10, :, 36:39]
    for task in range(2):
        assert len(np.unique(goals[:, task], axis=0)) >= 5
    for env in (first, second, other):
        env.close()


def test_eval_mode_cycles_goal_variations():
    env = make_mt_env(PAIR, seed=0, max_episode_steps=5)
    env.env_method("set_eval_mode", True)
    env.reset()
    seen = [env.get_attr("goal_index")]
    for _ in range(3 * 5):
        _, _, dones, _ = env.step(np.zeros((2, 4), dtype=np.float32))
        if dones.any():
            seen.append(env.get_attr("goal_index"))
    assert seen == [[k, k] for k in range(4)]
    env.env_method("set_eval_mode", False)
    assert env.get_attr("eval_mode") == [False, False]
    env.close()


def test_unknown_names_raise():
    with pytest.raises(ValueError, match="MT10"):
        make_mt_env("MT11")
    with pytest.raises(ValueError, match=r"Unknown Meta-World v3 env name 'not-a-task-v3' \(nearest: "):
        make_mt_env(["reach-v3", "not-a-task-v3"])
    with pytest.raises(ValueError, match="distinct"):
        make_mt_env(["reach-v3", "reach-v3"])
    with pytest.raises(ValueError):
        make_mt_env("toy-conflict", n_tasks=1)
    with pytest.raises(ValueError, match="n_tasks"):
        make_mt_env("toy-conflict-3", n_tasks=5)
    with pytest.raises(ValueError, match="n_tasks"):
        make_mt_env("MT10", n_tasks=5)
    with pytest.raises(TypeError):
        make_mt_env(PAIR, not_an_option=1)


def test_layout_mismatch_is_reported():
    def drop_last(env_fns):
        return DummyVecEnv(env_fns[:-1])

    with pytest.raises(ValueError, match=r"one-hot|sub-env"):
        make_mt_env("toy-conflict", vec_env_cls=drop_last)


# ----- toy benchmarks -----


def test_toy_names():
    assert set(TOY_BENCHMARKS) == {"toy-conflict", "toy-agree"}
    assert parse_toy_name("toy-conflict") == ("toy-conflict", 4)
    assert parse_toy_name("ToyConflict-6") == ("toy-conflict", 6)
    assert parse_toy_name("toy-agree", n_tasks=3) == ("toy-agree", 3)
    assert parse_toy_name("MT10") is None
    assert make_mt_env("toy-conflict-6").num_envs == 6


def test_toy_layout_infos_and_truncation():
    env = make_mt_env("toy-conflict", n_tasks=4, seed=0)
    assert get_task_names(env) == ["agree-0", "agree-1", "agree-2", "conflict"]
    assert env.observation_space.shape == (8,) and env.observation_space.dtype == np.float32
    obs = env.reset()
    np.testing.assert_array_equal(obs[:, 4:], np.eye(4, dtype=np.float32))
    for t in range(1, 51):
        obs, _, dones, infos = env.step(np.zeros((4, 2), dtype=np.float32))
        assert [info["task_index"] for info in infos] == [0, 1, 2, 3]
        assert dones.all() == (t == 50) and dones.any() == (t == 50)
    assert all(info["TimeLimit.truncated"] and info["is_success"] is False for info in infos)


def test_toy_conflict_geometry():
    for n_tasks in (2, 4, 10):
        _, centers = TOY_BENCHMARKS["toy-conflict"](n_tasks)
        assert centers.shape == (n_tasks, 2)
        assert (centers[:-1, 0] > 0.5).all(), "the agreeing tasks' goals lie on the +x side"
        assert centers[-1, 0] < -0.5 and abs(centers[-1, 1]) < 1e-9, "the last task's goal lies at -x"
        np.testing.assert_allclose(np.linalg.norm(centers, axis=1), GOAL_DISTANCE)
    _, agree = TOY_BENCHMARKS["toy-agree"](4)
    assert (agree[:, 0] > 0.5).all()


def test_toy_seeding_and_goal_variations():
    run_a = _rollout(make_mt_env("toy-conflict", seed=1, max_episode_steps=5), 40)
    run_b = _rollout(make_mt_env("toy-conflict", seed=1, max_episode_steps=5), 40)
    run_c = _rollout(make_mt_env("toy-conflict", seed=2, max_episode_steps=5), 40)
    np.testing.assert_array_equal(run_a, run_b)
    assert not np.array_equal(run_a, run_c)
    env = make_mt_env("toy-agree", seed=0, max_episode_steps=2)
    env.reset()
    goal_indices = []
    for _ in range(20):
        _, _, dones, _ = env.step(np.zeros((4, 2), dtype=np.float32))
        if dones.any():
            goal_indices.append(env.get_attr("goal_index"))
    assert len({g[0] for g in goal_indices}) >= 5


def test_toy_success_reaching_goal():
    env = make_env_fns("toy-conflict", n_tasks=2)[1]()  # the conflicting task: goal at -x
    obs, _ = env.reset()
    goal = env.unwrapped.goal
    assert goal[0] < 0
    for _ in range(10):
        obs, reward, _, _, info = env.step(np.clip((goal - obs[:2]) / 0.1, -1, 1).astype(np.float32))
    assert info["is_success"] and info["distance"] <= SUCCESS_RADIUS and reward > 0
    for _ in range(3):
        obs, reward, _, _, info = env.step(np.array([1.0, 0.0], dtype=np.float32))
    assert info["is_success"] and info["distance"] > SUCCESS_RADIUS, "success is kept for the whole episode"


def test_toy_speed():
    env = make_mt_env("toy-conflict", n_tasks=4)
    env.reset()
    actions = np.random.default_rng(0).uniform(-1, 1, size=(1000, 4, 2)).astype(np.float32)
    start = time.process_time()  # this process's CPU time: other work on the machine does not count
    for action in actions:
        env.step(action)
    steps_per_s = actions.shape[0] * 4 / (time.process_time() - start)
    assert steps_per_s > 2000, f"{steps_per_s:.0f} env steps/s"


def test_toy_subproc_vec_env():
    env = make_mt_env("toy-agree", n_tasks=2, vec_env_cls=SubprocVecEnv)
    try:
        assert get_task_names(env) == ["agree-0", "agree-1"]
        obs, _, _, infos = env.step(np.zeros((2, 2), dtype=np.float32))
        np.testing.assert_array_equal(obs[:, 4:], np.eye(2, dtype=np.float32))
        assert [info["task_index"] for info in infos] == [0, 1]
    finally:
        env.close()


def test_one_hot_task_wrapper_is_importable_from_the_package():
    """The README's `OneHotTaskWrapper(gym.make("Pendulum-v1"))`, imported from sb3_mtte: state followed by [1.0]."""
    import gymnasium as gym

    from sb3_mtte import OneHotTaskWrapper

    obs, _ = OneHotTaskWrapper(gym.make("Pendulum-v1")).reset(seed=0)
    assert obs.shape == (4,) and obs[-1] == 1.0
