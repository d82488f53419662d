"""The registry of algorithm families, architectures and variants; one call registers each.

* a family (:func:`register_family`): an algorithm class, its base hyperparameter file and its optuna space;
* an architecture (:func:`register_architecture`): a policy class, under a name the families' ``policy``
  hyperparameter accepts;
* a variant (:func:`register_variant`): a zoo key, how to build it (:class:`Build`: family, policy,
  hyperparameters) and how to present it (its label in figures and tables, the published numbers).

The package's own families and variants are registered by :mod:`sb3_mtte.experiments.variants`; import the
registry from there.
"""

from __future__ import annotations

import fnmatch
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.policies import BasePolicy


@dataclass(frozen=True)
class Family:
    """An algorithm family: a class, its base hyperparameters and its optuna search space.

    :param key: zoo key of the family (its base hyperparameters, used as they are).
    :param algorithm: the algorithm class.
    :param sample_params: optuna search space (rl-zoo's sampler signature).
    :param config: name of the file ``zoo_configs/<config>.yml`` holding the base hyperparameters (default ``key``;
        a family built on another one's hyperparameters names that family's file).
    """

    key: str
    algorithm: type[BaseAlgorithm]
    sample_params: Callable[..., dict[str, Any]]
    config: str | None = None

    @property
    def config_name(self) -> str:
        return self.config or self.key


@dataclass(frozen=True)
class Build:
    """How to build a variant: its family, its policy and the hyperparameters that make it this variant.

    :param family: key of its family in :data:`FAMILIES`: its class and base hyperparameters.
    :param policy: the policy (hyperparameter ``policy``: a name of the family's ``policy_aliases``).
    :param overrides: hyperparameters set in every env entry of the family's file.
    :param env_overrides: further hyperparameters per env entry, keyed by a pattern of the entry (``"toy-*"``).
    """

    family: str
    policy: str = "MlpPolicy"
    overrides: Mapping[str, Any] = field(default_factory=dict)
    env_overrides: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)

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


@dataclass(frozen=True)
class Variant:
    """One algorithm variant: a zoo key, how to build it, and its name and published numbers.

    :param key: zoo algorithm key (``--algo``).
    :param label: its name in figures and tables (the paper's).
    :param build: how to build it.
    :param paper: published success rate (%) per benchmark: the paper's Table 1, or ``paper_source``'s.
    :param paper_source: where ``paper`` comes from when it is not the paper's Table 1.
    :param ablation_of: key of the variant it ablates (Fig. 7), if any.
    """

    key: str
    label: str
    build: Build
    paper: Mapping[str, float] = field(default_factory=dict)
    paper_source: str | None = None
    ablation_of: str | None = None


FAMILIES: dict[str, Family] = {}
"""Family key -> family."""
VARIANTS: dict[str, Variant] = {}
"""Zoo key -> variant, in the row order of Table 1 and then Fig. 7."""


def register_family(family: Family) -> Family:
    """Add an algorithm family (its key becomes a zoo key).

    :raises ValueError: for a key of a family or variant.
    :raises TypeError: for a class that is no SB3 algorithm.
    """
    if family.key in FAMILIES or family.key in VARIANTS:
        raise ValueError(f"A family or variant with the key {family.key!r} exists.")
    if not (isinstance(family.algorithm, type) and issubclass(family.algorithm, BaseAlgorithm)):
        raise TypeError(f"The algorithm of family {family.key!r} must be an SB3 algorithm class.")
    FAMILIES[family.key] = family
    return family


def unregister_family(key: str) -> Family:
    """Remove a family with no variant and return it."""
    users = [variant.key for variant in VARIANTS.values() if variant.build.family == key]
    if users:
        raise ValueError(f"Family {key!r} still has the variants {users}: unregister them first.")
    return FAMILIES.pop(key)


