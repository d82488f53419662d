"""The package's algorithm families and variants: one variant per row of the paper's Table 1 and Fig. 7.

A variant is a zoo key (``--algo``), how to build it (:class:`~sb3_mtte.experiments.registry.Build`: its family's
class and base hyperparameter file ``zoo_configs/<family>.yml``, its policy, the hyperparameters that make it this
variant), its name in figures and tables, and the published numbers. Zoo keys, labels, the order of Table 1, the
benchmark's variants and the hyperparameters of each key come from :data:`VARIANTS`. Adding a family, an
architecture or a variant is one call each (:mod:`sb3_mtte.experiments.registry`)::

    register_family(Family("mtsac_mine", MyMTSAC, sample_mtsac_params, config="mtsac"))
    register_architecture("MyPolicy", MyPolicy, family="mtsac_mine")
    register_variant(Variant("mine", "Mine", Build("mtsac_mine", "MyPolicy", overrides={"tau": 0.02})))
"""

from __future__ import annotations

from typing import Any

from sb3_mtte.experiments.registry import (
    FAMILIES,
    VARIANTS,
    Build,
    Family,
    Variant,
    ablation_labels,
    algo_classes,
    family_of,
    label_of,
    paper_sources,
    paper_table1,
    register_architecture,
    register_family,
    register_variant,
    unregister_architecture,
    unregister_family,
    unregister_variant,
    variant_labels,
)
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


for _family in (
    Family("mtsac", MTSAC, sample_mtsac_params),
    Family("mtsacte", MTSACTE, sample_mtsacte_params),
):
    register_family(_family)


_CAGRAD_TABLE3 = (
    "Liu et al. 2021 (CAGrad), Table 3: mean of 10 runs on mtrl's multi-task SAC (one critic and one entropy "
    "coefficient for every task, the method on the critic, actor and entropy-coefficient losses), 2M env steps per "
    "task, on the Meta-World of Feb 2021 that their README pins (commit d9a75c4), not Meta-World v3"
)
# PCGrad and CAGrad as their authors ran them on Meta-World (mtrl's gradient-manipulation agents, the commands of
# Cranial-XIX/CAGrad mtrl/mtrl_files/run.sh): one critic and one entropy coefficient for every task
# (should_use_disentangled_alpha=False), the method applied to the critic, actor and entropy-coefficient losses.
_SURGERY_AUTHORS = {"critic_arch": "shared", "ent_coef_arch": "shared"}
CAGRAD_C: dict[str, float] = {"MT10*": 0.9, "MT20*": 0.9, "MT25*": 0.9, "MT50*": 0.5, "DEV6*": 0.9, "toy-*": 0.9}
"""CAGrad's c per env entry pattern (zoo key ``mtsac_cagrad``): the authors' Meta-World commands (Cranial-XIX/CAGrad,
``mtrl/mtrl_files/run.sh``, ``cagrad_method=cagrad``) run MT10 with c = 0.9 and MT50 with c = 0.5. MT20, MT25, DEV6
and the toy have no command of theirs and take MT10's value: MT10 is the nearest task count, and the authors' solver
treats every task count but 50 as MT10's (its step size). A task list takes MT10's entry, so c = 0.9."""
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


def _on_metaworld(policy_kwargs: str) -> dict[str, dict[str, str]]:
    """The same ``policy_kwargs`` for every Meta-World entry, each in a dict of its own."""
    return {entry: {"policy_kwargs": policy_kwargs} for entry in METAWORLD_ENTRIES}


def _reported_variant(
    key: str, label: str, policy: str, policy_kwargs: str, mt10: tuple[float, float], source: str
) -> Variant:
    """A variant of a method not in the paper: its policy at 2 x 400 on Meta-World and 2 x 64 on the toys, with the
    MT10 success its authors report and Meta-World+'s re-run (``mt10``)."""
    env_overrides = {**_on_metaworld(policy_kwargs.format(400)), "toy-*": {"policy_kwargs": policy_kwargs.format(64)}}
    reported, rerun = mt10
    return Variant(
        key,
        label,
        Build("mtsac", policy, env_overrides=env_overrides),
        paper={"MT10": reported},
        paper_source=_REPORTED.format(source, rerun),
    )


