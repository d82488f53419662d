"""Command line: ``sb3-mtte <command>``, or ``python -m sb3_mtte <command>``.

Commands::

    train         train with rl-zoo3, one sub-env per task (every rl-zoo flag works as usual)
    enjoy         run a trained model and print every finished episode
    record_video  write one video per task of a trained model
    evaluate      per-task success of a saved model, with Meta-World's protocol
    plot          figures and Table 1 from records or run folders
    compare       two algorithms compared as fixed before the runs
    record        one small JSON record per finished run
    sweep         a grid of training runs on Ray Tune

Usage::

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
    sb3-mtte --version

``sb3-mtte <command> --help`` describes a command's options. Ctrl-C ends any command with one line and exit status
130; output paths and devices are checked before any work starts.

What ``train`` adds to rl-zoo3: the package's zoo keys (:mod:`~sb3_mtte.experiments.variants`) in ``rl_zoo3.ALGOS``
with their hyperparameters (:mod:`~sb3_mtte.experiments.zoo.configs`); the benchmarks' env ids, one sub-env per task
(:mod:`~sb3_mtte.experiments.env_ids`); Meta-World's success protocol for evaluation (``--eval-freq`` in total env
steps, ``--eval-episodes`` per task, ``evaluations.npz`` and ``best_model.zip``); a run folder with
``progress.csv``, tensorboard events, ``negative_transfer.jsonl`` (MTSACTE) and ``run_info.json``
(:mod:`~sb3_mtte.experiments.run_info`); checkpoints (``--save-freq``) that ``--resume`` continues exactly
(:mod:`~sb3_mtte.experiments.zoo.run_checkpoints`). ``enjoy`` prints every finished episode; ``record_video``
writes one video per task (``--tile``: also all tasks side by side).
"""

from __future__ import annotations

import argparse
import contextlib
import contextvars
import difflib
import importlib
import multiprocessing
import os
import re
import sys
import tempfile
import textwrap
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NoReturn

from sb3_mtte.experiments.extras import require_extra

CONSOLE_SCRIPT = "sb3-mtte"
MODULE_FORM = "python -m sb3_mtte"

COMMAND_TARGETS: dict[str, str] = {
    "train": "sb3_mtte.experiments.zoo.launcher:train",
    "enjoy": "sb3_mtte.experiments.playback.zoo_playback:enjoy",
    "record_video": "sb3_mtte.experiments.playback.zoo_playback:record_video",
    "evaluate": "sb3_mtte.experiments.playback.evaluate_model:main",
    "plot": "sb3_mtte.experiments.results.plot:main",
    "compare": "sb3_mtte.experiments.results.compare:main",
    "record": "sb3_mtte.experiments.results.records:main",
    "sweep": "sb3_mtte.experiments.zoo.sweep:main",
}
"""Command -> ``module:function`` that runs it on the command's arguments."""

_CALLED_AS: contextvars.ContextVar[str | None] = contextvars.ContextVar("sb3_mtte_called_as", default=None)


def program_name() -> str:
    """How the user called the package: ``python -m sb3_mtte`` when the process runs its ``__main__``, else
    ``sb3-mtte`` (the console script, and any call from Python)."""
    called_as = _CALLED_AS.get()
    if called_as is not None:
        return called_as
    argv0 = Path(sys.argv[0]) if sys.argv and sys.argv[0] else Path()
    return MODULE_FORM if (argv0.name, argv0.parent.name) == ("__main__.py", "sb3_mtte") else CONSOLE_SCRIPT


