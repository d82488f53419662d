"""The algorithm variants: one entry per row of the paper's Table 1 and Fig. 7, and everything known about it.

A variant is a zoo key (``--algo``), its algorithm family (class and base hyperparameter file
``sb3_mtte/zoo_configs/<family>.yml``), its policy, the hyperparameters that make it this variant, its name in figures and
tables, and the paper's numbers. Zoo keys, labels, the order of Table 1, the benchmark's variants and the
hyperparameters of each key come from :data:`VARIANTS`. Adding a variant is one call::

    register_variant(Variant("mtsac_mh_tau", "SAC-MT-MH-tau", "mtsac", "MultiHeadPolicy", overrides={"tau": 0.02}))

(plus its policy or algorithm class when it is new).
"""

from __future__ import annotations

import fnmatch
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from stable_baselines3.common.base_class import BaseAlgorithm

from sb3_mtte.mtsac import MTSAC
from sb3_mtte.mtsacte import MTSACTE


def sample_mtsac_params(trial: Any, n_actions: int, n_envs: int, additional_args: dict) -> dict[str, Any]:
    """Optuna search space of the MTSAC family (architecture fixed by the hyperparameter file)."""
    trial.suggest_float("learning_rate", 1e-4, 1e-3, log=True)
    trial.suggest_float("one_minus_gamma", 0.002, 0.03, log=True)
    trial.suggest_float("tau", 0.001, 0.02, log=True)
    trial.suggest_int("batch_size_pow", 6, 8)
    return convert_trial_params(trial.params)


def sample_mtsacte_params(trial: Any, n_actions: int, n_envs: int, additional_args: dict) -> dict[str, Any]:
    """Optuna search space of MTSACTE: the MTSAC one plus alpha_nt, c_vae and the J^rep steps per iteration."""
    sample_mtsac_params(trial, n_actions, n_envs, additional_args)
    trial.suggest_float("nt_step_size", 1e-4, 1e-2, log=True)
    trial.suggest_float("c_vae", 1e-3, 1.0, log=True)
    trial.suggest_categorical("rep_gradient_steps", [1, 5, 10, 20])
    return convert_trial_params(trial.params)


def convert_trial_params(params: dict[str, Any]) -> dict[str, Any]:
    """Optuna trial parameters -> model keyword arguments."""
    kwargs = dict(params)
    if "one_minus_gamma" in kwargs:
        kwargs["gamma"] = 1.0 - kwargs.pop("one_minus_gamma")
    if "batch_size_pow" in kwargs:
        kwargs["batch_size"] = 2 ** kwargs.pop("batch_size_pow")
    return kwargs


@dataclass(frozen=True)
class Family:
    """An algorithm family: a class and its base hyperparameter file ``sb3_mtte/zoo_configs/<key>.yml``.

    :param key: zoo key of the family (the base hyperparameters, used as they are) and name of its file.
    :param algorithm: the algorithm class.
    :param sample_params: optuna search space (rl-zoo's sampler signature).
    """

    key: str
    algorithm: type[BaseAlgorithm]
    sample_params: Callable[..., dict[str, Any]]


FAMILIES: dict[str, Family] = {
    "mtsac": Family("mtsac", MTSAC, sample_mtsac_params),
    "mtsacte": Family("mtsacte", MTSACTE, sample_mtsacte_params),
}
"""Family key -> family."""


@dataclass(frozen=True)
class Variant:
    """One algorithm variant.

    :param key: zoo algorithm key (``--algo``).
    :param label: its name in figures and tables (the paper's).
    :param family: key of its family in :data:`FAMILIES`: its class and base hyperparameters.
    :param policy: the policy (hyperparameter ``policy``).
    :param overrides: hyperparameters that make it this variant, set in every env entry of the family's file.
    :param env_overrides: further hyperparameters per env entry, keyed by a pattern of the entry (``"toy-*"``).
    :param paper: published success rate (%) per benchmark: the paper's Table 1, or ``paper_source``'s.
    :param paper_source: where ``paper`` comes from when it is not the paper's Table 1.
    :param ablation_of: key of the variant it ablates (Fig. 7), if any.
    """

    key: str
    label: str
    family: str
    policy: str = "MlpPolicy"
    overrides: Mapping[str, Any] = field(default_factory=dict)
    env_overrides: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    paper: Mapping[str, float] = field(default_factory=dict)
    paper_source: str | None = None
    ablation_of: str | None = None

    @property
    def algorithm(self) -> type[BaseAlgorithm]:
        return FAMILIES[self.family].algorithm

    def defining_hyperparams(self) -> dict[str, Any]:
        """The hyperparameters that tell this variant from its family's base: policy and overrides."""
        return {"policy": self.policy, **self.overrides}

    def compose(self, env_key: str, base: Mapping[str, Any]) -> dict[str, Any]:
        """Hyperparameters of this variant for one env entry: the family's entry plus the overrides."""
        hyperparams = {**base, **self.defining_hyperparams()}
        for pattern, values in self.env_overrides.items():
            if fnmatch.fnmatchcase(env_key, pattern):
                hyperparams.update(values)
        return hyperparams


