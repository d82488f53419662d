"""Tests of the multi-task replay buffer: balanced sampling, timeouts, episode tracking, top-K store, pickling."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from conftest import CUDA
from stable_baselines3 import SAC
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.save_util import load_from_pkl, save_to_pkl
from stable_baselines3.common.utils import set_random_seed
from stable_baselines3.common.vec_env import DummyVecEnv

from sb3_mtte.common.buffers import MultiTaskReplayBuffer, MultiTaskReplayBufferSamples

OBS_SPACE = spaces.Box(-np.inf, np.inf, shape=(3,), dtype=np.float32)  # (task, global step, episode index)
ACT_SPACE = spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)


def make_buffer(n_tasks: int, rows_per_task: int, device: str = "cpu", **kwargs) -> MultiTaskReplayBuffer:
    return MultiTaskReplayBuffer(n_tasks * rows_per_task, OBS_SPACE, ACT_SPACE, device=device, n_envs=n_tasks, **kwargs)


def make_stream(episodes: list[list[float]], n_steps: int, truncated: set[int] = frozenset()) -> dict[str, np.ndarray]:
    """One task's per-step rewards, dones, truncations and episode index; padded with an unfinished episode."""
    rewards, dones, truncs, ep_ids = [], [], [], []
    for j, ep in enumerate(episodes):
        rewards += ep
        dones += [False] * (len(ep) - 1) + [True]
        truncs += [False] * (len(ep) - 1) + [j in truncated]
        ep_ids += [j] * len(ep)
    pad = n_steps - len(rewards)
    assert pad > 0
    return {
        "rewards": np.array(rewards + [0.5] * pad, dtype=np.float32),
        "dones": np.array(dones + [False] * pad),
        "truncs": np.array(truncs + [False] * pad),
        "ep_ids": np.array(ep_ids + [len(episodes)] * pad),
    }


def feed(buf: MultiTaskReplayBuffer, streams: list[dict[str, np.ndarray]], t0: int = 0) -> None:
    """Add the streams step by step; obs = (task, t, episode), next_obs = (task, t + 1, episode)."""
    n_tasks = len(streams)
    for t in range(len(streams[0]["rewards"])):
        ep = np.array([s["ep_ids"][t] for s in streams], dtype=np.float32)
        tasks = np.arange(n_tasks, dtype=np.float32)
        obs = np.stack([tasks, np.full(n_tasks, t0 + t, np.float32), ep], axis=1)
        next_obs = obs + np.array([0, 1, 0], dtype=np.float32)
        action = np.stack([tasks / 10, np.full(n_tasks, (t0 + t) / 1000, np.float32)], axis=1)
        reward = np.array([s["rewards"][t] for s in streams], dtype=np.float32)
        done = np.array([s["dones"][t] for s in streams])
        infos = [{"TimeLimit.truncated": True} if s["truncs"][t] else {} for s in streams]
        buf.add(obs, next_obs, action, reward, done, infos)


def constant_streams(n_tasks: int, n_steps: int) -> list[dict[str, np.ndarray]]:
    """Streams without any episode end; reward = 100 * task + step (stored as float32, exact)."""
    return [
        {
            "rewards": (100 * i + np.arange(n_steps)).astype(np.float32),
            "dones": np.zeros(n_steps, bool),
            "truncs": np.zeros(n_steps, bool),
            "ep_ids": np.zeros(n_steps, int),
        }
        for i in range(n_tasks)
    ]


def check_consistent(samples: MultiTaskReplayBufferSamples) -> None:
    """Every row's fields belong to the same stored transition."""
    obs, next_obs = samples.observations.numpy(), samples.next_observations.numpy()
    np.testing.assert_array_equal(next_obs, obs + np.array([0, 1, 0], dtype=np.float32))
    np.testing.assert_allclose(samples.actions.numpy()[..., 0], obs[..., 0] / 10, rtol=1e-6)
    np.testing.assert_allclose(samples.actions.numpy()[..., 1], obs[..., 1] / 1000, rtol=1e-6)


# ---------------------------------------------------------------------------------------------- balanced sampling
def test_constructor_validation():
    with pytest.raises(ValueError):
        make_buffer(3, 10, optimize_memory_usage=True, handle_timeout_termination=False)
    with pytest.raises(ValueError):
        make_buffer(3, 10, top_k=-1)
    assert make_buffer(1, 10).n_envs == 1


