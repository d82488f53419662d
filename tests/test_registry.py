"""A new algorithm family and a new architecture, added through the registry alone, train with the zoo."""

from __future__ import annotations

from typing import Any

import pytest
import torch as th
from conftest import ENV, tiny_train

from sb3_mtte import MTSAC
from sb3_mtte.common.update_hooks import UpdateHook
from sb3_mtte.experiments.playback import evaluate_model as evaluate
from sb3_mtte.experiments.run_info import read_run_info
from sb3_mtte.experiments.variants import (
    FAMILIES,
    VARIANTS,
    Build,
    Family,
    Variant,
    label_of,
    register_architecture,
    register_family,
    register_variant,
    sample_mtsac_params,
    unregister_architecture,
    unregister_family,
    unregister_variant,
)
from sb3_mtte.experiments.zoo.configs import zoo_hyperparameters
from sb3_mtte.experiments.zoo.run_checkpoints import load_model
from sb3_mtte.mtsac.policies import MTSACPolicy

RECORDS: list[dict[str, th.Tensor]] = []
"""What the family's hook saw in every update of the run."""


class CriticLossWeights(UpdateHook):
    """Actor weights: a softmax of the tasks' critic losses over ``temperature``."""

    def __init__(self, temperature: float) -> None:
        self.temperature = temperature

    def loss_mask(self, task_losses: th.Tensor) -> th.Tensor:
        self.weights = th.softmax(task_losses / self.temperature, dim=0)
        RECORDS.append({"losses": task_losses.clone(), "weights": self.weights})
        return th.ones_like(task_losses)

    def task_weights(self) -> th.Tensor:
        return self.weights


class LossWeightedMTSAC(MTSAC):
    """A family: MTSAC whose actor weights the tasks by their critic losses."""

    def __init__(self, *args: Any, weight_temperature: float = 1.0, **kwargs: Any) -> None:
        self.weight_temperature = weight_temperature
        super().__init__(*args, **kwargs)

    def update_hooks(self) -> list[UpdateHook]:
        return [*super().update_hooks(), CriticLossWeights(self.weight_temperature)]


class NarrowActorPolicy(MTSACPolicy):
    """An architecture: the actor one hidden layer of ``actor_width``, the critics as given."""

    def __init__(self, *args: Any, actor_width: int = 8, net_arch: Any = None, **kwargs: Any) -> None:
        self.actor_width = actor_width
        super().__init__(*args, net_arch={"pi": [actor_width], "qf": net_arch or [16, 16]}, **kwargs)

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(actor_width=self.actor_width, net_arch=self.net_arch["qf"])
        return data


FAMILY, ARCHITECTURE, KEY = "mtsac_lossweighted", "NarrowActorPolicy", "lossweighted_narrow"


@pytest.fixture
def registered():
    """The family, its architecture and one variant of both, registered for one test."""
    register_family(Family(FAMILY, LossWeightedMTSAC, sample_mtsac_params, config="mtsac"))
    register_architecture(ARCHITECTURE, NarrowActorPolicy, family=FAMILY)
    build = Build(
        FAMILY,
        ARCHITECTURE,
        overrides={"weight_temperature": 0.5},
        env_overrides={"toy-*": {"policy_kwargs": {"actor_width": 12, "net_arch": [16, 16]}}},
    )
    register_variant(Variant(KEY, "LossWeighted-narrow", build))
    RECORDS.clear()
    yield
    unregister_variant(KEY)
    unregister_architecture(ARCHITECTURE, family=FAMILY)
    unregister_family(FAMILY)


def test_a_family_and_an_architecture_registered_alone_train_with_the_zoo(registered, tmp_path):
    assert zoo_hyperparameters(FAMILY) == zoo_hyperparameters("mtsac")  # the family's base is mtsac's file
    run = tiny_train(tmp_path, KEY, "-params", "learning_starts:200", steps=400)
    info = read_run_info(run)
    assert info["label"] == "LossWeighted-narrow" and info["hyperparams"]["policy"] == ARCHITECTURE
    model = load_model(run / f"{ENV}.zip")
    assert type(model) is LossWeightedMTSAC and model.weight_temperature == 0.5
    assert type(model.policy) is NarrowActorPolicy and model.policy.actor_width == 12
    in_dim, out_dim = model.observation_space.shape[0], 2 * model.action_space.shape[0]
    assert sum(p.numel() for p in model.actor.parameters()) == (in_dim + 1) * 12 + (12 + 1) * out_dim
    assert model._n_updates > 0 and len(RECORDS) == model._n_updates  # the family's hook ran in every update
    for record in RECORDS:
        th.testing.assert_close(record["weights"], th.softmax(record["losses"] / 0.5, dim=0))
    assert evaluate.main([str(run / f"{ENV}.zip"), "--episodes", "1"])["label"] == "LossWeighted-narrow"


def test_the_family_uses_its_weights_in_the_actor_update(registered, monkeypatch):
    """The actor step gets the hook's weights (not MTSAC's uniform 1/N)."""
    from sb3_mtte import make_mt_env

    model = LossWeightedMTSAC(ARCHITECTURE, make_mt_env(ENV), learning_starts=64, batch_size=8, seed=0)
    received = []
    actor_step = model._actor_step

    def recording_actor_step(task_losses, task_weights):
        received.append(task_weights.clone())
        return actor_step(task_losses, task_weights)

    monkeypatch.setattr(model, "_actor_step", recording_actor_step)
    model.learn(80)
    assert len(received) == len(RECORDS) > 0
    for weights, record in zip(received, RECORDS, strict=True):
        assert th.equal(weights, record["weights"])


def test_registering_is_checked_and_leaves_the_base_family_alone(registered):
    assert ARCHITECTURE in LossWeightedMTSAC.policy_aliases and ARCHITECTURE not in MTSAC.policy_aliases
    assert label_of(FAMILY, {"policy": ARCHITECTURE, "weight_temperature": 0.5}) == "LossWeighted-narrow"
    assert label_of("mtsac_lossweighted_x", {"policy": ARCHITECTURE}) == "mtsac_lossweighted_x"
    with pytest.raises(ValueError, match="exists"):
        register_family(Family(FAMILY, MTSAC, sample_mtsac_params))
    with pytest.raises(TypeError, match="SB3 algorithm class"):
        register_family(Family("other", dict, sample_mtsac_params))  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="has a policy"):
        register_architecture(ARCHITECTURE, NarrowActorPolicy, family=FAMILY)
    with pytest.raises(TypeError, match="SB3 policy class"):
        register_architecture("Other", dict, family=FAMILY)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="Unknown family"):
        register_architecture("Other", NarrowActorPolicy, family="no-family")
    with pytest.raises(ValueError, match="register_architecture it first"):
        register_variant(Variant("other", "Other", Build("mtsac", ARCHITECTURE)))
    with pytest.raises(ValueError, match="unregister them first"):
        unregister_family(FAMILY)
    assert FAMILY in FAMILIES and KEY in VARIANTS