_CAGRAD_TABLE3 = (
    "Liu et al. 2021 (CAGrad), Table 3: mean of 10 runs on mtrl's multi-task SAC, 2M env steps per task, on the "
    "Meta-World of Feb 2021 that their README pins (commit d9a75c4), not Meta-World v3"
)
# MOORE's and PaCo's MT10 success as their papers report it (MT10-rand, Meta-World v2); the "reported" column of
# Meta-World+'s multi-task table lists the same values beside its own re-runs.
_REPORTED = (
    "{0}, MT10 results table (MT10-rand: goal positions resampled, Meta-World v2); Meta-World+ (McLean et al., "
    "NeurIPS 2025) lists the same reported value and re-ran the method at {1}% (V2 rewards, 10 seeds, IQM)"
)
_SOFT_MODULAR = "actor_kwargs=dict(n_layers={0}, n_modules={0}, module_size={1})"
# MOORE, Meta-World MT10: k = 4 experts (metaworld-algorithms config/nn.py MOOREConfig, the authors' values: "4 for
# MT10 and 6 for MT50"), MOORE in actor and critic (metaworld-algorithms examples/multi_task/moore_mt10.py), widths
# 2 x 400 (the package's Meta-World nets; metaworld-algorithms' width is 400).
_MOORE = "dict(net_arch=[{0}, {0}], n_experts=4)"
# PaCo, Meta-World MT10: K = 5 parameter sets, compositional actor and critic, reset threshold 3e3 on a task's loss
# (TToTMooN/paco-mtrl paco/examples/metaworld_mt10_paco_conf.py: num_of_param_set, use_compositional_encoding,
# critic_use_compositional_encoding, task_loss_threshold), widths 2 x 400 (their hidden sizes live outside that repo).
_PACO = "dict(net_arch=[{0}, {0}], n_parameter_sets=5, task_loss_threshold=3000.0)"

METAWORLD_ENTRIES = ("MT*", "DEV6*")
"""Patterns of the Meta-World env entries of the hyperparameter files (the toy entries are ``toy-*``)."""

VARIANTS: dict[str, Variant] = {}
"""Zoo key -> variant, in the row order of Table 1 and then Fig. 7."""


def register_variant(variant: Variant) -> Variant:
    """Add a variant to :data:`VARIANTS` (zoo key, label, order, hyperparameters).

    :raises ValueError: for a known key or label, or an unknown family.
    """
    if variant.family not in FAMILIES:
        raise ValueError(f"Unknown family {variant.family!r} of {variant.key!r}: one of {sorted(FAMILIES)}.")
    if variant.key in VARIANTS or variant.label in variant_labels():
        raise ValueError(f"A variant with the key {variant.key!r} or the label {variant.label!r} exists.")
    VARIANTS[variant.key] = variant
    return variant


def unregister_variant(key: str) -> Variant:
    """Remove a variant from :data:`VARIANTS` and return it."""
    return VARIANTS.pop(key)


def algo_classes() -> dict[str, type[BaseAlgorithm]]:
    """Zoo key -> algorithm class, for the families and every variant."""
    classes = {key: family.algorithm for key, family in FAMILIES.items()}
    classes.update({key: variant.algorithm for key, variant in VARIANTS.items()})
    return classes


def variant_labels() -> list[str]:
    """Labels of the variants in the order of Table 1, then Fig. 7."""
    return [variant.label for variant in VARIANTS.values()]


def ablation_labels() -> list[str]:
    """Fig. 7: the ablated variants' labels, each ablated one first (``["Ours", "Ours-VAE", ...]``)."""
    labels: list[str] = []
    for variant in VARIANTS.values():
        if variant.ablation_of is not None:
            base = VARIANTS[variant.ablation_of].label
            labels += [label for label in (base, variant.label) if label not in labels]
    return labels


def paper_sources() -> dict[str, str]:
    """Label -> source of its published numbers, for the variants whose numbers are not the paper's Table 1."""
    return {variant.label: variant.paper_source for variant in VARIANTS.values() if variant.paper_source}


def paper_table1() -> dict[str, dict[str, float]]:
    """Published success (%): label -> benchmark -> success, for the variants with published numbers (the paper's
    Table 1 on Meta-World v2, or :func:`paper_sources`)."""
    return {variant.label: dict(variant.paper) for variant in VARIANTS.values() if variant.paper}


