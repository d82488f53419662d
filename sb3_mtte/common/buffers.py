"""Multi-task replay buffer: balanced task-major sampling, episode-return tracking and a top-K episode store.

The VecEnv holds one sub-env per task (sub-env i is task i), so SB3's ``ReplayBuffer`` built with
``n_envs = N`` already stores ``(buffer_size // N, N, ...)`` arrays whose column i is task i. This buffer
keeps that layout and changes three things:

* :meth:`MultiTaskReplayBuffer.sample` draws ``L = batch_size`` transitions *per task* and returns them
  task-major, as ``(N, L, ...)`` tensors whose index ``[i]`` is task i's mini-batch.
* :meth:`MultiTaskReplayBuffer.add` tracks the undiscounted return of every episode of every task.
* Per task, the K highest-return complete episodes are copied into a side store that
  :meth:`MultiTaskReplayBuffer.sample_top_k` samples from (top-K replay). The store lives in the buffer
  object, so SB3's ``save_replay_buffer`` / ``load_replay_buffer`` keep it.

On a GPU the main buffer's transitions also live on the device (``storage``, :mod:`sb3_mtte.common.device_storage`),
where batches are gathered.
"""

from __future__ import annotations

import warnings
from collections import deque
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.vec_env import VecNormalize

from sb3_mtte.common.device_storage import DeviceStorage, check_storage, resolve_storage, to_device

# Per-transition arrays of the main buffer that the top-K store copies, in this order.
_FIELDS = ("observations", "next_observations", "actions", "rewards", "dones", "timeouts")


class MultiTaskReplayBufferSamples(NamedTuple):
    """A task-major batch: index ``[i]`` of every field is task i's L transitions.

    :param observations: ``(N, L, obs_dim)``
    :param actions: ``(N, L, action_dim)``
    :param next_observations: ``(N, L, obs_dim)``
    :param dones: ``(N, L)``, 1 at a termination (a time-limit truncation is not one when timeouts are handled)
    :param rewards: ``(N, L)``
    """

    observations: th.Tensor
    actions: th.Tensor
    next_observations: th.Tensor
    dones: th.Tensor
    rewards: th.Tensor


@dataclass
class TopKStore:
    """The stored top-K episodes of one task, laid out flat.

    ``data[name]`` holds the transitions of every stored episode back to back (episode ``j`` occupies
    the ``lengths[j]`` rows after ``lengths[:j].sum()``); episodes are kept in insertion order, not
    sorted by return.

    :param data: flat transition arrays keyed by the main buffer's field names
    :param returns: undiscounted return of each stored episode
    :param lengths: number of transitions of each stored episode
    :param episode_ids: index of each stored episode among the task's completed episodes (0 = first)
    """

    data: dict[str, np.ndarray]
    returns: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.float64))
    lengths: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    episode_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    @property
    def n_transitions(self) -> int:
        """Total number of stored transitions."""
        return int(self.lengths.sum())


