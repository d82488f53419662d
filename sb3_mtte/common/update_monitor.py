"""What the host reads of the updates: whether their losses are finite, and the statistics the logger records.

Reading a tensor of a CUDA device waits for every queued kernel, so an update that reads one each step runs at the
pace of its kernel launches. :class:`UpdateMonitor` reads at once where that costs nothing (the CPU), and otherwise
keeps both on the device until the logger dumps:

- a non-finite loss raises ``FloatingPointError`` naming the loss before its optimizer step (immediate), or, deferred,
  marks the update and the env step where it first appeared, and raises at the next read (the logger's dump, a
  save, the end of ``learn``), naming both;
- the statistics of every ``train`` call are recorded to the logger at once, or kept on the device and recorded at
  the dump (the last call's values, and the mean over the calls since the last dump for mean keys).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch as th

from sb3_mtte.common.utils import check_finite

Stats = dict[str, th.Tensor]


class UpdateMonitor:
    """Finiteness of the losses and the train statistics of one algorithm.

    :param device: the model's device.
    :param deferred: keep both on the device until :meth:`read` (else check and record at once).
    :param record: records one ``train`` call's statistics (numpy arrays) to the logger.
    :param mean_keys: statistics averaged over the calls between two reads (the others: the last call's).
    :param n_updates: the model's count of updates so far (where the device's count starts).
    """

    def __init__(
        self,
        device: th.device,
        deferred: bool,
        record: Callable[[dict[str, Any]], None],
        mean_keys: tuple[str, ...],
        n_updates: int,
    ) -> None:
        self.deferred = deferred
        self.record = record
        self.mean_keys = mean_keys
        self.names: list[str] = []
        self.first_bad = th.full((3,), -1, dtype=th.long, device=device)
        """(loss index in :attr:`names`, update, env step) where a loss was first not finite; -1 while none."""
        self.n_updates = th.full((), n_updates, dtype=th.long, device=device)
        """The model's updates (a device counter, so that a captured update can count itself)."""
        self.env_step = th.zeros((), dtype=th.long, device=device)
        self.pending: Stats = {}
        self.sums: Stats = {}
        self.n_train_calls = 0

    def set_env_step(self, env_step: int) -> None:
        """The env step of the coming updates (written on the device without waiting)."""
        if self.deferred:
            self.env_step.fill_(env_step)

    def check_finite(self, name: str, loss: th.Tensor) -> None:
        """Raise now on a non-finite ``loss`` (immediate), or mark it on the device (deferred)."""
        if not self.deferred:
            check_finite(name, loss)
            return
        if name not in self.names:
            self.names.append(name)
        bad = ~th.isfinite(loss.detach()).all()
        first = bad & (self.first_bad[0] < 0)
        where = th.stack([th.full_like(self.n_updates, self.names.index(name)), self.n_updates + 1, self.env_step])
        self.first_bad.copy_(th.where(first, where, self.first_bad))

    def count_update(self) -> None:
        if self.deferred:
            self.n_updates.add_(1)

    def add_train_stats(self, stats: Stats) -> None:
        """Record one ``train`` call's statistics now (immediate) or at the next :meth:`read` (deferred); the tensors
        are the caller's to give (not written afterwards)."""
        if not self.deferred:
            self.record(_on_host(stats))
            return
        self.pending = dict(stats)
        for key in self.mean_keys:
            if key in stats:
                value = stats[key].detach().double()
                self.sums[key] = self.sums[key] + value if key in self.sums else value
        self.n_train_calls += 1

    def check(self) -> None:
        """Raise for a non-finite loss seen since the start (deferred only)."""
        if not self.deferred:
            return
        loss, update, env_step = (int(v) for v in self.first_bad.cpu())
        if loss >= 0:
            raise FloatingPointError(
                f"The {self.names[loss]} is not finite (first at update {update}, env step {env_step}); "
                "training stopped."
            )

    def read(self) -> None:
        """:meth:`check`, then record the kept statistics (deferred only)."""
        self.check()
        if not self.pending:
            return
        stats = dict(self.pending)
        for key, total in self.sums.items():
            stats[key] = total / self.n_train_calls
        self.record(_on_host(stats))
        self.pending, self.sums, self.n_train_calls = {}, {}, 0


def record_train_stats(model: Any) -> None:
    """Record what ``model``'s update monitor keeps, if it has one: before a dump of the logger that is not the
    model's own ``dump_logs`` (a checkpoint's, an evaluation's)."""
    monitor = getattr(model, "update_monitor", None)
    if monitor is not None:
        monitor.read()


def _on_host(stats: Stats) -> dict[str, Any]:
    return {key: value.detach().cpu().numpy() for key, value in stats.items()}