def label_of(algo: str, hyperparams: Mapping[str, Any] | None = None) -> str:
    """The name of a run from its zoo key, or, for another key of a family (``mtsac``, ``mtsac_x``), the name of
    the family's variant its hyperparameters match (the one with the most overrides).

    :param algo: zoo algorithm key (``"mtsacte"``, ``"mtsac_mh"``, ``"mtsac"``, ...).
    :param hyperparams: the run's hyperparameters (used for keys that are no variant's).
    """
    if algo in VARIANTS:
        return VARIANTS[algo].label
    family = max((key for key in FAMILIES if algo.startswith(key)), key=len, default=None)
    if family is None:
        return algo
    params = {"policy": "MlpPolicy", **(hyperparams or {})}
    params["policy"] = str(params["policy"]).split(".")[-1]
    matches = [
        variant
        for variant in VARIANTS.values()
        if variant.family == family
        and all(key in params and params[key] == value for key, value in variant.defining_hyperparams().items())
    ]
    if not matches:
        return algo
    return max(matches, key=lambda variant: len(variant.overrides)).label


for _variant in (
    Variant("mtsac_ind", "SAC-Ind", "mtsac", "IndependentPolicy", paper={"MT10": 94.0, "MT20": 94.1}),
    Variant("mtsac_mt", "SAC-MT", "mtsac", paper={"MT10": 74.3, "MT20": 56.2}),
    Variant("mtsac_mh", "SAC-MT-MH", "mtsac", "MultiHeadPolicy", paper={"MT10": 76.9, "MT20": 65.3}),
    Variant(
        "mtsac_softmod",
        "SAC-soft-modular",
        "mtsac",
        "SoftModularPolicy",
        env_overrides={
            **dict.fromkeys(
                METAWORLD_ENTRIES, {"policy_kwargs": f"dict(net_arch=[400, 400], {_SOFT_MODULAR.format(4, 128)})"}
            ),
            "toy-*": {"policy_kwargs": f"dict(net_arch=[64, 64], {_SOFT_MODULAR.format(2, 32)})"},
        },
        paper={"MT10": 83.3, "MT20": 65.0},
    ),
    Variant(
        "mtsac_clip", "SAC-MT-with-clip", "mtsac", overrides={"q_loss_clip": 2000}, paper={"MT10": 85.9, "MT20": 65.5}
    ),
    Variant("mtsacte", "Ours", "mtsacte", paper={"MT10": 89.3, "MT20": 70.1}),
    # Gradient surgery on the shared actor (and on the critic when it is shared); no MT20 number is published.
    # c = 0.5: the CAGrad authors' Meta-World agent config (Cranial-XIX/CAGrad, mtrl/mtrl_files/cagrad_state_sac.yaml).
    Variant(
        "mtsac_pcgrad",
        "PCGrad",
        "mtsac",
        overrides={"gradient_surgery": "pcgrad"},
        paper={"MT10": 72.0},
        paper_source=_CAGRAD_TABLE3,
    ),
    Variant(
        "mtsac_cagrad",
        "CAGrad",
        "mtsac",
        overrides={"gradient_surgery": "cagrad", "cagrad_c": 0.5},
        paper={"MT10": 83.0},
        paper_source=_CAGRAD_TABLE3,
    ),
    Variant(
        "mtsac_moore",
        "MOORE",
        "mtsac",
        "MOOREPolicy",
        env_overrides={
            **dict.fromkeys(METAWORLD_ENTRIES, {"policy_kwargs": _MOORE.format(400)}),
            "toy-*": {"policy_kwargs": _MOORE.format(64)},
        },
        paper={"MT10": 88.7},
        paper_source=_REPORTED.format("Hendawi et al. (ICLR 2024)", 83.2),
    ),
    Variant(
        "mtsac_paco",
        "PaCo",
        "mtsac",
        "PaCoPolicy",
        env_overrides={
            **dict.fromkeys(METAWORLD_ENTRIES, {"policy_kwargs": _PACO.format(400)}),
            "toy-*": {"policy_kwargs": _PACO.format(64)},
        },
        paper={"MT10": 85.4},
        paper_source=_REPORTED.format("Sun et al. (NeurIPS 2022)", 73.6),
    ),
    Variant("mtsacte_novae", "Ours-VAE", "mtsacte", overrides={"use_vae": False}, ablation_of="mtsacte"),
    Variant("mtsacte_noclip", "Ours-clip", "mtsacte", overrides={"q_loss_clip": None}, ablation_of="mtsacte"),
    Variant("mtsacte_nobestbatch", "Ours-bestbatch", "mtsacte", overrides={"use_topk": False}, ablation_of="mtsacte"),
):
    register_variant(_variant)


__all__ = [
    "FAMILIES",
    "VARIANTS",
    "Family",
    "Variant",
    "ablation_labels",
    "algo_classes",
    "label_of",
    "paper_sources",
    "paper_table1",
    "register_variant",
    "unregister_variant",
    "variant_labels",
]