for _variant in (
    Variant("mtsac_ind", "SAC-Ind", Build("mtsac", "IndependentPolicy"), paper={"MT10": 94.0, "MT20": 94.1}),
    Variant("mtsac_mt", "SAC-MT", Build("mtsac"), paper={"MT10": 74.3, "MT20": 56.2}),
    Variant("mtsac_mh", "SAC-MT-MH", Build("mtsac", "MultiHeadPolicy"), paper={"MT10": 76.9, "MT20": 65.3}),
    Variant(
        "mtsac_softmod",
        "SAC-soft-modular",
        Build(
            "mtsac",
            "SoftModularPolicy",
            env_overrides={
                **_on_metaworld(f"dict(net_arch=[400, 400], {_SOFT_MODULAR.format(4, 128)})"),
                "toy-*": {"policy_kwargs": f"dict(net_arch=[64, 64], {_SOFT_MODULAR.format(2, 32)})"},
            },
        ),
        paper={"MT10": 83.3, "MT20": 65.0},
    ),
    Variant(
        "mtsac_clip",
        "SAC-MT-with-clip",
        Build("mtsac", overrides={"q_loss_clip": 2000}),
        paper={"MT10": 85.9, "MT20": 65.5},
    ),
    Variant("mtsacte", "Ours", Build("mtsacte"), paper={"MT10": 89.3, "MT20": 70.1}),
    # Gradient surgery as its authors ran it on Meta-World (no MT20 number is published), then on the actor alone.
    Variant(
        "mtsac_pcgrad",
        "PCGrad",
        Build("mtsac", overrides={"gradient_surgery": "pcgrad", **_SURGERY_AUTHORS}),
        paper={"MT10": 72.0},
        paper_source=_CAGRAD_TABLE3,
    ),
    Variant(
        "mtsac_cagrad",
        "CAGrad",
        Build(
            "mtsac",
            overrides={"gradient_surgery": "cagrad", **_SURGERY_AUTHORS},
            env_overrides={pattern: {"cagrad_c": c} for pattern, c in CAGRAD_C.items()},
        ),
        paper={"MT10": 83.0},
        paper_source=_CAGRAD_TABLE3,
    ),
    Variant("mtsac_pcgrad_actor", "PCGrad-actor", Build("mtsac", overrides={"gradient_surgery": "pcgrad"})),
    Variant(
        "mtsac_cagrad_actor",
        "CAGrad-actor",
        Build("mtsac", overrides={"gradient_surgery": "cagrad", "cagrad_c": 0.5}),
    ),
    _reported_variant("mtsac_moore", "MOORE", "MOOREPolicy", _MOORE, (88.7, 83.2), "Hendawi et al. (ICLR 2024)"),
    _reported_variant("mtsac_paco", "PaCo", "PaCoPolicy", _PACO, (85.4, 73.6), "Sun et al. (NeurIPS 2022)"),
    Variant("mtsacte_novae", "Ours-VAE", Build("mtsacte", overrides={"use_vae": False}), ablation_of="mtsacte"),
    Variant("mtsacte_noclip", "Ours-clip", Build("mtsacte", overrides={"q_loss_clip": None}), ablation_of="mtsacte"),
    Variant(
        "mtsacte_nobestbatch", "Ours-bestbatch", Build("mtsacte", overrides={"use_topk": False}), ablation_of="mtsacte"
    ),
):
    register_variant(_variant)


__all__ = [
    "CAGRAD_C",
    "FAMILIES",
    "VARIANTS",
    "Build",
    "Family",
    "Variant",
    "ablation_labels",
    "algo_classes",
    "convert_trial_params",
    "family_of",
    "label_of",
    "paper_sources",
    "paper_table1",
    "register_architecture",
    "register_family",
    "register_variant",
    "sample_mtsac_params",
    "sample_mtsacte_params",
    "unregister_architecture",
    "unregister_family",
    "unregister_variant",
    "variant_labels",
]
