"""Run metadata: what was run, with which versions, seed and source commit (``run_info.json`` in every run folder).

``run_info.json`` is written when a run starts and updated when it is resumed or ends. Its fields:

- ``algo`` (the zoo algorithm key, e.g. ``"mtsac_mh"``), ``label`` (the paper's name, e.g. ``"SAC-MT-MH"``),
  ``algorithm_class``, ``env_id`` (e.g. ``"MT10-smoke"``), ``benchmark`` (e.g. ``"MT10"``), ``n_tasks``,
  ``task_names``, ``seed``, ``benchmark_seed``, ``reward_function_version`` (Meta-World's reward functions, ``"v2"``
  or ``"v1"``; null for a toy benchmark; runs that predate the field used ``"v2"``), ``episode_length``,
  ``n_timesteps``;
- ``hyperparams`` (as loaded, JSON-friendly), ``command``, ``zoo_args``;
- ``versions`` (python, sb3_mtte, torch, stable_baselines3, rl_zoo3, gymnasium, metaworld, numpy, mujoco),
  ``git`` (commit, dirty flag and branch of the source tree of ``sb3_mtte``), ``host``, ``device``;
- ``started``, ``resumes`` (one entry per resume: time and checkpoint), ``timesteps`` and ``finished``;
- ``launcher`` (the launcher's own options: ``tensorboard``, ``keep_buffers``, ``align_checkpoints``);
- ``stopped`` (a run stopped by Ctrl-C: its ``timesteps``, ``time`` and the ``checkpoint`` a resume continues
  from; null once a resume finishes it), ``ended`` and ``final_model`` (a finished run's model file).

Only a run that reached its budget has ``finished: true`` and a final model ``<env>.zip``.
"""

from __future__ import annotations

import datetime as _dt
import importlib
import json
import os
import platform
import socket
import subprocess
import sys
import zipfile
from collections.abc import Mapping
from importlib.metadata import version as dist_version
from pathlib import Path
from typing import Any

import numpy as np
import torch as th

from sb3_mtte.experiments.variants import label_of

RUN_INFO_FILE = "run_info.json"

VERSION_PACKAGES = (
    "sb3_mtte",
    "torch",
    "stable_baselines3",
    "rl_zoo3",
    "gymnasium",
    "metaworld",
    "numpy",
    "mujoco",
)
"""Packages whose versions are recorded."""


def now() -> str:
    """The current UTC time, ISO 8601."""
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")


def package_versions() -> dict[str, str | None]:
    """Versions of python and of :data:`VERSION_PACKAGES` (None for a package that is not installed)."""
    versions: dict[str, str | None] = {"python": platform.python_version()}
    for name in VERSION_PACKAGES:
        try:
            module = importlib.import_module(name)
        except Exception:  # a missing or broken optional package is recorded as None
            versions[name] = None
            continue
        version = getattr(module, "__version__", None)
        if version is None:
            try:
                version = dist_version(name.replace("_", "-"))
            except Exception:
                version = None
        versions[name] = None if version is None else str(version)
    return versions


def git_info(path: str | os.PathLike | None = None) -> dict[str, Any]:
    """Commit, branch and dirty flag of the git work tree holding ``path`` (the sb3_mtte sources by default).

    :return: ``{"commit": ..., "branch": ..., "dirty": ...}``; values are None outside a git work tree.
    """
    if path is None:
        path = Path(__file__).resolve().parents[1]
    path = os.fspath(path)

    def git(*args: str) -> str | None:
        try:
            result = subprocess.run(["git", "-C", path, *args], capture_output=True, text=True, timeout=10, check=False)
        except (OSError, subprocess.SubprocessError):
            return None
        return result.stdout.strip() if result.returncode == 0 else None

    commit = git("rev-parse", "HEAD")
    if commit is None:
        return {"commit": None, "branch": None, "dirty": None}
    status = git("status", "--porcelain", "--untracked-files=no")
    return {"commit": commit, "branch": git("rev-parse", "--abbrev-ref", "HEAD"), "dirty": bool(status)}


def device_info() -> dict[str, Any]:
    """CPU count, torch threads and the CUDA device, if any."""
    info: dict[str, Any] = {"cpu_count": os.cpu_count()}
    info["torch_threads"] = th.get_num_threads()
    info["cuda"] = th.cuda.is_available()
    if info["cuda"]:
        info["cuda_device"] = th.cuda.get_device_name(0)
    return info


