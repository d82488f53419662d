"""The arguments of MTSAC, each with its type and range, in one table (:data:`MTSAC_ARGUMENTS`).

:func:`check_arguments` checks a constructor's arguments against its class's table before any work. A value of the
wrong type raises :class:`ArgumentTypeError`, one out of range a ``ValueError``. Either is one line that names the
argument and its valid values, or the nearest valid name. MTSACTE's table extends this one
(:mod:`sb3_mtte.mtsacte.checks`). The command line checks its hyperparameters with the same function.
"""

from __future__ import annotations

import inspect
import math
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from numbers import Integral, Real
from typing import Any

import torch as th
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.policies import BasePolicy

from sb3_mtte.common.critics import CRITIC_ARCHS
from sb3_mtte.common.gradient_surgery import GRADIENT_SURGERY_METHODS
from sb3_mtte.common.utils import did_you_mean

ENT_COEF_ARCHS = ("per_task", "shared")
UPDATE_PATHS = ("auto", "eager", "cuda_graph")
TRAIN_FREQ_UNITS = ("step", "episode")
NONE = type(None)


class ArgumentTypeError(TypeError, ValueError):
    """An argument of the wrong type. It is a ``ValueError`` too, as every other refusal of a value, so that code
    catching either sees it."""


def _anything(value: Any) -> bool:
    return True


@dataclass(frozen=True)
class ArgumentSpec:
    """What one argument accepts.

    :param rule: the sentence a refusal starts with, naming the argument and its valid values.
    :param types: the types accepted (``NONE`` for None); a bool is a number only where ``types`` holds ``bool``.
    :param in_range: whether a value of an accepted type is in range.
    :param names: the valid strings, for the nearest one in a refusal.
    :param type_rule: the sentence of a refusal for the wrong type, when it is not ``rule``.
    :param task_check: the check of the value against the task count N, where the range depends on N.
    """

    rule: str
    types: tuple[type, ...]
    in_range: Callable[[Any], bool] = _anything
    names: tuple[str, ...] = ()
    type_rule: str | None = None
    task_check: Callable[[Any, int], None] | None = None


# ------------------------------------------------------------------------------------------- spec builders
def _finite(value: Any) -> bool:
    return math.isfinite(float(value))


def integer(rule: str, low: int, high: float = math.inf, optional: bool = False) -> ArgumentSpec:
    """An int in ``[low, high]``, or None when ``optional``."""
    types = (Integral, NONE) if optional else (Integral,)
    return ArgumentSpec(rule, types, lambda value: value is None or low <= value <= high)


def number(rule: str, low: float, high: float = math.inf, ends: str = "[]", optional: bool = False) -> ArgumentSpec:
    """A finite number from ``low`` to ``high``; ``ends`` says which ends belong, as in ``"[]"`` or ``"(]"``."""

    def in_range(value: Any) -> bool:
        if value is None:
            return True
        above = value >= low if ends[0] == "[" else value > low
        below = value <= high if ends[1] == "]" else value < high
        return _finite(value) and above and below

    return ArgumentSpec(rule, (Real, NONE) if optional else (Real,), in_range)


def choice(name: str, names: tuple[str, ...], optional: bool = False) -> ArgumentSpec:
    """One of ``names``, or None when ``optional``."""
    rule = f"{name} must be {'None or ' if optional else ''}one of {names}"
    return ArgumentSpec(rule, (str, NONE) if optional else (str,), lambda value: value is None or value in names, names)


def flag(name: str) -> ArgumentSpec:
    return ArgumentSpec(f"{name} must be True or False", (bool,))


def instance(rule: str, *types: type) -> ArgumentSpec:
    """An instance of ``types``, or None."""
    return ArgumentSpec(rule, (*types, NONE))


# ------------------------------------------------------------------------------ ranges of the union arguments
def _positive_or_schedule(value: Any) -> bool:
    return callable(value) or (_finite(value) and value > 0)


def _train_freq_in_range(value: Any) -> bool:
    if isinstance(value, Integral):
        return value >= 1
    if len(value) != 2:
        return False
    frequency, unit = value
    positive = isinstance(frequency, Integral) and not isinstance(frequency, bool) and frequency >= 1
    return positive and getattr(unit, "value", unit) in TRAIN_FREQ_UNITS  # a str or SB3's TrainFrequencyUnit


def _ent_coef_in_range(value: Any) -> bool:
    if not isinstance(value, str):
        return _finite(value) and value > 0
    prefix, underscore, initial = value.partition("_")
    if prefix != "auto" or not underscore:
        return value == "auto"
    try:
        return _finite(initial) and float(initial) > 0
    except ValueError:
        return False


