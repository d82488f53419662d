"""How MTSAC runs its updates: eagerly, or replayed as a CUDA graph (the default on CUDA where the update allows it:
:mod:`~sb3_mtte.common.gpu_defaults`), and what the host reads.

Both paths run one function, :meth:`UpdatePathMixin._update` (the SAC update of Eq. 9 and 15-16, then Polyak); the
CUDA-graph path records its kernels once and replays them (:class:`~sb3_mtte.common.captured_update.CapturedUpdate`),
and reads the finiteness of the losses and the logged statistics only when the logger dumps
(:class:`~sb3_mtte.common.update_monitor.UpdateMonitor`). An update whose hooks read the GPU on the host (gradient
surgery's solve on the Gram matrix, PaCo's reset of collapsed tasks) runs eagerly.
"""

from __future__ import annotations

from typing import Any

import torch as th

from sb3_mtte.common import gpu_defaults
from sb3_mtte.common.captured_update import CapturedUpdate, set_learning_rate
from sb3_mtte.common.update_hooks import UpdateHook
from sb3_mtte.common.update_monitor import Stats, UpdateMonitor
from sb3_mtte.common.utils import polyak_update
from sb3_mtte.mtsac.task_logs import MEAN_STATS

UPDATE_PATHS = ("auto", "eager", "cuda_graph")


def check_update_path(update_path: str) -> None:
    """:raises ValueError: for an ``update_path`` other than ``"auto"``, ``"eager"`` and ``"cuda_graph"``."""
    if update_path not in UPDATE_PATHS:
        raise ValueError(f"update_path must be one of {UPDATE_PATHS}, got {update_path!r}.")


class UpdatePathMixin:
    """``train`` of MTSAC: every gradient step through :attr:`_update_runner`, the eager update or its CUDA graph."""

    update_path: str
    update_hook: UpdateHook
    device: th.device
    actor: Any
    critic: Any
    critic_target: Any
    ent_coef_optimizer: th.optim.Optimizer | None
    tau: float
    target_update_interval: int

    def resolved_update_path(self) -> str:
        """``"eager"`` or ``"cuda_graph"``: ``"auto"`` takes the graph on CUDA when the update's hooks allow it and
        :data:`~sb3_mtte.common.gpu_defaults.FAST_PATH_BY_DEFAULT` is set (the default), else eager.

        :raises ValueError: for ``"cuda_graph"`` off CUDA or with hooks that read the GPU on the host.
        """
        if self.update_path == "auto":
            fast = gpu_defaults.FAST_PATH_BY_DEFAULT and self.device.type == "cuda" and self.update_hook.capturable
            return "cuda_graph" if fast else "eager"
        if self.update_path == "cuda_graph" and self.device.type != "cuda":
            raise ValueError(f"update_path='cuda_graph' needs a CUDA device, got {self.device}: use 'auto' or 'eager'.")
        if self.update_path == "cuda_graph" and not self.update_hook.capturable:
            raise ValueError(
                "update_path='cuda_graph': this update reads the GPU on the host every step (gradient surgery, or "
                "PaCo's reset with a task_loss_threshold): use 'auto' or 'eager'."
            )
        return self.update_path

    def _setup_update_path(self, capture: bool = True) -> None:
        """Build the monitor and the runner of the resolved path (``capture=False``: the graph path's static
        inputs and deferred reads without the graph, which the CPU can run). What the old monitor kept is read
        first (its statistics recorded, a non-finite loss raised)."""
        if getattr(self, "update_monitor", None) is not None:
            self.update_monitor.read()
        path = self.resolved_update_path() if capture else "cuda_graph"
        self.update_monitor = UpdateMonitor(
            self.device,
            path != "eager",
            self._record_train_stats,
            MEAN_STATS,
            self._n_updates,  # type: ignore[attr-defined]
        )
        if path == "eager":
            for optimizer in self._optimizers():  # a checkpoint of the graph path keeps its optimizers' flag
                for group in optimizer.param_groups:
                    group["capturable"] = False
            self._update_runner = self._update
        else:
            self._update_runner = CapturedUpdate(self._update, self._optimizers, self.device, capture)

    def _optimizers(self) -> list[th.optim.Optimizer]:
        optimizers = [self.actor.optimizer, self.critic.optimizer]
        return optimizers if self.ent_coef_optimizer is None else [*optimizers, self.ent_coef_optimizer]

    def _update_learning_rate(self, optimizers: list[th.optim.Optimizer]) -> None:  # type: ignore[override]
        """SB3's, writing a learning rate held in a tensor in place (the CUDA graph reads it there)."""
        learning_rate = self.lr_schedule(self._current_progress_remaining)  # type: ignore[attr-defined]
        self.logger.record("train/learning_rate", learning_rate)  # type: ignore[attr-defined]
        set_learning_rate(optimizers, learning_rate)

    def train(self, gradient_steps: int, batch_size: int = 128) -> None:
        self.policy.set_training_mode(True)  # type: ignore[attr-defined]
        self._update_learning_rate(self._optimizers())
        self.update_monitor.set_env_step(self.num_timesteps)  # type: ignore[attr-defined]
        stats: dict[str, list[th.Tensor]] = {}
        for gradient_step in range(gradient_steps):
            replay_data = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)  # type: ignore[attr-defined]
            polyak = gradient_step % self.target_update_interval == 0
            for key, value in self._update_runner(replay_data, polyak).items():
                stats.setdefault(key, []).append(value)
        self._n_updates += gradient_steps  # type: ignore[attr-defined]
        self.update_monitor.add_train_stats({key: th.stack(values).mean(0) for key, values in stats.items()})

    def _update(self, replay_data: Any, polyak: bool) -> Stats:
        """One update (:meth:`_sac_update`), then the Polyak step of the target critics when ``polyak``."""
        stats = self._sac_update(replay_data)  # type: ignore[attr-defined]
        if polyak:
            polyak_update(self.critic.parameters(), self.critic_target.parameters(), self.tau)
        self.update_monitor.count_update()
        return stats

    def set_parameters(self, *args: Any, **kwargs: Any) -> None:
        """SB3's, then a new runner: a loaded optimizer state replaces the tensors a captured graph would read."""
        super().set_parameters(*args, **kwargs)  # type: ignore[misc]
        self._setup_update_path()

    def dump_logs(self) -> None:
        """Read the monitor (a non-finite loss stops training here at the latest), then SB3's dump."""
        self.update_monitor.read()
        super().dump_logs()  # type: ignore[misc]
