"""Every place where the launcher reaches into rl-zoo3 past its public API, in one module.

Written for rl-zoo3 2.9 and tested with 2.9.2 (:data:`TESTED_RL_ZOO3`); setup.cfg pins ``rl_zoo3`` to that minor
release. The rest of the package uses rl-zoo's public seams only:

- a subclass of ``ExperimentManager`` that overrides public methods (:data:`PUBLIC_OVERRIDES`);
- ``ExperimentManager.default_vec_env_cls``, the VecEnv class of ``enjoy``;
- the tables ``rl_zoo3.ALGOS``, ``HYPERPARAMS_SAMPLER`` and ``HYPERPARAMS_CONVERTER``;
- ``get_model_path``, ``get_latest_run_id``, ``StoreDict`` and ``TrialEvalCallback``.

rl-zoo's ``train()`` and ``enjoy()`` build their parser and manager inside the function, and ``objective()`` its trial
callback. No argument lets a caller choose them, so this module puts the package's in place for the time of a call:

=============================================  =================================================================
private reach                                  what the package puts there
=============================================  =================================================================
``rl_zoo3.train.argparse``                     ``train``'s parser: the package's zoo keys, help and checks
``rl_zoo3.enjoy.argparse``                     the same for ``enjoy``
``rl_zoo3.train.ExperimentManager``            the multi-task manager
``rl_zoo3.exp_manager.TrialEvalCallback``      the optuna trial callback scored by success
``ExperimentManager._preprocess_hyperparams``  called: a resumed run repeats rl-zoo's set-up step by step
``ExperimentManager._preprocess_action_noise`` called, likewise
``ExperimentManager._save_config``             overridden: a resumed run keeps its ``config.yml`` and ``args.yml``
``ExperimentManager._eval_env_kwargs_args``    read and set: ``--eval-env-kwargs`` as given, None when not given
=============================================  =================================================================

The swaps rely on rl-zoo using these names inside its functions (:data:`USES_INSIDE`). A release that moves a name,
or stops using it, fails ``tests/test_zoo_adapter.py``, which names it. At run time :func:`swapped` names a missing
one in one line.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import inspect
import sys
from collections.abc import Callable, Iterator, Sequence
from types import SimpleNamespace
from typing import Any

import rl_zoo3.enjoy
import rl_zoo3.exp_manager
import rl_zoo3.train
from rl_zoo3.callbacks import TrialEvalCallback
from rl_zoo3.exp_manager import ExperimentManager
from stable_baselines3.common.vec_env import VecEnv

TESTED_RL_ZOO3 = ("2.9",)
"""The rl-zoo3 minor releases this module was written and tested for."""

PRIVATE_ATTRIBUTES: tuple[tuple[str, str], ...] = (
    ("rl_zoo3.train", "argparse"),
    ("rl_zoo3.enjoy", "argparse"),
    ("rl_zoo3.train", "ExperimentManager"),
    ("rl_zoo3.exp_manager", "TrialEvalCallback"),
    ("rl_zoo3.exp_manager:ExperimentManager", "_preprocess_hyperparams"),
    ("rl_zoo3.exp_manager:ExperimentManager", "_preprocess_action_noise"),
    ("rl_zoo3.exp_manager:ExperimentManager", "_save_config"),
)
"""(owner, attribute) of every private reach: a module, or ``module:class``."""

PRIVATE_INSTANCE_ATTRIBUTES = ("_eval_env_kwargs_args",)
"""Attributes that ``ExperimentManager.__init__`` sets and the package reads or sets."""

USES_INSIDE: dict[str, tuple[str, ...]] = {
    "rl_zoo3.train:train": ("argparse.ArgumentParser(", "ExperimentManager("),
    "rl_zoo3.enjoy:enjoy": ("argparse.ArgumentParser(", "ExperimentManager.default_vec_env_cls"),
    "rl_zoo3.exp_manager:ExperimentManager.objective": ("TrialEvalCallback(",),
    "rl_zoo3.exp_manager:ExperimentManager.setup_experiment": (
        "self._preprocess_hyperparams(",
        "self._preprocess_action_noise(",
        "self._save_config(",
    ),
}
"""Function -> the uses in its source that a swap or an override relies on: a release that keeps a name but stops
using it there would make the swap do nothing."""

PUBLIC_SEAMS: tuple[tuple[str, str], ...] = (
    ("rl_zoo3", "ALGOS"),
    ("rl_zoo3.hyperparams_opt", "HYPERPARAMS_SAMPLER"),
    ("rl_zoo3.hyperparams_opt", "HYPERPARAMS_CONVERTER"),
    ("rl_zoo3.exp_manager:ExperimentManager", "default_vec_env_cls"),
    ("rl_zoo3.utils", "get_model_path"),
    ("rl_zoo3.utils", "get_latest_run_id"),
    ("rl_zoo3.utils", "StoreDict"),
    ("rl_zoo3.callbacks", "TrialEvalCallback"),
    ("rl_zoo3.train", "train"),
    ("rl_zoo3.enjoy", "enjoy"),
)
"""(owner, attribute) of the public names the package uses, checked with the private ones."""

PUBLIC_OVERRIDES = (
    "__init__",
    "read_hyperparameters",
    "create_envs",
    "create_callbacks",
    "setup_experiment",
    "objective",
    "learn",
    "save_trained_model",
)
"""The methods of ``ExperimentManager`` that the package's managers override: every other method they define is
their own, and must not shadow one of rl-zoo's."""