def _device_in_range(value: Any) -> bool:
    if isinstance(value, th.device) or value == "auto":
        return True
    try:
        th.device(value)
    except (RuntimeError, ValueError):
        return False
    return True


def _replay_buffer_class_in_range(value: Any) -> bool:
    return value is None or issubclass(value, ReplayBuffer)


def _positive_int(value: Any) -> bool:
    return isinstance(value, Integral) and not isinstance(value, bool) and value >= 1


def _widths(value: Any) -> bool:
    return isinstance(value, (list, tuple)) and all(_positive_int(width) for width in value)


def policy_kwargs_in_range(value: Any) -> bool:
    """Whether ``policy_kwargs`` gives positive widths in ``net_arch`` (a list, or a dict of lists by network) and a
    positive ``z_dim``, where it gives them."""
    if value is None:
        return True
    arch, z_dim = value.get("net_arch"), value.get("z_dim")
    arch_ok = arch is None or _widths(arch) or (isinstance(arch, Mapping) and all(map(_widths, arch.values())))
    return arch_ok and (z_dim is None or _positive_int(z_dim))


POLICY_KWARGS_RULE = (
    "policy_kwargs must be a dict or None, its net_arch positive widths such as [400, 400] "
    "(or a dict of them by network), its z_dim a positive int"
)


def check_buffer_holds_a_batch(buffer_size: int, batch_size: int, n_tasks: int) -> None:
    """:raises ValueError: unless every task's share of the buffer holds one batch of L = ``batch_size``."""
    if buffer_size // n_tasks < batch_size:
        raise ValueError(
            f"buffer_size={buffer_size} holds {buffer_size // n_tasks} transitions per task, fewer than one batch "
            f"(batch_size={batch_size} per task): give buffer_size >= N * batch_size = {n_tasks * batch_size}."
        )


MTSAC_ARGUMENTS: dict[str, ArgumentSpec] = {
    "learning_rate": ArgumentSpec(
        "learning_rate must be a positive number such as 3e-4 or a schedule", (Real, Callable), _positive_or_schedule
    ),
    "buffer_size": integer(
        "buffer_size (transitions over all tasks) must be a positive int such as 1_000_000 or int(1e6)", 1
    ),
    "learning_starts": integer("learning_starts (transitions over all tasks before learning) must be an int >= 0", 0),
    "batch_size": integer(
        "batch_size (L, transitions per task in every mini-batch) must be a positive int such as 128", 1
    ),
    "tau": number(
        "tau (Polyak coefficient of the target critics) must be a number in (0, 1] such as 0.005", 0, 1, "(]"
    ),
    "gamma": number("gamma (the discount factor) must be a number in [0, 1] such as 0.99", 0, 1),
    "train_freq": ArgumentSpec(
        "train_freq must be a positive int (vector steps) or a pair (n, 'step' or 'episode') with n >= 1",
        (Integral, tuple, list),
        _train_freq_in_range,
    ),
    "gradient_steps": ArgumentSpec(
        "gradient_steps must be an int >= 1, or -1 for one per vector step collected",
        (Integral,),
        lambda value: value == -1 or value >= 1,
    ),
    "ent_coef": ArgumentSpec(
        "ent_coef must be 'auto', 'auto_<initial value>' such as 'auto_0.1', or a positive number",
        (str, Real),
        _ent_coef_in_range,
    ),
    "target_entropy": ArgumentSpec(
        "target_entropy must be 'auto' (-dim(A)) or a finite number",
        (str, Real),
        lambda value: value == "auto" if isinstance(value, str) else _finite(value),
    ),
    "target_update_interval": integer("target_update_interval (gradient steps) must be a positive int", 1),
    "critic_arch": choice("critic_arch", CRITIC_ARCHS),
    "ent_coef_arch": choice("ent_coef_arch", ENT_COEF_ARCHS),
    "q_loss_clip": number("q_loss_clip (V_clip) must be a positive number or None", 0, ends="(]", optional=True),
    "gradient_surgery": choice("gradient_surgery", GRADIENT_SURGERY_METHODS, optional=True),
    "cagrad_c": number("cagrad_c must be a number in (0, 1)", 0, 1, "()"),
    "update_path": choice("update_path", UPDATE_PATHS),
    "overlap_env_step": flag("overlap_env_step"),
    "action_noise": instance("action_noise must be an SB3 ActionNoise or None", ActionNoise),
    "replay_buffer_class": ArgumentSpec(
        "replay_buffer_class must be a subclass of SB3's ReplayBuffer or None",
        (type, NONE),
        _replay_buffer_class_in_range,
    ),
    "replay_buffer_kwargs": instance("replay_buffer_kwargs must be a dict or None", Mapping),
    "stats_window_size": integer("stats_window_size (episodes) must be a positive int", 1),
    "tensorboard_log": instance("tensorboard_log must be a folder (a str or path) or None", str, os.PathLike),
    "policy_kwargs": ArgumentSpec(
        POLICY_KWARGS_RULE, (Mapping, NONE), policy_kwargs_in_range, type_rule="policy_kwargs must be a dict or None"
    ),
    "verbose": integer("verbose must be 0, 1 or 2", 0, 2),
    "seed": integer("seed must be None or an int in [0, 2**32)", 0, 2**32 - 1, optional=True),
    "device": ArgumentSpec(
        "device must be 'auto', 'cpu', 'cuda' or 'cuda:<index>' (a str or torch.device)",
        (str, th.device),
        _device_in_range,
    ),
    "_init_setup_model": flag("_init_setup_model"),
}
"""Every argument of :class:`~sb3_mtte.MTSAC` but ``policy`` (:func:`check_policy`) and ``env``."""


