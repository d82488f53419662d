"""Hyperparameters of a zoo key: its family's file ``zoo_configs/<family>.yml`` plus the variant's overrides.

The family files are rl-zoo3 hyperparameter files (one entry per env id: ``MT10``, ``MT10-smoke``, ...) written
once per algorithm family; a variant's entries are the family's with the variant's policy and overrides
(:meth:`~sb3_mtte.experiments.variants.Variant.compose`). A file given with ``-conf`` is read by rl-zoo as usual.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable, Iterable
from importlib import resources
from pathlib import Path
from typing import Any

import yaml

from sb3_mtte.common.utils import did_you_mean
from sb3_mtte.envs.metaworld_envs import is_task_list
from sb3_mtte.envs.toy import parse_toy_name
from sb3_mtte.experiments.env_ids import benchmark_task_names, split_env_id
from sb3_mtte.experiments.variants import FAMILIES, VARIANTS, algo_classes, family_of

CONFIG_DIR_NAME = "zoo_configs"
LAUNCHER_YAML_KEYS = ("eval_freq", "eval_episodes", "save_freq")
"""Hyperparameter-file keys read by the launcher (defaults of the command-line flags), not by the model."""
ZOO_YAML_KEYS = (
    "n_timesteps",
    "n_envs",
    "normalize",
    "frame_stack",
    "env_wrapper",
    "vec_env_wrapper",
    "callback",
    "monitor_kwargs",
    "env_kwargs",
    "noise_type",
    "noise_std",
)
"""Hyperparameter-file keys read by rl-zoo itself, not arguments of the algorithm."""
FLAG_KEYS = {"env": "--env", "seed": "--seed", "verbose": "--verbose", "device": "--device", "tensorboard_log": "-tb"}
"""Arguments of the algorithm that rl-zoo sets from its flags."""


def find_config_dir() -> Path:
    """``zoo_configs/``, shipped inside the package as ``sb3_mtte.zoo_configs`` (setup.cfg's ``package_dir``): the
    checkout's folder in an editable install, the installed copy from a wheel."""
    return Path(str(resources.files(f"sb3_mtte.{CONFIG_DIR_NAME}")))


def family_config_path(algo: str) -> Path | None:
    """The family file of a zoo key (``zoo_configs/mtsac.yml`` for ``mtsac_mh``), or None when not found."""
    family = family_of(algo)
    if family is None:
        return None
    path = find_config_dir() / f"{family.config_name}.yml"
    return path if path.is_file() else None


def zoo_hyperparameters(algo: str, env_ids: Iterable[str] = ()) -> dict[str, dict[str, Any]] | None:
    """Every env entry of a zoo key's hyperparameters (rl-zoo's file layout), or None for a key of no family.

    :param env_ids: env ids to add an entry for when they are task lists or toys (:func:`task_list_entry`).
    :raises FileNotFoundError: when the family's file is missing.
    """
    if family_of(algo) is None:
        return None
    path = family_config_path(algo)
    if path is None:
        raise FileNotFoundError(f"No {CONFIG_DIR_NAME}/ file for {algo!r} found: pass -conf <file>.yml.")
    entries = yaml.safe_load(path.read_text())
    if algo not in FAMILIES:
        entries = {env_key: VARIANTS[algo].build.compose(env_key, entry) for env_key, entry in entries.items()}
    for env_id in env_ids:
        entry = None if env_id in entries else task_list_entry(entries, env_id)
        if entry is not None:
            entries[env_id] = entry
    return entries


TASK_LIST_REFERENCE = "MT10"
"""The benchmark whose settings per task a task list (``--env reach-v3_push-v3``) trains with."""
TOY_REFERENCE = "toy-conflict"
"""The toy whose settings per task every other toy (``toy-agree``, ``toy-conflict-6``) trains with."""
PER_TASK_KEYS = ("n_timesteps", "buffer_size", "learning_starts", "eval_freq", "save_freq")
"""Hyperparameters that grow with the task count N (env steps and transitions over all tasks)."""


def reference_benchmark(benchmark: str) -> str | None:
    """The benchmark whose entry ``benchmark`` scales: :data:`TASK_LIST_REFERENCE` for a task list,
    :data:`TOY_REFERENCE` for a toy, None for any other (or an invalid one)."""
    try:
        benchmark_task_names(benchmark)
    except ValueError:
        return None
    if is_task_list(benchmark):
        return TASK_LIST_REFERENCE
    return TOY_REFERENCE if parse_toy_name(benchmark) is not None else None


def task_list_entry(entries: dict[str, dict[str, Any]], env_id: str) -> dict[str, Any] | None:
    """The entry of a task list (``reach-v3_push-v3-smoke``) or a toy (``toy-agree-1``): its
    :func:`reference_benchmark`'s entry at the same budget suffix with each of :data:`PER_TASK_KEYS` scaled to the
    N tasks and ``n_select`` (M) N // 2, at least 1; None for any other env id or without the reference entry."""
    benchmark, suffix = split_env_id(env_id)
    reference = reference_benchmark(benchmark)
    if reference is None:
        return None
    reference = reference if suffix is None else f"{reference}-{suffix}"
    if reference not in entries:
        return None
    n_tasks, n_reference = len(benchmark_task_names(benchmark)), len(benchmark_task_names(split_env_id(reference)[0]))
    entry = dict(entries[reference])
    for key in PER_TASK_KEYS:
        if key in entry:
            entry[key] = type(entry[key])(entry[key] * n_tasks / n_reference)
    if "n_select" in entry:
        entry["n_select"] = max(n_tasks // 2, 1)
    return entry


def missing_entries_message(algo: str, env_ids: list[str], conf_flag: str = "-conf") -> str | None:
    """The error for ``env_ids`` that the zoo key ``algo`` has no hyperparameter entry for, or None when it has
    every one (or is a key of no family, whose file the user gives)."""
    entries = zoo_hyperparameters(algo, env_ids)
    missing = [env_id for env_id in env_ids if entries is not None and env_id not in entries]
    if not missing:
        return None
    hints = [f"did you mean {key}?" for env_id in missing for key in entries or {} if key.lower() == env_id.lower()]
    return (
        f"{algo} has no hyperparameters for {' '.join(missing)}{': ' + ' '.join(hints) if hints else ''} (its "
        f"entries: {' '.join(entries or {})}): pass {conf_flag} <file>.yml that has an entry for "
        f"{' and '.join(missing)}."
    )


def hyperparameter_keys(algo: str) -> list[str]:
    """Every key a hyperparameter entry of the zoo key ``algo`` may hold: the arguments of its class (but those
    set from rl-zoo's flags), rl-zoo's own keys and the launcher's."""
    arguments = [
        name for name in _init_arguments(algo_classes()[algo]) if name not in ("_init_setup_model", *FLAG_KEYS)
    ]
    return [*arguments, *ZOO_YAML_KEYS, *LAUNCHER_YAML_KEYS]


def _init_arguments(cls: type) -> list[str]:
    """Named arguments of ``cls.__init__``, and of its bases' while each passes on ``**kwargs``."""
    names: list[str] = []
    for klass in cls.__mro__:
        if "__init__" not in klass.__dict__:
            continue
        parameters = list(inspect.signature(klass.__init__).parameters.values())[1:]
        named = (p.name for p in parameters if p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD))
        names += [name for name in named if name not in names]
        if not any(p.kind is p.VAR_KEYWORD for p in parameters):
            break
    return names


def unknown_key_message(algo: str, keys: Iterable[str], source: Callable[[str], str]) -> str | None:
    """The error for the first key that no hyperparameter entry of ``algo`` may hold (the nearest valid key named),
    or None when every key is valid.

    :param source: where a key was given (``"-params"``, a file), for the message.
    """
    valid = hyperparameter_keys(algo)
    for key in keys:
        if key in valid:
            continue
        if key in FLAG_KEYS:
            return f"{key} (in {source(key)}) is not a hyperparameter: set it with the flag {FLAG_KEYS[key]}."
        hint = did_you_mean(key, valid) or f"the keys of {algo} are {' '.join(sorted(valid))}."
        return f"Unknown hyperparameter {key} (in {source(key)}) of {algo}: {hint}"
    return None


__all__ = [
    "CONFIG_DIR_NAME",
    "LAUNCHER_YAML_KEYS",
    "family_config_path",
    "find_config_dir",
    "hyperparameter_keys",
    "missing_entries_message",
    "reference_benchmark",
    "task_list_entry",
    "unknown_key_message",
    "zoo_hyperparameters",
]
