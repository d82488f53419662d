"""Hyperparameters of a zoo key: its family's file ``zoo_configs/<family>.yml`` plus the variant's overrides.

The family files are rl-zoo3 hyperparameter files (one entry per env id: ``MT10``, ``MT10-smoke``, ...) written
once per algorithm family; a variant's entries are the family's with the variant's policy and overrides
(:meth:`~sb3_mtte.experiments.variants.Variant.compose`). A file given with ``-conf`` is read by rl-zoo as usual.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import Any

import yaml

from sb3_mtte.experiments.variants import FAMILIES, VARIANTS, family_of

CONFIG_DIR_NAME = "zoo_configs"


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


def zoo_hyperparameters(algo: str) -> dict[str, dict[str, Any]] | None:
    """Every env entry of a zoo key's hyperparameters (rl-zoo's file layout), or None for a key of no family.

    :raises FileNotFoundError: when the family's file is missing.
    """
    if family_of(algo) is None:
        return None
    path = family_config_path(algo)
    if path is None:
        raise FileNotFoundError(f"No {CONFIG_DIR_NAME}/ file for {algo!r} found: pass -conf <file>.yml.")
    base = yaml.safe_load(path.read_text())
    if algo in FAMILIES:
        return base
    return {env_key: VARIANTS[algo].build.compose(env_key, entry) for env_key, entry in base.items()}


__all__ = ["CONFIG_DIR_NAME", "family_config_path", "find_config_dir", "zoo_hyperparameters"]


def missing_entries_message(algo: str, env_ids: list[str], conf_flag: str = "-conf") -> str | None:
    """The error for ``env_ids`` that the zoo key ``algo`` has no hyperparameter entry for, or None when it has
    every one (or is a key of no family, whose file the user gives)."""
    entries = zoo_hyperparameters(algo)
    missing = [env_id for env_id in env_ids if entries is not None and env_id not in entries]
    if not missing:
        return None
    return (
        f"{algo} has no hyperparameters for {' '.join(missing)} (its entries: {' '.join(entries or {})}): pass "
        f"{conf_flag} <file>.yml with an entry for each"
    )