# ----------------------------------------------------------------------------------------------- the checks
def check_argument(name: str, value: Any, spec: ArgumentSpec) -> None:
    """:raises ArgumentTypeError: for a value of a type ``spec`` does not accept.
    :raises ValueError: for a value out of range, naming the nearest valid string where one is near."""
    if (isinstance(value, bool) and bool not in spec.types) or not isinstance(value, spec.types):
        rule = spec.type_rule or spec.rule
        raise ArgumentTypeError(f"{rule}, got {name}={value!r} ({type(value).__name__}).")
    if not spec.in_range(value):
        hint = did_you_mean(value, spec.names) if isinstance(value, str) else ""
        raise ValueError(f"{spec.rule}, got {name}={value!r}{': ' + hint if hint else '.'}")


def check_policy(policy: Any, algorithm: type) -> None:
    """:raises ValueError: for a policy name the algorithm does not have, naming the nearest and the valid ones.
    :raises ArgumentTypeError: for a policy that is neither a name nor an SB3 policy class."""
    names = tuple(algorithm.policy_aliases)
    valid = f"valid: {', '.join(names)}, or a policy class"
    if isinstance(policy, str):
        if policy in names:
            return
        owner = next((base for base in algorithm.__mro__[1:] if policy in getattr(base, "policy_aliases", {})), None)
        hint = f"it is {owner.__name__}'s;" if owner is not None else did_you_mean(policy, names)
        raise ValueError(
            f"policy {policy!r} is not a policy of {algorithm.__name__}: {hint + ' ' if hint else ''}{valid}."
        )
    if not (isinstance(policy, type) and issubclass(policy, BasePolicy)):
        raise ArgumentTypeError(
            f"policy must be a policy name of {algorithm.__name__} or an SB3 policy class, got {policy!r}: {valid}."
        )


def check_arguments(algorithm: type, arguments: Mapping[str, Any], n_tasks: int | None = None) -> None:
    """Check ``arguments`` against the policies of ``algorithm`` and its table (``algorithm.argument_specs``).

    Only the arguments of the table that ``arguments`` holds are checked: a constructor passes its ``locals()``,
    the command line its hyperparameters. With ``n_tasks``, the checks against the task count N run too, the
    buffer's room for one batch per task among them (the class's defaults standing in for what is not given).

    :param algorithm: the class, :class:`~sb3_mtte.MTSAC` or :class:`~sb3_mtte.MTSACTE`.
    :param arguments: the arguments by name.
    :param n_tasks: N, where it is known.
    :raises ArgumentTypeError: for a value of the wrong type.
    :raises ValueError: for a value out of range.
    """
    if "policy" in arguments:
        check_policy(arguments["policy"], algorithm)
    specs: Mapping[str, ArgumentSpec] = algorithm.argument_specs
    for name, spec in specs.items():
        if name in arguments:
            check_argument(name, arguments[name], spec)
            if spec.task_check is not None and n_tasks is not None:
                spec.task_check(arguments[name], n_tasks)
    if n_tasks is not None:
        defaults = inspect.signature(algorithm.__init__).parameters
        names = ("buffer_size", "batch_size")
        sizes = [arguments.get(name, getattr(defaults.get(name), "default", None)) for name in names]
        if all(isinstance(size, int) for size in sizes):
            check_buffer_holds_a_batch(*sizes, n_tasks)