@pytest.mark.parametrize("n_steps", [7, 25])  # partly filled, wrapped around twice
def test_balanced_task_major_sampling(n_steps):
    n_tasks, rows, L = 3, 10, 5
    buf = make_buffer(n_tasks, rows)
    feed(buf, constant_streams(n_tasks, n_steps))
    assert buf.full == (n_steps >= rows)

    np.random.seed(0)
    s = buf.sample(L)
    assert isinstance(s, MultiTaskReplayBufferSamples)
    assert s.observations.shape == (n_tasks, L, 3) and s.next_observations.shape == (n_tasks, L, 3)
    assert s.actions.shape == (n_tasks, L, 2)
    assert s.rewards.shape == (n_tasks, L) and s.dones.shape == (n_tasks, L)
    assert s._fields == ("observations", "actions", "next_observations", "dones", "rewards")
    # Task-major: index [i] is task i's mini-batch (the first state entry is the task index).
    np.testing.assert_array_equal(s.observations[..., 0].numpy(), np.repeat(np.arange(n_tasks)[:, None], L, axis=1))
    check_consistent(s)
    np.testing.assert_array_equal(
        s.rewards.numpy(), 100 * s.observations[..., 0].numpy() + s.observations[..., 1].numpy()
    )

    # Reproducible with a seeded numpy RNG (and SB3's set_random_seed).
    np.random.seed(0)
    again = buf.sample(L)
    for a, b in zip(s, again, strict=True):
        assert th.equal(a, b)
    set_random_seed(3)
    a = buf.sample(L)
    set_random_seed(3)
    assert th.equal(a.observations, buf.sample(L).observations)

    # Uniform over exactly the live transitions of each column: the most recent min(n_steps, rows) steps.
    big = buf.sample(2000)
    steps = big.observations[..., 1].numpy()
    live = set(range(max(0, n_steps - rows), n_steps))
    for i in range(n_tasks):
        assert set(steps[i].astype(int)) == live
    assert np.all(big.dones.numpy() == 0)


def test_timeout_handling():
    streams = [
        {"rewards": np.ones(1, np.float32), "dones": np.array([True]), "truncs": np.array([trunc]), "ep_ids": [0]}
        for trunc in (True, False)
    ]
    buf = make_buffer(2, 1)
    feed(buf, streams)
    np.testing.assert_array_equal(buf.dones[0], [1, 1])  # the truncated step is stored as done
    np.testing.assert_array_equal(buf.sample(4).dones.numpy(), [[0] * 4, [1] * 4])
    np.testing.assert_array_equal(buf.episode_returns(0), [1.0])

    no_handling = make_buffer(2, 1, handle_timeout_termination=False)
    feed(no_handling, streams)
    np.testing.assert_array_equal(no_handling.sample(4).dones.numpy(), [[1] * 4] * 2)


# ---------------------------------------------------------------------------------------------- episode tracking
def test_episode_tracking():
    episodes = [
        [[1.0, 2.0, 3.0], [0.5, 0.5], [-1.0, 4.0, 1.0, 1.0]],  # ends at steps 2, 4, 8
        [[10.0] * 5, [1.0, 2.0]],  # ends at steps 4, 6
        [],  # never ends
    ]
    T = 12
    buf = make_buffer(3, 20, top_k=0)
    feed(buf, [make_stream(ep, T) for ep in episodes])
    np.testing.assert_allclose(buf.episode_returns(0), [6.0, 1.0, 5.0])
    np.testing.assert_allclose(buf.episode_returns(1), [50.0, 3.0])
    assert buf.episode_returns(2).size == 0
    np.testing.assert_array_equal(buf.n_episodes, [3, 2, 0])
    # Running episodes: task 0 padded after step 8 (3 steps), task 1 after step 6 (5 steps), task 2 all 12.
    np.testing.assert_array_equal(buf.running_episode_lengths, [3, 5, 12])
    np.testing.assert_allclose(buf.running_episode_returns, [1.5, 2.5, 6.0])
    # K = 0 disables the store; sample_top_k falls back to the main buffer.
    np.testing.assert_array_equal(buf.n_top_k_episodes, [0, 0, 0])
    s = buf.sample_top_k(4)
    np.testing.assert_array_equal(s.observations[..., 0].numpy(), np.repeat([[0], [1], [2]], 4, axis=1))

    bounded = make_buffer(3, 20, max_episode_history=2)
    feed(bounded, [make_stream(ep, T) for ep in episodes])
    np.testing.assert_allclose(bounded.episode_returns(0), [1.0, 5.0])
    np.testing.assert_array_equal(bounded.n_episodes, [3, 2, 0])


