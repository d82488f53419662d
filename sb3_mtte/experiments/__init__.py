"""Experiment tooling: the rl-zoo3 launcher, evaluation, figures, sweeps and run metadata, one concern a module.

- :mod:`~sb3_mtte.experiments.variants`: the algorithm variants (zoo keys, classes, labels, order, paper numbers);
- :mod:`~sb3_mtte.experiments.configs`: a zoo key's hyperparameters (family file + variant overrides);
- :mod:`~sb3_mtte.experiments.env_ids`: benchmark env ids and the one-task-per-sub-env VecEnv;
- :mod:`~sb3_mtte.experiments.manager`: rl-zoo3's ``ExperimentManager`` for multi-task runs;
- :mod:`~sb3_mtte.experiments.launcher`: ``train`` (rl-zoo's, with resume);
- :mod:`~sb3_mtte.experiments.playback`, :mod:`~sb3_mtte.experiments.video`,
  :mod:`~sb3_mtte.experiments.episode_reporter`: ``enjoy`` and ``record_video`` (its videos streamed task by task),
  the episode report of ``enjoy``;
- :mod:`~sb3_mtte.experiments.checkpoints`, :mod:`~sb3_mtte.experiments.callbacks`,
  :mod:`~sb3_mtte.experiments.run_logs`: resumable checkpoints, training callbacks, the logs of a run folder;
- :mod:`~sb3_mtte.experiments.run_info`: ``run_info.json``;
- :mod:`~sb3_mtte.experiments.evaluate`: the official per-task evaluation of a saved model;
- :mod:`~sb3_mtte.experiments.runs`, :mod:`~sb3_mtte.experiments.figures`, :mod:`~sb3_mtte.experiments.results`,
  :mod:`~sb3_mtte.experiments.plot`: reading runs, the figures, Table 1 and results, the ``plot`` command;
- :mod:`~sb3_mtte.experiments.sweep`: a grid of runs on Ray Tune;
- :mod:`~sb3_mtte.experiments.cli`: the ``sb3-mtte`` command.
"""

import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any


def command_prog(command: str, module: str) -> str:
    """How the user called ``command``: ``sb3-mtte <command>`` from the console script, else
    ``python -m <module>`` (for usage lines and errors)."""
    return f"sb3-mtte {command}" if Path(sys.argv[0]).name == "sb3-mtte" else f"python -m {module}"


def closed_pipe_exit(main: Callable[[], Any]) -> Any:
    """Run ``main``; output cut short by a closed pipe (``... --help | head``) ends the command quietly, as a shell
    command does, with no traceback (Python's recipe: stdout to devnull, exit status 1)."""
    try:
        result = main()
        sys.stdout.flush()
        return result
    except BrokenPipeError:
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        raise SystemExit(1) from None


def device_error(flag: str, device: str | None) -> str | None:
    """Why ``device`` is no torch device (``--device gpu``), or None: SB3's ``auto`` and any name torch takes."""
    import torch as th

    if device in (None, "auto"):
        return None
    try:
        th.device(device)
    except (RuntimeError, TypeError):
        return f"{flag} {device}: not a torch device; give auto, cpu, cuda or cuda:<index>."
    return None


def output_folder_error(flag: str, path: str | Path) -> str | None:
    """Why ``path`` cannot be the output folder of ``flag`` (an existing file), or None."""
    return f"{flag} {path} is a file: give a folder." if Path(path).is_file() else None


def output_file_error(flag: str, path: str | Path) -> str | None:
    """Why ``path`` cannot be the output file of ``flag`` (an existing folder, or a name ending in a slash), or None."""
    if Path(path).is_dir() or str(path).endswith(("/", "\\")):
        return f"{flag} {path} is a folder: give a file path (e.g. {Path(path) / 'success.json'})."
    return None
