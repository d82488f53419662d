"""Which optional install each command needs, checked before the command's module is imported.

The core install runs the algorithms, the environments and ``sb3-mtte evaluate``. The other commands need one or
more extras of the package:

============  ================  =============================================================================
command       extras            modules looked for
============  ================  =============================================================================
train         zoo               rl_zoo3, optuna, yaml, requests, huggingface_sb3, pandas, tensorboard
enjoy         zoo               the same
record_video  zoo, video        the same, and moviepy
sweep         zoo, ray          the same, and ray, pyarrow (Ray Tune)
plot          plots             matplotlib, rliable, scipy, pandas, tensorboard
record        plots             the same
compare       plots             the same
evaluate      (none)
============  ================  =============================================================================

:func:`require_extra` only looks the modules up (``importlib.util.find_spec``): it imports none of them.
"""

from __future__ import annotations

import importlib.util

EXTRA_MODULES: dict[str, dict[str, str]] = {
    "zoo": {
        "rl_zoo3": "rl-zoo3",
        "optuna": "optuna",
        "yaml": "pyyaml",
        "requests": "requests",
        "huggingface_sb3": "sb3-team-hf-integration",
        "pandas": "pandas",
        "tensorboard": "tensorboard",
    },
    "plots": {
        "matplotlib": "matplotlib",
        "rliable": "rliable",
        "scipy": "scipy",
        "pandas": "pandas",
        "tensorboard": "tensorboard",
    },
    "video": {"moviepy": "moviepy"},
    "ray": {"ray": "ray[tune]", "pyarrow": "ray[tune]"},
    "envpool": {"envpool": "envpool"},  # make_mt_env(..., backend="envpool"); no command needs it
}
"""Extra -> {top-level module: the distribution that installs it} (what a missing module is called on screen)."""

COMMAND_EXTRAS: dict[str, tuple[str, ...]] = {
    "train": ("zoo",),
    "enjoy": ("zoo",),
    "record_video": ("zoo", "video"),
    "sweep": ("zoo", "ray"),
    "plot": ("plots",),
    "record": ("plots",),
    "compare": ("plots",),
    "evaluate": (),
}
"""Command of ``sb3-mtte`` -> the extras it needs."""


def module_missing(name: str) -> bool:
    """Whether the top-level module ``name`` cannot be found (nothing is imported to find out)."""
    try:
        return importlib.util.find_spec(name) is None
    except (ImportError, ValueError):  # a module that is half there: found, but broken or without a spec
        return True


def missing_extras(command: str) -> dict[str, list[str]]:
    """Extra -> the distributions of it that ``command`` needs and cannot find (extras with none missing left out).

    :raises ValueError: for a command missing from :data:`COMMAND_EXTRAS`.
    """
    if command not in COMMAND_EXTRAS:
        raise ValueError(f"No extras are listed for the command {command!r}: add it to COMMAND_EXTRAS.")
    missing = {}
    for extra in COMMAND_EXTRAS[command]:
        names = [dist for module, dist in EXTRA_MODULES[extra].items() if module_missing(module)]
        if names:
            missing[extra] = list(dict.fromkeys(names))
    return missing


def missing_extra_message(command: str, prog: str | None = None) -> str | None:
    """The one line naming what ``command`` lacks and the install that brings it, or None when nothing is missing.

    :param prog: how the command is shown (``sb3-mtte <command>`` when None).
    """
    missing = missing_extras(command)
    if not missing:
        return None
    names = ", ".join(dict.fromkeys(name for names in missing.values() for name in names))
    return f'{prog or f"sb3-mtte {command}"} needs {names}: pip install "sb3-mtte[{",".join(missing)}]"'


def require_extra(command: str, prog: str | None = None) -> None:
    """Exit with one line naming the install when ``command`` needs an extra that is not installed.

    Call it before importing the command's module, so the user meets this line, not an ImportError from inside a
    library.

    :param command: a command of ``sb3-mtte`` (a key of :data:`COMMAND_EXTRAS`).
    :param prog: how the command is shown (``sb3-mtte <command>`` when None).
    :raises SystemExit: with the line, when something is missing.
    """
    message = missing_extra_message(command, prog)
    if message is not None:
        raise SystemExit(message)