def test_episode_break_detection():
    buf = make_buffer(1, 20)
    feed(buf, [make_stream([], 4)])  # running episode, return 2.0
    # The env was reset without a done: the next observation does not continue the stored next_obs.
    feed(buf, [make_stream([[1.0, 2.0]], 3)], t0=100)
    np.testing.assert_allclose(buf.episode_returns(0), [3.0])
    buf.reset_running_episodes()
    np.testing.assert_array_equal(buf.running_episode_lengths, [0])

    no_detection = make_buffer(1, 20, detect_episode_breaks=False)
    feed(no_detection, [make_stream([], 4)])
    feed(no_detection, [make_stream([[1.0, 2.0]], 3)], t0=100)
    np.testing.assert_allclose(no_detection.episode_returns(0), [5.0])


# ---------------------------------------------------------------------------------------------- top-K store
def spread(ret: float, length: int) -> list[float]:
    """An episode of ``length`` integer rewards summing exactly to ``ret``."""
    return [1.0] * (length - 1) + [ret - (length - 1.0)]


TASK0_RETURNS = [3, 1, 4, 1, 5, 9, 2, 6]
TOPK_EPISODES = [
    [spread(r, 2 + j % 3) for j, r in enumerate(TASK0_RETURNS)],  # lengths 2, 3, 4, 2, 3, ...
    [spread(2, 3), spread(2, 2), spread(2, 4), spread(1, 2), spread(2, 3)],  # ties: only the first three 2s
    [],  # no complete episode
]
TOPK_T = 40


def top_k_buffer(rows: int = 50, **kwargs) -> MultiTaskReplayBuffer:
    buf = make_buffer(3, rows, top_k=3, **kwargs)
    feed(buf, [make_stream(ep, TOPK_T, truncated={5}) for ep in TOPK_EPISODES])  # episode 5 (return 9) truncated
    return buf


def test_top_k_store_contents():
    buf = top_k_buffer()
    np.testing.assert_allclose(buf.top_k_returns(0), [9, 6, 5], rtol=1e-6)
    np.testing.assert_allclose(buf.top_k_returns(1), [2, 2, 2], rtol=1e-6)
    assert buf.top_k_returns(2).size == 0
    np.testing.assert_array_equal(buf.n_top_k_episodes, [3, 3, 0])

    ep0 = buf.top_k_episodes(0)
    assert [e["episode_id"] for e in ep0] == [5, 7, 4]
    assert [e["length"] for e in ep0] == [4, 3, 3]
    assert [e["episode_id"] for e in buf.top_k_episodes(1)] == [0, 1, 2]
    np.testing.assert_array_equal(buf.n_top_k_transitions, [10, 9, 0])
    for task in (0, 1):
        for e in buf.top_k_episodes(task):
            obs = e["observations"]
            np.testing.assert_array_equal(obs[:, 0], task)
            np.testing.assert_array_equal(obs[:, 2], e["episode_id"])  # the right episode ...
            np.testing.assert_array_equal(np.diff(obs[:, 1]), 1)  # ... all of it, in order
            np.testing.assert_array_equal(e["next_observations"], obs + np.array([0, 1, 0], np.float32))
            np.testing.assert_allclose(e["rewards"].sum(), e["return"], rtol=1e-6)
            np.testing.assert_array_equal(e["dones"], [0] * (e["length"] - 1) + [1])
            truncated = task == 0 and e["episode_id"] == 5
            np.testing.assert_array_equal(e["timeouts"][-1], float(truncated))


def test_sample_top_k():
    buf = top_k_buffer()
    L = 3000
    np.random.seed(1)
    s = buf.sample_top_k(L)
    assert s.observations.shape == (3, L, 3) and s.rewards.shape == (3, L)
    check_consistent(s)
    obs = s.observations.numpy()
    np.testing.assert_array_equal(obs[..., 0], np.broadcast_to(np.arange(3)[:, None], (3, L)))
    # Only (and all of) the stored transitions of tasks 0 and 1.
    for task in (0, 1):
        stored = {tuple(o) for e in buf.top_k_episodes(task) for o in e["observations"]}
        assert {tuple(o) for o in obs[task]} == stored
    # Task 2 has no complete episode: its whole main-buffer column.
    assert set(obs[2, :, 1].astype(int)) == set(range(TOPK_T))
    # The truncated episode's last step is not a terminal; the others' are.
    dones = s.dones.numpy()
    last_of_ep = {(0, 5): 0.0, (0, 7): 1.0, (0, 4): 1.0}
    for (task, ep), expected in last_of_ep.items():
        e = next(e for e in buf.top_k_episodes(task) if e["episode_id"] == ep)
        rows = np.all(obs[task] == e["observations"][-1], axis=1)
        assert rows.any() and np.all(dones[task][rows] == expected)
    np.random.seed(1)
    assert th.equal(buf.sample_top_k(L).observations, s.observations)