def _policy_aliases(family: str) -> dict[str, type[BasePolicy]]:
    """The ``policy_aliases`` of a family's class, made its own (not its base class's) before it changes."""
    if family not in FAMILIES:
        raise ValueError(f"Unknown family {family!r}: one of {sorted(FAMILIES)}.")
    algorithm = FAMILIES[family].algorithm
    if "policy_aliases" not in vars(algorithm):
        algorithm.policy_aliases = dict(algorithm.policy_aliases)
    return algorithm.policy_aliases


def register_architecture(name: str, policy_class: type[BasePolicy], family: str = "mtsac") -> type[BasePolicy]:
    """Make ``policy_class`` the family's policy ``name`` (in hyperparameters, ``Build.policy`` and the model).

    :raises ValueError: for an unknown family or a name the family knows.
    :raises TypeError: for a class that is no SB3 policy.
    """
    aliases = _policy_aliases(family)
    if name in aliases:
        raise ValueError(f"Family {family!r} has a policy {name!r}.")
    if not (isinstance(policy_class, type) and issubclass(policy_class, BasePolicy)):
        raise TypeError(f"Architecture {name!r} must be an SB3 policy class, got {policy_class!r}.")
    aliases[name] = policy_class
    return policy_class


def unregister_architecture(name: str, family: str = "mtsac") -> type[BasePolicy]:
    """Remove the family's policy ``name`` and return its class."""
    return _policy_aliases(family).pop(name)


def register_variant(variant: Variant) -> Variant:
    """Add a variant to :data:`VARIANTS` (zoo key, label, order, hyperparameters).

    :raises ValueError: for a known key or label, an unknown family, or a policy its family does not know.
    """
    family = variant.build.family
    if family not in FAMILIES:
        raise ValueError(f"Unknown family {family!r} of {variant.key!r}: one of {sorted(FAMILIES)}.")
    if variant.key in VARIANTS or variant.label in variant_labels():
        raise ValueError(f"A variant with the key {variant.key!r} or the label {variant.label!r} exists.")
    aliases = FAMILIES[family].algorithm.policy_aliases
    if variant.build.policy not in aliases:
        raise ValueError(
            f"Family {family!r} has no policy {variant.build.policy!r} (one of {sorted(aliases)}): "
            "register_architecture it first."
        )
    VARIANTS[variant.key] = variant
    return variant


def unregister_variant(key: str) -> Variant:
    """Remove a variant from :data:`VARIANTS` and return it."""
    return VARIANTS.pop(key)


def family_of(algo: str) -> Family | None:
    """The family of a zoo key (a family's or a variant's), None for another key."""
    key = VARIANTS[algo].build.family if algo in VARIANTS else algo
    return FAMILIES.get(key)


def algo_classes() -> dict[str, type[BaseAlgorithm]]:
    """Zoo key -> algorithm class, for the families and every variant."""
    classes = {key: family.algorithm for key, family in FAMILIES.items()}
    classes.update({key: variant.build.algorithm for key, variant in VARIANTS.items()})
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
    """The name of a run from its zoo key, or, for a family's key (``mtsac -conf my.yml``), the name of the family's
    variant its hyperparameters match (the one with the most overrides); the key itself when none matches.

    :param algo: zoo algorithm key (``"mtsacte"``, ``"mtsac_mh"``, ``"mtsac"``, ...).
    :param hyperparams: the run's hyperparameters (used for a family's key).
    """
    if algo in VARIANTS:
        return VARIANTS[algo].label
    if algo not in FAMILIES:
        return algo
    params = {"policy": "MlpPolicy", **(hyperparams or {})}
    params["policy"] = str(params["policy"]).split(".")[-1]
    matches = [
        variant
        for variant in VARIANTS.values()
        if variant.build.family == algo
        and all(key in params and params[key] == value for key, value in variant.build.defining_hyperparams().items())
    ]
    if not matches:
        return algo
    return max(matches, key=lambda variant: len(variant.build.overrides)).label