def resolve_owner(owner: str) -> Any:
    """The module, or the object of ``module:name`` (``name`` may be dotted: ``Class.method``), that ``owner``
    names."""
    module, _, name = owner.partition(":")
    found = importlib.import_module(module)
    for part in name.split(".") if name else ():
        found = getattr(found, part)
    return found


def missing_uses() -> list[str]:
    """``function: use`` of every use of :data:`USES_INSIDE` missing from the installed rl-zoo3's source."""
    missing = []
    for function, uses in USES_INSIDE.items():
        try:
            source = inspect.getsource(resolve_owner(function))
        except (ImportError, AttributeError, OSError, TypeError):
            source = ""
        missing += [f"{function.replace(':', '.')}: {use}" for use in uses if use not in source]
    return missing


def missing_attributes(pairs: Sequence[tuple[str, str]]) -> list[str]:
    """``owner.attribute`` of every pair the installed rl-zoo3 lacks."""
    missing = []
    for owner, attribute in pairs:
        try:
            found = hasattr(resolve_owner(owner), attribute)
        except (ImportError, AttributeError):
            found = False
        if not found:
            missing.append(f"{owner.replace(':', '.')}.{attribute}")
    return missing


def moved_message(name: str) -> str:
    """One line naming a private reach the installed rl-zoo3 no longer has."""
    return (
        f"rl-zoo3 {rl_zoo3.__version__} has no {name}: sb3-mtte was written for rl-zoo3 "
        f'{", ".join(TESTED_RL_ZOO3)}; install it with pip install "rl_zoo3>={TESTED_RL_ZOO3[0]},<'
        f'{_next_minor(TESTED_RL_ZOO3[-1])}".'
    )


def _next_minor(version: str) -> str:
    major, minor = version.split(".")[:2]
    return f"{major}.{int(minor) + 1}"


@contextlib.contextmanager
def swapped(owner: Any, name: str, value: Any) -> Iterator[None]:
    """Set ``owner.name`` to ``value`` for the time of a ``with`` block; an attribute that is not there ends with
    one line naming it."""
    if not hasattr(owner, name):
        label = getattr(owner, "__qualname__", None) or getattr(owner, "__name__", repr(owner))
        raise SystemExit(moved_message(f"{label}.{name}"))
    old = getattr(owner, name)
    setattr(owner, name, value)
    try:
        yield
    finally:
        setattr(owner, name, old)


def argparse_with(parser: Callable[..., argparse.ArgumentParser]) -> SimpleNamespace:
    """Python's ``argparse`` module with ``ArgumentParser`` replaced by ``parser``."""
    return SimpleNamespace(**{**vars(argparse), "ArgumentParser": parser})


