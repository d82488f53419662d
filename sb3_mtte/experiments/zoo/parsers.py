"""rl-zoo's own argument parsers of ``train`` and ``enjoy`` as this package shows them: a description, the
launcher's options in ``train``'s help, ``--algo`` limited to the package's zoo keys, and a ``key:value`` of
``-params`` or ``--env-kwargs`` that is no Python value ending with one line."""

from __future__ import annotations

import argparse
import functools
from collections.abc import Callable
from typing import Any

from rl_zoo3.utils import StoreDict

from sb3_mtte.experiments.cli import CommandParser
from sb3_mtte.experiments.env_ids import benchmark_help
from sb3_mtte.experiments.variants import algo_classes

TRAIN_DESCRIPTION = (
    "rl-zoo3's train on a benchmark of sb3_mtte, one sub-env per task. Without -conf, the hyperparameters of --algo "
    "are its family's file plus its overrides; --eval-freq counts env steps over all tasks and --eval-episodes "
    "episodes per task (Meta-World's success protocol); checkpoints (--save-freq) are what --resume continues from."
)
ENJOY_DESCRIPTION = (
    "rl-zoo3's enjoy on a run of sb3_mtte: the model of -f, --algo, --env and --exp-id acts in one sub-env per task, "
    "and every finished episode is printed."
)
PROGRESS_HELP = "display a progress bar with tqdm and rich (on by default: --no-progress hides it)"
TRAIN_STEPS_HELP = "env steps over all tasks (enjoy's -n counts vector steps, one step of every task)"


def _int(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an int") from None


def non_negative_int(text: str) -> int:
    """An option's int of 0 or more (a run folder's id, a count of files kept)."""
    value = _int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"{value} is negative: give 0 or more")
    return value


def threads(text: str) -> int:
    """rl-zoo's ``--num-threads``: a positive int, or -1 for PyTorch's default."""
    value = _int(text)
    if value < 1 and value != -1:
        raise argparse.ArgumentTypeError(f"{value} threads: give 1 or more, or -1 for PyTorch's default")
    return value


def seed(text: str) -> int:
    """rl-zoo's ``--seed``: an int from 0 to 2**32 - 1, or -1 for a random one."""
    value = _int(text)
    if not -1 <= value < 2**32:
        raise argparse.ArgumentTypeError(f"{value} is out of range: give 0 to 2**32 - 1, or -1 for a random seed")
    return value


def add_launcher_options(parser: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """The options of ``train`` that rl-zoo does not have."""
    parser.add_argument(
        "--resume",
        nargs="?",
        const="",
        default=None,
        metavar="RUN_DIR",
        help="continue the latest checkpoint of RUN_DIR (without RUN_DIR: of the latest run of --algo/--env in -f) "
        "with the run's own settings; a flag given again overrides one, and says so. A finished run is left as it "
        "is, unless -n is larger than its steps",
    )
    parser.add_argument(
        "--exp-id",
        type=non_negative_int,
        default=None,
        metavar="N",
        help="run folder <env>_N (default: the next free N). If it holds a finished run with the settings given, "
        "the command says so and exits 0 without training, so it can be run twice; a stopped run there is "
        "continued with --resume",
    )
    parser.add_argument(
        "--no-progress", action="store_true", help="no progress bar (a resumed run keeps its own unless -P is given)"
    )
    parser.add_argument("--no-tensorboard", action="store_true", default=None, help="no tensorboard events")
    parser.add_argument(
        "--keep-buffers",
        type=non_negative_int,
        default=None,
        metavar="K",
        help="replay-buffer checkpoints kept (default 1; 0: all)",
    )
    parser.add_argument(
        "--no-align-checkpoints",
        action="store_true",
        default=None,
        help="save a checkpoint at the step reached, not at the next end of episodes",
    )


class CheckedStoreDict(StoreDict):
    """rl-zoo's ``key:value`` option, whose values are Python expressions; one that does not evaluate ends with one
    line naming it."""

    def __call__(self, parser: argparse.ArgumentParser, namespace: Any, values: Any, option_string: Any = None) -> None:
        try:
            super().__call__(parser, namespace, values, option_string)
        except Exception:  # rl-zoo evaluates the values: any error of Python's; name the item that raised it
            for item in values:
                try:
                    super().__call__(parser, argparse.Namespace(), [item], option_string)
                except Exception as error:
                    raise SystemExit(
                        f"{option_string} {item}: {error}; each value is Python, strings quoted (batch_size:64 "
                        f"policy:\"'MlpPolicy'\")."
                    ) from None
            raise


class ZooParser(CommandParser):
    """rl-zoo's parser with this package's keys as ``--algo`` choices, checked ``key:value`` options and, with
    ``launcher_options``, the launcher's options in a group of the help."""

    def __init__(self, *args: Any, launcher_options: bool = False, **kwargs: Any) -> None:
        self.steps_help = TRAIN_STEPS_HELP if launcher_options else None
        super().__init__(*args, **kwargs)
        if launcher_options:
            add_launcher_options(self.add_argument_group("sb3_mtte options"))

    def add_argument(self, *names: Any, **kwargs: Any) -> argparse.Action:
        if "--env" in names:
            kwargs["help"] = f"env id: {benchmark_help()}"
        if "--algo" in names:
            kwargs.update(choices=list(algo_classes()), help="zoo key of the algorithm (MTSAC's or MTSACTE's variants)")
        if "-n" in names and self.steps_help:
            kwargs["help"] = self.steps_help
        if "--progress" in names:
            kwargs["help"] = PROGRESS_HELP
        if "--num-threads" in names:
            kwargs["type"] = threads
        if "--seed" in names:
            kwargs["type"] = seed
        if kwargs.get("action") is StoreDict:
            kwargs["action"] = CheckedStoreDict
        return super().add_argument(*names, **kwargs)


def zoo_parser(description: str, launcher_options: bool = False, prog: str | None = None) -> Callable[..., ZooParser]:
    """What rl-zoo's ``train()`` or ``enjoy()`` builds its parser with: a :class:`ZooParser` named ``prog`` (how
    the user called the command), described by ``description``
    (:func:`~sb3_mtte.experiments.zoo.adapter.run_train` puts it in place)."""
    return functools.partial(ZooParser, prog=prog, description=description, launcher_options=launcher_options)


__all__ = [
    "ENJOY_DESCRIPTION",
    "TRAIN_DESCRIPTION",
    "TRAIN_STEPS_HELP",
    "CheckedStoreDict",
    "ZooParser",
    "add_launcher_options",
    "zoo_parser",
]