def to_jsonable(value: Any) -> Any:
    """A JSON-friendly copy of ``value``: containers are converted, anything else becomes its ``repr``."""
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, Mapping):
        return {str(key): to_jsonable(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_jsonable(item) for item in value]
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, type):
        return f"{value.__module__}.{value.__qualname__}"
    return repr(value)


def collect_run_info(
    *,
    algo: str,
    env_id: str,
    seed: int,
    benchmark: str | None = None,
    hyperparams: Mapping[str, Any] | None = None,
    command: str | None = None,
    **fields: Any,
) -> dict[str, Any]:
    """The metadata of a run that starts now.

    :param algo: zoo algorithm key.
    :param env_id: env id the run was launched with.
    :param seed: the run's seed.
    :param benchmark: the benchmark the env id names (the env id when None).
    :param hyperparams: the hyperparameters as loaded.
    :param command: the command line (``sys.orig_argv`` joined when None).
    :param fields: any further fields (``n_tasks``, ``task_names``, ``n_timesteps``, ...). ``env_protocol`` says how
        the training envs differ from the benchmark's (:func:`sb3_mtte.envs.env_protocol`; None for a toy).
    """
    info: dict[str, Any] = {
        "algo": algo,
        "label": label_of(algo, hyperparams),
        "env_id": env_id,
        "benchmark": benchmark or env_id,
        "seed": int(seed),
        "hyperparams": to_jsonable(dict(hyperparams or {})),
        "command": command if command is not None else " ".join(getattr(sys, "orig_argv", sys.argv)),
        "versions": package_versions(),
        "git": git_info(),
        "host": socket.gethostname(),
        "platform": platform.platform(),
        "device": device_info(),
        "started": now(),
        "resumes": [],
        "finished": False,
    }
    info.update(to_jsonable(fields))
    return info


def write_run_info(run_dir: str | os.PathLike, info: Mapping[str, Any]) -> Path:
    """Write ``run_info.json`` into ``run_dir`` (atomically: a write that fails leaves the old file and no temporary
    one) and return its path."""
    path = Path(run_dir) / RUN_INFO_FILE
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".json.tmp")
    try:
        tmp.write_text(json.dumps(to_jsonable(dict(info)), indent=2) + "\n")
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def read_json(path: Path) -> Any:
    """The JSON value in ``path``; a file that is not JSON exits with one line naming it."""
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise SystemExit(f"{path} is not valid JSON ({error}): fix or remove it") from None


def read_npz(path: Path) -> dict[str, np.ndarray]:
    """The arrays in the ``.npz`` file ``path``; a file that is not one exits with one line naming it."""
    try:
        with np.load(path) as data:
            return {key: np.asarray(data[key]) for key in data.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as error:
        raise SystemExit(f"{path} is not a valid .npz file ({error}): fix or remove it") from None


def read_run_info(run_dir: str | os.PathLike) -> dict[str, Any] | None:
    """The ``run_info.json`` of ``run_dir``, or None when there is none."""
    path = Path(run_dir) / RUN_INFO_FILE
    if not path.is_file():
        return None
    return read_json(path)


def update_run_info(run_dir: str | os.PathLike, **fields: Any) -> dict[str, Any]:
    """Set ``fields`` in the ``run_info.json`` of ``run_dir`` (created when missing) and return the result."""
    info = read_run_info(run_dir) or {}
    info.update(to_jsonable(fields))
    write_run_info(run_dir, info)
    return info


def append_resume(run_dir: str | os.PathLike, **entry: Any) -> dict[str, Any]:
    """Record one resume of the run (``entry``: checkpoint, timesteps, ...) with its time and versions."""
    info = read_run_info(run_dir) or {}
    resumes = list(info.get("resumes", []))
    resumes.append({"time": now(), **to_jsonable(entry), "versions": package_versions(), "git": git_info()})
    info["resumes"] = resumes
    write_run_info(run_dir, info)
    return info


__all__ = [
    "RUN_INFO_FILE",
    "append_resume",
    "collect_run_info",
    "device_info",
    "git_info",
    "package_versions",
    "read_run_info",
    "to_jsonable",
    "update_run_info",
    "write_run_info",
]