class CommandParser(argparse.ArgumentParser):
    """A command's parser whose errors are one line, without the usage block (``--help`` shows it)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message}\n")


def command_prog(command: str) -> str:
    """How the user called ``command``, for usage lines and errors: ``sb3-mtte <command>`` or
    ``python -m sb3_mtte <command>``."""
    return f"{program_name()} {command}"


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
    """Why ``device`` cannot run here, or None: a name torch does not take (``--device gpu``), or a CUDA or MPS
    device this machine lacks (SB3 would fall back to the CPU without a word). SB3's ``auto`` is always fine."""
    import torch as th

    if device in (None, "auto"):
        return None
    try:
        chosen = th.device(device)
    except (RuntimeError, TypeError):
        return f"{flag} {device}: not a torch device; give auto, cpu, cuda or cuda:<index>."
    if chosen.type == "cuda":
        return _cuda_error(flag, device, chosen.index)
    if chosen.type == "mps" and not th.backends.mps.is_available():
        return f"{flag} {device}: MPS is not available on this machine; give {flag} cpu or {flag} auto."
    return None


def _cuda_error(flag: str, device: str, index: int | None) -> str | None:
    import torch as th

    if not th.cuda.is_available():
        return f"{flag} {device}: CUDA is not available on this machine; give {flag} cpu or {flag} auto."
    count = th.cuda.device_count()
    if index is not None and index >= count:
        devices = "cuda:0" if count == 1 else f"cuda:0 to cuda:{count - 1}"
        return f"{flag} {device}: this machine's CUDA devices are {devices}; give one of them, or {flag} auto."
    return None


def output_folder_error(flag: str, path: str | Path) -> str | None:
    """Why ``path`` cannot be the output folder of ``flag``, or None: an existing file, a file on the way to it, or
    a place where nothing can be written (checked by writing there, before any work)."""
    if Path(path).is_file():
        return f"{flag} {path} is a file: give a folder."
    return unwritable_error(flag, path, Path(path))


def output_file_error(flag: str, path: str | Path) -> str | None:
    """Why ``path`` cannot be the output file of ``flag``, or None: an existing folder, a name ending in a slash, a
    file on the way to it, or a folder where nothing can be written (checked by writing there, before any work)."""
    if Path(path).is_dir() or str(path).endswith(("/", "\\")):
        return f"{flag} {path} is a folder: give a file path (e.g. {Path(path) / 'success.json'})."
    return unwritable_error(flag, path, Path(path).parent)


def unwritable_error(flag: str, given: str | Path, folder: Path) -> str | None:
    """Why ``folder`` (the output folder of ``flag``, or the folder of its output file ``given``) cannot be made
    and written, or None. Its nearest existing folder must take a new file: one is made there and removed, so the
    answer holds for every user, root included, and every file system."""
    existing = folder
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        return f"{flag} {given}: {existing} is a file, not a folder; give a path in a folder."
    try:
        handle, probe = tempfile.mkstemp(prefix=".sb3_mtte_write_check_", dir=existing)
    except OSError as error:
        reason = error.strerror or type(error).__name__
        return f"{flag} {given}: nothing can be written in {existing} ({reason}); give a folder you can write to."
    os.close(handle)
    os.remove(probe)
    return None


class LazyCommand:
    """A command whose module is imported only when it runs, once its extras are found.

    :param name: the command (a key of :data:`COMMAND_TARGETS`).
    :param target: ``module:function`` that runs it.
    """

    def __init__(self, name: str, target: str) -> None:
        self.name, self.target = name, target

    def __call__(self, argv: Sequence[str]) -> Any:
        require_extra(self.name, command_prog(self.name))
        module, function = self.target.split(":")
        return getattr(importlib.import_module(module), function)(argv)

    def __repr__(self) -> str:
        return f"LazyCommand({self.name!r}, {self.target!r})"


COMMANDS: dict[str, Callable[[Sequence[str]], Any]] = {
    name: LazyCommand(name, target) for name, target in COMMAND_TARGETS.items()
}
"""Every command of ``sb3-mtte`` and of ``python -m sb3_mtte``."""


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
    close = difflib.get_close_matches(command, list(commands), n=1, cutoff=0.6)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    return f"{prog}: unknown command {command!r}{hint}; commands: {', '.join(commands)} ({prog} --help for more)"