def test_top_k_wrapping_and_too_small_buffer():
    # 6 rows per task: episodes of up to 4 steps fit, some of them across the ring's end.
    buf = top_k_buffer(rows=6)
    np.testing.assert_allclose(buf.top_k_returns(0), [9, 6, 5], rtol=1e-6)
    for e in buf.top_k_episodes(0):
        np.testing.assert_array_equal(e["observations"][:, 2], e["episode_id"])
        np.testing.assert_array_equal(np.diff(e["observations"][:, 1]), 1)
    # 3 rows per task: the 4-step episode with return 9 was overwritten before it ended and is skipped.
    with pytest.warns(UserWarning, match="skipped"):
        small = top_k_buffer(rows=3)
    np.testing.assert_allclose(small.top_k_returns(0), [6, 5, 3], rtol=1e-6)  # 4 is a 4-step episode too
    np.testing.assert_array_equal(small.n_top_k_skipped, [2, 1, 0])  # task 1: its 4-step episode
    np.testing.assert_allclose(small.episode_returns(0), TASK0_RETURNS, rtol=1e-6)


def test_pickle_round_trip(tmp_path):
    buf = top_k_buffer()
    path = tmp_path / "buffer.pkl"
    save_to_pkl(path, buf)
    loaded = load_from_pkl(path)
    assert isinstance(loaded, MultiTaskReplayBuffer)
    assert (loaded.pos, loaded.full, loaded.top_k) == (buf.pos, buf.full, buf.top_k)
    for name in ("observations", "next_observations", "actions", "rewards", "dones", "timeouts"):
        np.testing.assert_array_equal(getattr(loaded, name), getattr(buf, name))
    for attr in ("n_episodes", "n_top_k_episodes", "n_top_k_transitions", "n_top_k_skipped"):
        np.testing.assert_array_equal(getattr(loaded, attr), getattr(buf, attr))
    np.testing.assert_array_equal(loaded.running_episode_returns, buf.running_episode_returns)
    np.testing.assert_array_equal(loaded.running_episode_lengths, buf.running_episode_lengths)
    for task in range(3):
        np.testing.assert_array_equal(loaded.episode_returns(task), buf.episode_returns(task))
        np.testing.assert_array_equal(loaded.top_k_returns(task), buf.top_k_returns(task))
        for a, b in zip(loaded.top_k_episodes(task), buf.top_k_episodes(task), strict=True):
            assert a.keys() == b.keys()
            for key in a:
                np.testing.assert_array_equal(a[key], b[key])

    for method in ("sample", "sample_top_k"):
        np.random.seed(7)
        x = getattr(buf, method)(16)
        np.random.seed(7)
        y = getattr(loaded, method)(16)
        for a, b in zip(x, y, strict=True):
            assert th.equal(a, b)

    # Both go on identically: more episodes for task 2 (return 20 enters its store).
    more = [make_stream([[1.0]], 3), make_stream([[2.0] * 4], 6), make_stream([[20.0]], 2)]
    for b in (buf, loaded):
        feed(b, [{k: v[:2] for k, v in s.items()} for s in more], t0=TOPK_T)
    np.testing.assert_allclose(loaded.top_k_returns(2), [40.0])  # 40 running steps at 0.5, then 20
    np.testing.assert_array_equal(loaded.top_k_returns(2), buf.top_k_returns(2))
    np.testing.assert_array_equal(loaded.n_episodes, buf.n_episodes)