class MultiTaskReplayBuffer(ReplayBuffer):
    """Replay buffer for N tasks with balanced task-major sampling and a per-task top-K episode store.

    Build it with ``n_envs`` equal to the number of tasks, sub-env i being task i (SB3 does this when it
    is passed as ``replay_buffer_class``; SB3's own ``train`` methods expect flat batches, so train with
    :class:`~sb3_mtte.MTSAC` or :class:`~sb3_mtte.MTSACTE`). ``buffer_size`` is the total over tasks, as in SB3:
    each task gets ``buffer_size // n_envs`` rows.

    Top-K store: when an episode of task i ends (termination or truncation, a truncated episode counts as
    complete) and its return is strictly greater than the worst stored return of that task (or fewer than
    K are stored), its transitions are copied out of the main buffer into the store and the worst stored
    episode is dropped (the oldest one among equal worst returns). The copy needs the whole episode to be
    still in the main buffer, i.e. ``episode length <= buffer_size // n_envs``; a longer qualifying
    episode is skipped with a warning and counted in ``n_top_k_skipped``.

    Episode tracking assumes consecutive calls to :meth:`add` continue each sub-env's episode. When a
    column's observation differs from the previous step's stored next observation although that step was
    not ``done`` (the env was reset outside of an episode end, e.g. by ``learn(reset_num_timesteps=True)``
    after loading), the running episode of that column is discarded and a new one starts
    (``detect_episode_breaks``).

    :param buffer_size: maximum number of transitions, over all tasks
    :param observation_space: observation space
    :param action_space: action space
    :param device: PyTorch device of the sampled tensors
    :param n_envs: number of tasks (= sub-envs of the VecEnv); 1 is allowed
    :param optimize_memory_usage: not supported, must be False
    :param handle_timeout_termination: a time-limit truncation is not a terminal when sampling
        (``done * (1 - timeout)``), as in SB3
    :param top_k: number K of best episodes kept per task; 0 disables the store
    :param max_episode_history: completed-episode returns kept per task for :meth:`episode_returns`
        (None keeps all); ``n_episodes`` always counts all
    :param detect_episode_breaks: discard a running episode when a column's observations are not
        continuous (see above)
    :param storage: where batches are gathered: ``"host"`` (numpy, as SB3), ``"device"`` (a copy of the transitions
        on ``device``), ``"pinned"`` (gathered on the host into page-locked memory, copied without waiting) or
        ``"auto"``: the device when a CUDA device holds the buffer in half its free memory, else pinned; the host
        on a CPU. The numpy arrays stay what ``save_replay_buffer`` writes; the numbers are the same for every one.
    """

    def __init__(
        self,
        buffer_size: int,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        device: th.device | str = "auto",
        n_envs: int = 1,
        optimize_memory_usage: bool = False,
        handle_timeout_termination: bool = True,
        top_k: int = 0,
        max_episode_history: int | None = None,
        detect_episode_breaks: bool = True,
        storage: str = "auto",
    ):
        if optimize_memory_usage:
            raise ValueError("MultiTaskReplayBuffer does not support optimize_memory_usage=True")
        if top_k < 0:
            raise ValueError(f"top_k must be >= 0, got {top_k}")
        super().__init__(
            buffer_size,
            observation_space,
            action_space,
            device=device,
            n_envs=n_envs,
            optimize_memory_usage=False,
            handle_timeout_termination=handle_timeout_termination,
        )
        self.top_k = top_k
        self.detect_episode_breaks = detect_episode_breaks
        check_storage(storage)
        self.storage = storage
        self._resolved_storage: str | None = None
        self._device_copy: DeviceStorage | None = None
        # Running episode of each task.
        self._ep_return = np.zeros(self.n_envs, dtype=np.float64)
        self._ep_len = np.zeros(self.n_envs, dtype=np.int64)
        # Completed episodes.
        self.n_episodes = np.zeros(self.n_envs, dtype=np.int64)
        self._episode_returns: list[deque[float]] = [deque(maxlen=max_episode_history) for _ in range(self.n_envs)]
        # Top-K store.
        self.n_top_k_skipped = np.zeros(self.n_envs, dtype=np.int64)
        self._top_k: list[TopKStore] = [
            TopKStore({name: getattr(self, name)[:0, 0].copy() for name in _FIELDS}) for _ in range(self.n_envs)
        ]

    # ------------------------------------------------------------------ adding and episode tracking
    def add(
        self,
        obs: np.ndarray,
        next_obs: np.ndarray,
        action: np.ndarray,
        reward: np.ndarray,
        done: np.ndarray,
        infos: list[dict[str, Any]],
    ) -> None:
        """Store one transition per task (leading dim ``n_envs``) and update the episode bookkeeping.

        :param obs: observations
        :param next_obs: next observations (the terminal observation where ``done``)
        :param action: actions
        :param reward: rewards
        :param done: True at termination or truncation
        :param infos: per-task infos; ``"TimeLimit.truncated"`` marks a truncation
        """
        row = self.pos
        if self.detect_episode_breaks and (self.pos > 0 or self.full):
            prev = (row - 1) % self.buffer_size
            stored = self.next_observations[prev].reshape(self.n_envs, -1)
            now = np.asarray(obs).astype(stored.dtype, copy=False).reshape(self.n_envs, -1)
            broken = (self.dones[prev] == 0) & np.any(now != stored, axis=1)
            self._ep_return[broken] = 0.0
            self._ep_len[broken] = 0
        super().add(obs, next_obs, action, reward, done, infos)
        device_copy = self._on_device()
        if device_copy is not None:
            device_copy.write(row, {name: getattr(self, name) for name in _FIELDS})
        self._ep_return += np.asarray(reward, dtype=np.float64).reshape(self.n_envs)
        self._ep_len += 1
        for task in np.flatnonzero(np.asarray(done).reshape(self.n_envs)):
            self._end_episode(int(task), row)

    def _end_episode(self, task: int, end_row: int) -> None:
        """Record the episode of ``task`` that ended at ``end_row``, offer it to the top-K store, restart.

        :param task: task index
        :param end_row: main-buffer row of the episode's last transition
        """
        ret, length = float(self._ep_return[task]), int(self._ep_len[task])
        episode_id = int(self.n_episodes[task])
        self._episode_returns[task].append(ret)
        self.n_episodes[task] += 1
        self._ep_return[task] = 0.0
        self._ep_len[task] = 0
        if self.top_k > 0:
            self._offer_top_k(task, ret, length, end_row, episode_id)

    def _offer_top_k(self, task: int, ret: float, length: int, end_row: int, episode_id: int) -> None:
        """Insert the episode into the task's top-K store if it is among the K best so far.

        :param task: task index
        :param ret: the episode's undiscounted return
        :param length: number of transitions of the episode
        :param end_row: main-buffer row of the episode's last transition
        :param episode_id: index of the episode among the task's completed episodes
        """
        store = self._top_k[task]
        is_full = len(store.returns) >= self.top_k
        if is_full and ret <= store.returns.min():
            return
        if length > self.buffer_size:
            self.n_top_k_skipped[task] += 1
            warnings.warn(
                f"Task {task}: an episode of length {length} qualifies for the top-{self.top_k} store but the "
                f"replay buffer keeps only {self.buffer_size} rows per task, so it was already partly "
                "overwritten and is skipped. Use buffer_size >= n_tasks * max episode length.",
                stacklevel=3,
            )
            return
        rows = np.arange(end_row - length + 1, end_row + 1) % self.buffer_size
        # Drop the worst stored episode (rows [start, stop) of the flat arrays) when the store is full.
        worst = int(np.argmin(store.returns)) if is_full else len(store.returns)
        start = int(store.lengths[:worst].sum())
        stop = start + (int(store.lengths[worst]) if is_full else 0)
        for name in _FIELDS:
            arr = store.data[name]
            store.data[name] = np.concatenate([arr[:start], arr[stop:], getattr(self, name)[rows, task]])
        keep = np.arange(len(store.returns)) != worst
        store.returns = np.append(store.returns[keep], ret)
        store.lengths = np.append(store.lengths[keep], length)
        store.episode_ids = np.append(store.episode_ids[keep], episode_id)

    def reset_running_episodes(self) -> None:
        """Forget the running (incomplete) episode of every task; the next step starts a new one."""
        self._ep_return[:] = 0.0
        self._ep_len[:] = 0

    def reset(self) -> None:
        """Empty the main buffer and the running episodes; completed-episode statistics and the top-K store stay."""
        super().reset()
        self.reset_running_episodes()

    # ------------------------------------------------------------------ sampling
    def sample(self, batch_size: int, env: VecNormalize | None = None) -> MultiTaskReplayBufferSamples:
        """Balanced task-major sample of ``batch_size`` transitions per task.

        Rows are uniform in the filled part of each task's column (numpy's global RNG, as SB3).

        :param batch_size: L, the number of transitions per task
        :param env: VecNormalize env to normalize observations and rewards with, as in SB3
        :return: the batch, ``(N, L, ...)`` tensors
        """
        upper_bound = self.buffer_size if self.full else self.pos
        rows = np.random.randint(0, upper_bound, size=(self.n_envs, batch_size))
        if env is None and (device_copy := self._on_device()) is not None:
            return self._make_samples(device_copy.gather(rows), None)
        cols = np.arange(self.n_envs)[:, None]
        return self._make_samples({name: getattr(self, name)[rows, cols] for name in _FIELDS}, env)

    def sample_top_k(self, batch_size: int, env: VecNormalize | None = None) -> MultiTaskReplayBufferSamples:
        """Task-major sample of ``batch_size`` transitions per task from the top-K store.

        Task i's rows are uniform over the transitions of its stored episodes; a task with no stored
        episode yet falls back to uniform rows of its main-buffer column.

        :param batch_size: L, the number of transitions per task
        :param env: VecNormalize env to normalize observations and rewards with, as in SB3
        :return: the batch, ``(N, L, ...)`` tensors
        """
        n_stored = self.n_top_k_transitions
        upper_bound = self.buffer_size if self.full else self.pos
        if upper_bound == 0 and not n_stored.all():
            raise ValueError("Cannot sample: a task has neither a stored top-K episode nor any transition")
        highs = np.where(n_stored > 0, n_stored, upper_bound)
        rows = np.random.randint(0, highs[:, None], size=(self.n_envs, batch_size))
        parts: list[list[np.ndarray]] = [[] for _ in _FIELDS]
        for task, store in enumerate(self._top_k):
            for part, name in zip(parts, _FIELDS, strict=True):
                source = store.data[name] if n_stored[task] > 0 else getattr(self, name)[:, task]
                part.append(source[rows[task]])
        return self._make_samples({name: np.stack(part) for name, part in zip(_FIELDS, parts, strict=True)}, env)

    def _make_samples(self, fields: dict[str, Any], env: VecNormalize | None) -> MultiTaskReplayBufferSamples:
        """Turn task-major ``(N, L, ...)`` fields (by :data:`_FIELDS` name; fresh numpy copies, or tensors gathered
        on the device with ``env`` None) into a batch of tensors on the model's device."""
        data = (
            self._normalize_obs(fields["observations"], env),
            fields["actions"],
            self._normalize_obs(fields["next_observations"], env),
            fields["dones"] * (1 - fields["timeouts"]),
            self._normalize_reward(fields["rewards"], env),
        )
        return MultiTaskReplayBufferSamples(*(self._as_batch_tensor(value) for value in data))

    def _as_batch_tensor(self, value: np.ndarray | th.Tensor) -> th.Tensor:
        if isinstance(value, th.Tensor):
            return value
        if self._storage() == "pinned":
            return to_device(value, th.device(self.device))
        return self.to_torch(value, copy=False)

    # ------------------------------------------------------------------ storage
    def _storage(self) -> str:
        """Where the transitions live: ``"host"``, ``"pinned"`` or ``"device"`` (:attr:`storage` resolved at first
        use, once SB3 has set the buffer's device)."""
        if self._resolved_storage is None:
            n_bytes = sum(getattr(self, name).nbytes for name in _FIELDS)
            self._resolved_storage = resolve_storage(self.storage, th.device(self.device), n_bytes)
        return self._resolved_storage

    def _on_device(self) -> DeviceStorage | None:
        """The copy of the transitions on the device for the ``"device"`` storage (made at first use, also after a
        load, from the arrays), else None."""
        if self._storage() == "device" and self._device_copy is None:
            self._device_copy = DeviceStorage({name: getattr(self, name) for name in _FIELDS}, th.device(self.device))
        return self._device_copy

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state["_device_copy"] = state["_resolved_storage"] = None  # the arrays are the record; a load copies them
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        state.setdefault("storage", "auto")  # a buffer saved before storages existed
        state.setdefault("_resolved_storage", None)
        state.setdefault("_device_copy", None)
        self.__dict__.update(state)

    # ------------------------------------------------------------------ introspection
    def episode_returns(self, task: int) -> np.ndarray:
        """Returns of the task's completed episodes, oldest first (the last ``max_episode_history``).

        :param task: task index
        """
        return np.array(self._episode_returns[task], dtype=np.float64)

    def top_k_returns(self, task: int) -> np.ndarray:
        """Returns of the task's stored top-K episodes, sorted descending.

        :param task: task index
        """
        return -np.sort(-self._top_k[task].returns)

    def top_k_episodes(self, task: int) -> list[dict[str, Any]]:
        """Copies of the task's stored episodes, best return first (stable on ties).

        :param task: task index
        :return: one dict per episode: the transition arrays under the main buffer's field names
            (``observations``, ``next_observations``, ``actions``, ``rewards``, ``dones``, ``timeouts``)
            plus ``return``, ``length`` and ``episode_id`` (index among the task's completed episodes)
        """
        store = self._top_k[task]
        starts = np.cumsum(store.lengths) - store.lengths
        episodes = []
        for j in np.argsort(-store.returns, kind="stable"):
            sl = slice(starts[j], starts[j] + store.lengths[j])
            episode: dict[str, Any] = {name: store.data[name][sl].copy() for name in _FIELDS}
            episode["return"] = float(store.returns[j])
            episode["length"] = int(store.lengths[j])
            episode["episode_id"] = int(store.episode_ids[j])
            episodes.append(episode)
        return episodes

    @property
    def n_top_k_episodes(self) -> np.ndarray:
        """Number of stored top-K episodes per task, shape (N,)."""
        return np.array([len(store.returns) for store in self._top_k], dtype=np.int64)

    @property
    def n_top_k_transitions(self) -> np.ndarray:
        """Number of stored top-K transitions per task, shape (N,)."""
        return np.array([store.n_transitions for store in self._top_k], dtype=np.int64)

    @property
    def running_episode_returns(self) -> np.ndarray:
        """Undiscounted return so far of each task's running episode, shape (N,)."""
        return self._ep_return.copy()

    @property
    def running_episode_lengths(self) -> np.ndarray:
        """Number of steps so far of each task's running episode, shape (N,)."""
        return self._ep_len.copy()