def run_command(commands: dict[str, Callable[[Sequence[str]], Any]], prog: str, argv: Sequence[str] | None) -> Any:
    """Run ``argv[0]`` of ``commands`` on the rest of ``argv`` (the process's arguments when None); output cut short
    by a closed pipe ends it quietly."""
    argv = list(sys.argv[1:] if argv is None else argv)
    token = _CALLED_AS.set(prog)
    try:
        return closed_pipe_exit(lambda: _dispatch(commands, prog, argv))
    finally:
        _CALLED_AS.reset(token)


def _dispatch(commands: dict[str, Callable[[Sequence[str]], Any]], prog: str, argv: list[str]) -> Any:
    if argv[:1] in (["--version"], ["-V"]):
        from sb3_mtte.version import __version__

        print(f"sb3-mtte {__version__}")
        return __version__
    if argv and argv[0] not in commands and argv[0] not in ("-h", "--help"):
        print(unknown_command_message(prog, argv[0], list(commands)), file=sys.stderr)
        raise SystemExit(2)
    if not argv or argv[0] not in commands:
        print(f"usage: {prog} {{{','.join(commands)}}} [options]\n\n{plain_text(__doc__ or '')}")
        raise SystemExit(0 if argv else 2)
    from sb3_mtte.experiments.env_ids import register_standard_env_ids  # loads torch: after the process settings

    register_standard_env_ids()
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*render_mode.*")
        return commands[argv[0]](argv[1:])


def main(argv: Sequence[str] | None = None, prog: str | None = None) -> Any:
    """``sb3-mtte <command> ...``: run one command of :data:`COMMANDS`.

    :param argv: the command and its arguments (default: the process's).
    :param prog: how the package was called, in usage lines and errors (default: :func:`program_name`).
    :return: what the command returns (written paths, results), for callers in Python.
    """
    return run_command(COMMANDS, prog or program_name(), argv)


def console_main() -> None:
    """The ``sb3-mtte`` console script and ``python -m sb3_mtte``: the package's process settings, then
    :func:`main`, with exit status 0 on success (the script's wrapper exits with the returned value, and a
    command's return value is for callers in Python). Ctrl-C ends any command at once with one line and exit
    status 130, as a shell expects (:func:`interrupted_exit`)."""
    from sb3_mtte.process import tune_process

    tune_process(spin_count="torch" not in sys.modules)  # a fresh command process: torch is not loaded yet
    try:
        main()
    except KeyboardInterrupt:
        interrupted_exit(sys.argv[1:2])


INTERRUPTED_STATUS = 130
"""Exit status of a command stopped by Ctrl-C (128 + SIGINT, as a shell reports it)."""


def interrupted_exit(command: Sequence[str]) -> NoReturn:
    """End the process stopped by Ctrl-C: one line naming the command, then exit status :data:`INTERRUPTED_STATUS`
    at once. The exit skips the interpreter's shutdown, which joins threads and sub-env processes and can take
    seconds. The sub-env processes leave Ctrl-C to the command
    (:class:`~sb3_mtte.experiments.env_ids.MultiTaskVecEnvFactory`), which ends them first: they would otherwise
    print the traceback of their closed pipe."""
    name = command_prog(command[0]) if command and command[0] in COMMANDS else program_name()
    for child in multiprocessing.active_children():
        with contextlib.suppress(OSError, ValueError):
            child.terminate()
    with contextlib.suppress(OSError, ValueError):
        sys.stdout.flush()
    with contextlib.suppress(OSError, ValueError):
        print(f"{name}: interrupted (Ctrl-C)", file=sys.stderr, flush=True)
    os._exit(INTERRUPTED_STATUS)


__all__ = [
    "COMMANDS",
    "COMMAND_TARGETS",
    "closed_pipe_exit",
    "command_prog",
    "console_main",
    "device_error",
    "interrupted_exit",
    "main",
    "output_file_error",
    "output_folder_error",
    "program_name",
    "unwritable_error",
]