# ---------------------------------------------------------------------------------------------- built by SB3
def test_built_by_sb3_sac():
    """SB3 builds and fills the buffer (its ``train`` expects flat batches, so no update runs here)."""
    n_tasks, ep_len, n_vec_steps = 3, 50, 200
    env = DummyVecEnv([lambda: Monitor(gym.make("Pendulum-v1", max_episode_steps=ep_len)) for _ in range(n_tasks)])
    model = SAC(
        "MlpPolicy",
        env,
        replay_buffer_class=MultiTaskReplayBuffer,
        replay_buffer_kwargs={"top_k": 2},
        batch_size=8,
        learning_starts=n_tasks * n_vec_steps,
        policy_kwargs={"net_arch": [16, 16]},
        seed=0,
        device="cpu",
    )
    model.learn(total_timesteps=n_tasks * n_vec_steps)
    buf = model.replay_buffer
    assert isinstance(buf, MultiTaskReplayBuffer) and buf.n_envs == n_tasks
    n_eps = n_vec_steps // ep_len
    np.testing.assert_array_equal(buf.n_episodes, [n_eps] * n_tasks)
    np.testing.assert_array_equal(buf.n_top_k_episodes, [2] * n_tasks)
    np.testing.assert_array_equal(buf.n_top_k_transitions, [2 * ep_len] * n_tasks)
    # The buffer's returns are the ones Monitor saw.
    ours = np.sort(np.concatenate([buf.episode_returns(i) for i in range(n_tasks)]))
    monitor = np.sort([info["r"] for info in model.ep_info_buffer])
    np.testing.assert_allclose(ours, monitor, rtol=1e-4)
    for i in range(n_tasks):
        np.testing.assert_allclose(buf.top_k_returns(i), np.sort(buf.episode_returns(i))[::-1][:2])
        for e in buf.top_k_episodes(i):
            assert e["timeouts"][-1] == 1 and e["timeouts"][:-1].sum() == 0  # truncated at the time limit
            np.testing.assert_allclose(e["rewards"].sum(), e["return"], rtol=1e-5)
    s = buf.sample(8)
    assert s.observations.shape == (n_tasks, 8, 3)
    assert buf.sample_top_k(8).rewards.shape == (n_tasks, 8)


# ---------------------------------------------------------------------------------------------- storage
def fed_alike(storage: str, device: str = "cpu") -> tuple[MultiTaskReplayBuffer, MultiTaskReplayBuffer]:
    """A host buffer and one with ``storage`` on ``device``, both fed the same transitions from the start: 50 rows
    per task, 110 steps, so both wrap."""
    host, other = top_k_buffer(), top_k_buffer(storage=storage, device=device)
    for buf in (host, other):
        feed(buf, constant_streams(3, 70), t0=TOPK_T)
    return host, other


def assert_samples_the_host_batches(buf: MultiTaskReplayBuffer, host: MultiTaskReplayBuffer, device: str) -> None:
    """Under the same numpy seed, ``buf`` draws the host's batches, bit for bit, on ``device``."""
    for method in ("sample", "sample_top_k"):
        np.random.seed(3)
        expected = getattr(host, method)(16)
        np.random.seed(3)
        for a, b in zip(getattr(buf, method)(16), expected, strict=True):
            assert a.device.type == device and a.dtype == b.dtype and th.equal(a.cpu(), b)


@pytest.mark.parametrize("storage", ["device", "pinned", "host"])
def test_every_storage_samples_the_host_batches_and_pickles_its_arrays(tmp_path, storage):
    """A copy on the device (here the CPU) is written row by row, gathered by the same numpy draw, made again from
    the arrays after a load, and never pickled; every storage gives the host's batches bit for bit, wrapping
    included."""
    host, other = fed_alike(storage)
    assert (other._device_copy is not None) == (storage == "device")
    save_to_pkl(tmp_path / "buffer.pkl", other)
    loaded = load_from_pkl(tmp_path / "buffer.pkl")
    assert loaded._device_copy is None and loaded.storage == storage
    for buf in (other, loaded):
        assert_samples_the_host_batches(buf, host, "cpu")
    if storage == "device":
        assert all(
            th.equal(loaded._device_copy.tensors[k], th.as_tensor(getattr(host, k))) for k in ("rewards", "dones")
        )


def test_auto_storage_is_the_host_on_a_cpu_and_an_unknown_storage_is_refused():
    buf = top_k_buffer(storage="auto")
    feed(buf, constant_streams(3, 2))
    assert buf._resolved_storage == "host" and buf._device_copy is None
    with pytest.raises(ValueError, match="storage must be one of"):
        top_k_buffer(storage="gpu")


@CUDA
@pytest.mark.parametrize("storage", ["device", "pinned"])
def test_cuda_storages_sample_the_host_batches(storage):
    host, other = fed_alike(storage, device="cuda")
    assert (other._device_copy is not None) == (storage == "device")
    assert_samples_the_host_batches(other, host, "cuda")
