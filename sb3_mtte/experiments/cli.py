"""Command line: ``sb3-mtte train|enjoy|record_video|evaluate|record|plot|compare|sweep`` (and ``python -m
sb3_mtte.zoo``).

Usage (every rl-zoo ``train`` / ``enjoy`` flag works as usual)::

    sb3-mtte train --algo mtsacte --env MT10 [-conf my.yml] [rl-zoo flags]
    sb3-mtte train --algo mtsacte --env MT10 --resume      # latest run of mtsacte/MT10 in -f
    sb3-mtte train --resume logs/mtsacte/MT10_1            # a given run folder
    sb3-mtte enjoy --algo mtsacte --env MT10 -f logs --no-render -n 2000
    sb3-mtte record_video --algo mtsacte --env MT10 -f logs [-o VIDEO_DIR] [--episodes 1] [--tile]
    sb3-mtte evaluate logs/mtsacte/MT10_1/MT10.zip --episodes 50
    sb3-mtte record logs                                   # docs/records/<env id>/<algo>_seed<k>.json
    sb3-mtte plot docs/records --out docs/figures          # from records (and/or run folders)
    sb3-mtte compare docs/records --benchmark MT10-100k    # two algorithms, as fixed before the runs
    sb3-mtte sweep --algos mtsacte mtsac_mt --envs MT10 --seeds 0 1 --out runs/

``python -m sb3_mtte.zoo <command>`` takes the same eight commands; ``python -m sb3_mtte.evaluate``,
``python -m sb3_mtte.record``, ``python -m sb3_mtte.plot``, ``python -m sb3_mtte.compare`` and
``python -m sb3_mtte.sweep`` are the same commands.

What ``train`` adds to rl-zoo3: the package's zoo keys (:mod:`~sb3_mtte.experiments.variants`) in ``rl_zoo3.ALGOS``
with their hyperparameters (:mod:`~sb3_mtte.experiments.configs`); the benchmarks' env ids, one sub-env per task
(:mod:`~sb3_mtte.experiments.env_ids`); Meta-World's success protocol for evaluation (``--eval-freq`` in total env
steps, ``--eval-episodes`` per task, ``evaluations.npz`` and ``best_model.zip``); a run folder with
``progress.csv``, tensorboard events, ``negative_transfer.jsonl`` (MTSACTE) and ``run_info.json``
(:mod:`~sb3_mtte.experiments.run_info`); checkpoints (``--save-freq``) that ``--resume`` continues exactly
(:mod:`~sb3_mtte.experiments.checkpoints`). ``enjoy`` prints every finished episode; ``record_video`` writes one
video per task (``--tile``: also all tasks side by side).
"""

from __future__ import annotations

import re
import sys
import textwrap
import warnings
from collections.abc import Callable, Sequence
from typing import Any

import rl_zoo3.enjoy

from sb3_mtte.common.utils import nearest_names
from sb3_mtte.experiments import closed_pipe_exit, command_prog, compare, evaluate, plot, records, sweep
from sb3_mtte.experiments.env_ids import register_standard_env_ids
from sb3_mtte.experiments.launcher import train
from sb3_mtte.experiments.playback import enjoy, record_video
from sb3_mtte.experiments.zoo_parsers import ENJOY_DESCRIPTION, zoo_parser


def enjoy_command(argv: Sequence[str]) -> Any:
    """``enjoy``, whose rl-zoo parser shows what it does and the package's zoo keys."""
    with zoo_parser(rl_zoo3.enjoy, ENJOY_DESCRIPTION, prog=command_prog("enjoy", "sb3_mtte.zoo enjoy")):
        return enjoy(argv)


COMMANDS: dict[str, Callable[[Sequence[str]], Any]] = {
    "train": train,
    "enjoy": enjoy_command,
    "record_video": record_video,
    "evaluate": evaluate.main,
    "plot": plot.main,
    "compare": compare.main,
    "record": records.main,
    "sweep": sweep.main,
}
"""Every command of ``sb3-mtte`` and of ``python -m sb3_mtte.zoo``."""


def plain_text(doc: str) -> str:
    """A docstring for the terminal: references to modules in parentheses dropped, other Sphinx roles as their last
    word, inline literals plain, ``::`` as ``:``, and paragraphs (but indented blocks) wrapped anew."""
    doc = re.sub(r"\s*\(:\w+:`[^`]+`\)", "", doc)
    doc = re.sub(r":\w+:`~?([\w.]+)`", lambda m: m.group(1).split(".")[-1], doc)
    doc = doc.replace("``", "").replace("::\n", ":\n")
    wrap = textwrap.TextWrapper(width=116, break_long_words=False, break_on_hyphens=False)
    blocks = doc.strip().split("\n\n")
    return "\n\n".join(block if block.startswith(" ") else wrap.fill(" ".join(block.split())) for block in blocks)


def unknown_command_message(prog: str, command: str, commands: Sequence[str]) -> str:
    """One line naming an unknown command, the nearest known one and every command."""
    close = nearest_names(command, commands)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    return f"{prog}: unknown command {command!r}{hint}; commands: {', '.join(commands)} ({prog} --help for more)"


def run_command(commands: dict[str, Callable[[Sequence[str]], Any]], prog: str, argv: Sequence[str] | None) -> Any:
    """Run ``argv[0]`` of ``commands`` on the rest of ``argv`` (the process's arguments when None); output cut short
    by a closed pipe ends it quietly."""
    argv = list(sys.argv[1:] if argv is None else argv)
    return closed_pipe_exit(lambda: _dispatch(commands, prog, argv))


def _dispatch(commands: dict[str, Callable[[Sequence[str]], Any]], prog: str, argv: list[str]) -> Any:
    if argv and argv[0] not in commands and argv[0] not in ("-h", "--help"):
        print(unknown_command_message(prog, argv[0], list(commands)), file=sys.stderr)
        raise SystemExit(2)
    if not argv or argv[0] not in commands:
        print(f"usage: {prog} {{{','.join(commands)}}} [options]\n\n{plain_text(__doc__ or '')}")
        raise SystemExit(0 if argv else 2)
    register_standard_env_ids()
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*render_mode.*")
        return commands[argv[0]](argv[1:])


def main(argv: Sequence[str] | None = None) -> Any:
    """``sb3-mtte {train,enjoy,record_video,evaluate,plot,sweep} ...`` (the console script)."""
    return run_command(COMMANDS, "sb3-mtte", argv)


def console_main() -> None:
    """The ``sb3-mtte`` console script: :func:`main` with exit status 0 on success (the script's wrapper exits with
    the returned value, and a command's return value is for callers in Python)."""
    main()


def zoo_main(argv: Sequence[str] | None = None) -> Any:
    """``python -m sb3_mtte.zoo {train,enjoy,record_video,evaluate,plot,record,sweep} ...``: the commands of
    :func:`main`."""
    return run_command(COMMANDS, "python -m sb3_mtte.zoo", argv)


__all__ = ["COMMANDS", "console_main", "enjoy_command", "main", "zoo_main"]
