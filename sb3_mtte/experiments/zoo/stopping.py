"""Ctrl-C during ``train``: the run stops at the next step, keeps a checkpoint there and says how to resume.

The first Ctrl-C asks for a stop (:class:`StopRequest`). The checkpoint callback sees it at the start of the next
rollout, where its checkpoints are always taken, saves one and raises :class:`TrainingStopped`. A second Ctrl-C stops
at once, without that checkpoint: a resume then continues from the last one. Either way the final model is not
written, ``run_info.json`` keeps ``finished: false`` and the command exits with status 130, as a shell expects.
"""

from __future__ import annotations

import contextlib
import signal
import sys
from dataclasses import dataclass
from types import FrameType, TracebackType
from typing import Any, NoReturn

from stable_baselines3.common.base_class import BaseAlgorithm

from sb3_mtte.experiments import run_info
from sb3_mtte.experiments.cli import command_prog
from sb3_mtte.experiments.zoo.run_checkpoints import Checkpoint, find_latest_checkpoint

STOPPED_STATUS = 130
"""Exit status of a run stopped by Ctrl-C (128 + SIGINT)."""


class TrainingStopped(Exception):
    """Raised by the checkpoint callback once it has saved the checkpoint a stop request asked for.

    :param checkpoint: that checkpoint.
    """

    def __init__(self, checkpoint: Checkpoint) -> None:
        super().__init__(f"stopped at {checkpoint.timesteps} env steps")
        self.checkpoint = checkpoint


class StopRequest:
    """Ctrl-C handling for the time of a ``with`` block: the first Ctrl-C sets :attr:`requested`, a second one raises
    ``KeyboardInterrupt`` at once. Outside the main thread (a Ray worker) Ctrl-C keeps Python's default."""

    def __init__(self) -> None:
        self.requested = False
        self._previous: Any = None
        self._installed = False

    def __enter__(self) -> StopRequest:
        with contextlib.suppress(ValueError):  # signal handlers belong to the main thread
            self._previous = signal.signal(signal.SIGINT, self._handle)
            self._installed = True
        return self

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None, tb: TracebackType | None) -> None:
        if self._installed:
            signal.signal(signal.SIGINT, self._previous)
            self._installed = False

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True
        print("Stopping at the next step with a checkpoint (Ctrl-C again: at once, without it).", flush=True)


@dataclass
class Stop:
    """Where a run stopped by Ctrl-C stopped, and the checkpoint taken there (None: stopped at once)."""

    timesteps: int
    checkpoint: Checkpoint | None


def stopped_message(
    timesteps: int, n_timesteps: int, resume_command: str, checkpoint_steps: int | None, at_stop: bool
) -> str:
    """The line a stopped run ends with: where it stopped and how to resume.

    :param timesteps: env steps done when it stopped.
    :param n_timesteps: the run's budget.
    :param resume_command: the command that resumes it.
    :param checkpoint_steps: step of the checkpoint a resume continues from (None: there is none).
    :param at_stop: whether that checkpoint was taken at the stop.
    """
    line = f"Stopped at {timesteps:,} of {n_timesteps:,} env steps; resume with: {resume_command}"
    if at_stop:
        return line
    if checkpoint_steps is None:
        return f"{line} (no checkpoint yet: it starts over)"
    return f"{line} (from the checkpoint at {checkpoint_steps:,})"


def print_stopped(message: str) -> None:
    """Write the stop line to stderr, after what is waiting on stdout."""
    with contextlib.suppress(OSError, ValueError):
        sys.stdout.flush()
    print(message, file=sys.stderr, flush=True)


def end_stopped_run(model: BaseAlgorithm, stop: Stop, run_dir: str, n_timesteps: int) -> NoReturn:
    """End a stopped run: record where it stopped (``run_info.json``: ``finished: false``, ``stopped``), say how to
    resume in one line on stderr, and exit with status :data:`STOPPED_STATUS`."""
    checkpoint = stop.checkpoint or find_latest_checkpoint(run_dir)
    run_info.update_run_info(
        run_dir,
        timesteps=stop.timesteps,
        n_updates=int(getattr(model, "_n_updates", 0)),
        finished=False,
        stopped={
            "timesteps": stop.timesteps,
            "time": run_info.now(),
            "checkpoint": None if checkpoint is None else checkpoint.model.name,
        },
    )
    resume = f"{command_prog('train')} --resume {run_dir}"
    steps = None if checkpoint is None else checkpoint.timesteps
    print_stopped(stopped_message(stop.timesteps, n_timesteps, resume, steps, stop.checkpoint is not None))
    raise SystemExit(STOPPED_STATUS)


__all__ = [
    "STOPPED_STATUS",
    "Stop",
    "StopRequest",
    "TrainingStopped",
    "end_stopped_run",
    "print_stopped",
    "stopped_message",
]
