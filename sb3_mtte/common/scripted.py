"""Scripted controllers behind SB3's ``predict``: the experts of the benchmarks (:mod:`sb3_mtte.envs`)."""

from __future__ import annotations

from typing import Any

import numpy as np


class ScriptedPolicy:
    """A scripted controller of every task behind SB3's ``predict``, batched over sub-envs.

    Row j of a batch goes to the controller of the task its one-hot names, without the one-hot; a subclass sets
    :attr:`n_tasks` and gives :meth:`task_actions`. Actions are clipped to [-1, 1].
    """

    n_tasks: int

    def predict(
        self,
        observation: np.ndarray,
        state: Any = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = True,
    ) -> tuple[np.ndarray, None]:
        """Actions for a batch of observations (state followed by the one-hot)."""
        observation = np.asarray(observation)
        tasks = observation[:, -self.n_tasks :].argmax(axis=1)
        actions = self.task_actions(observation[:, : -self.n_tasks], tasks)
        return np.clip(actions, -1.0, 1.0).astype(np.float32), None

    def task_actions(self, states: np.ndarray, tasks: np.ndarray) -> np.ndarray:
        """``(B, A)`` actions before the clip for ``(B, state)`` states of the tasks ``tasks`` (``(B,)``)."""
        raise NotImplementedError