def run_train(
    argv: Sequence[str],
    make_manager: Callable[..., ExperimentManager],
    make_parser: Callable[..., argparse.ArgumentParser],
) -> None:
    """rl-zoo's ``train()`` on ``argv``, with ``make_manager`` and ``make_parser`` in place of its own."""
    with (
        swapped(sys, "argv", [f"{sys.argv[0]} train", *argv]),
        swapped(rl_zoo3.train, "ExperimentManager", make_manager),
        swapped(rl_zoo3.train, "argparse", argparse_with(make_parser)),
    ):
        rl_zoo3.train.train()


def run_enjoy(
    argv: Sequence[str], vec_env_class: Callable[..., VecEnv], make_parser: Callable[..., argparse.ArgumentParser]
) -> None:
    """rl-zoo's ``enjoy()`` on ``argv``, its envs built by ``vec_env_class`` (the public
    ``ExperimentManager.default_vec_env_cls``) and its parser by ``make_parser``."""
    with (
        swapped(sys, "argv", [f"{sys.argv[0]} enjoy", *argv]),
        swapped(ExperimentManager, "default_vec_env_cls", vec_env_class),
        swapped(rl_zoo3.enjoy, "argparse", argparse_with(make_parser)),
    ):
        rl_zoo3.enjoy.enjoy()


class ZooExperimentManager(ExperimentManager):
    """rl-zoo's ``ExperimentManager`` with its private steps behind public names.

    A subclass sets :attr:`trial_eval_callback_class` and overrides :meth:`saves_config`; it calls
    :meth:`preprocess_hyperparams`, :meth:`preprocess_action_noise` and :attr:`eval_env_kwargs_given`.
    """

    trial_eval_callback_class: type[TrialEvalCallback] = TrialEvalCallback
    """The callback that scores an optuna trial (``-optimize``)."""

    @property
    def eval_env_kwargs_given(self) -> dict[str, Any] | None:
        """``--eval-env-kwargs`` as given on the command line, None when not given."""
        return self._eval_env_kwargs_args

    @eval_env_kwargs_given.setter
    def eval_env_kwargs_given(self, value: dict[str, Any] | None) -> None:
        self._eval_env_kwargs_args = value

    def preprocess_hyperparams(self, hyperparams: dict[str, Any]) -> tuple[dict[str, Any], Any, list[Any], Any]:
        """rl-zoo's pre-processing of the hyperparameters: (hyperparameters, env wrapper, callbacks, VecEnv
        wrapper)."""
        return self._preprocess_hyperparams(hyperparams)

    def preprocess_action_noise(
        self, hyperparams: dict[str, Any], saved_hyperparams: dict[str, Any], env: VecEnv
    ) -> dict[str, Any]:
        """rl-zoo's action-noise objects from ``noise_type`` and ``noise_std``."""
        return self._preprocess_action_noise(hyperparams, saved_hyperparams, env)

    def saves_config(self) -> bool:
        """Whether set-up writes ``config.yml``, ``args.yml`` and ``command.txt`` (rl-zoo always does)."""
        return True

    def _save_config(self, saved_hyperparams: dict[str, Any]) -> None:
        if self.saves_config():
            super()._save_config(saved_hyperparams)

    def objective(self, trial: Any) -> float:
        """rl-zoo's optuna trial, scored by :attr:`trial_eval_callback_class`."""
        with swapped(rl_zoo3.exp_manager, "TrialEvalCallback", self.trial_eval_callback_class):
            return super().objective(trial)


__all__ = [
    "PRIVATE_ATTRIBUTES",
    "PRIVATE_INSTANCE_ATTRIBUTES",
    "PUBLIC_OVERRIDES",
    "PUBLIC_SEAMS",
    "TESTED_RL_ZOO3",
    "USES_INSIDE",
    "ZooExperimentManager",
    "missing_attributes",
    "missing_uses",
    "run_enjoy",
    "run_train",
    "swapped",
]
