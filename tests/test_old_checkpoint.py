"""Models saved by an earlier version of the package load with today's code, with every saved tensor in place.

``tests/data/old_checkpoints/`` holds small models (2 x 16 networks, 400 env steps on toy-conflict, no replay buffer)
of MTSAC with a learned per-task, a shared and a fixed beta, with soft modularization, MOORE and PaCo, and of
MTSACTE. Each test reads the zip's tensors with torch alone and compares them with the loaded model's.
"""

from __future__ import annotations

import io
import json
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch as th

from sb3_mtte import MTSAC, MTSACTE, make_mt_env

CHECKPOINTS = Path(__file__).resolve().parent / "data" / "old_checkpoints"
NAMES = sorted(path.stem for path in CHECKPOINTS.glob("*.zip"))


def algorithm_of(name: str) -> type[MTSAC]:
    return MTSACTE if name.startswith("mtsacte") else MTSAC


def stored(path: Path, member: str) -> dict:
    """A ``.pth`` member of a saved model's zip, read by torch alone."""
    with zipfile.ZipFile(path) as archive:
        return th.load(io.BytesIO(archive.read(f"{member}.pth")), map_location="cpu", weights_only=False)


def stored_data(path: Path) -> bytes:
    with zipfile.ZipFile(path) as archive:
        return archive.read("data")


def assert_same_optimizer_state(optimizer: th.optim.Optimizer, saved: dict, name: str) -> None:
    state = optimizer.state_dict()["state"]
    assert state.keys() == saved["state"].keys(), name
    for index, entries in saved["state"].items():
        for key, value in entries.items():
            assert th.equal(th.as_tensor(state[index][key]).cpu(), th.as_tensor(value)), (name, index, key)


def test_every_algorithm_and_temperature_has_an_old_checkpoint():
    assert set(NAMES) == {
        "mtsac_fixed_ent_coef",
        "mtsac_mlp",
        "mtsac_moore",
        "mtsac_paco",
        "mtsac_shared",
        "mtsac_soft_modular",
        "mtsacte",
    }
    assert all((CHECKPOINTS / f"{name}.zip").stat().st_size < 200_000 for name in NAMES)


@pytest.mark.parametrize("name", NAMES)
def test_an_old_checkpoint_loads_with_its_tensors_and_predicts(name):
    path = CHECKPOINTS / f"{name}.zip"
    model = algorithm_of(name).load(path, device="cpu")
    saved_policy = stored(path, "policy")
    loaded_policy = model.policy.state_dict()
    assert loaded_policy.keys() == saved_policy.keys()
    for key, value in saved_policy.items():
        assert th.equal(loaded_policy[key], value), key
    for member, optimizer in (("actor.optimizer", model.actor.optimizer), ("critic.optimizer", model.critic.optimizer)):
        assert_same_optimizer_state(optimizer, stored(path, member), member)
    variables = stored(path, "pytorch_variables")
    if name == "mtsac_fixed_ent_coef":
        assert model.ent_coef_optimizer is None and th.equal(model.ent_coef_tensor, variables["ent_coef_tensor"])
    else:
        assert th.equal(model.log_ent_coef.detach(), variables["log_ent_coef"])
        assert_same_optimizer_state(model.ent_coef_optimizer, stored(path, "ent_coef_optimizer"), "ent_coef")
        assert th.equal(model.entropy_coefficients, variables["log_ent_coef"].exp().expand(model.n_tasks))
    obs = make_mt_env("toy-conflict", seed=0).reset()
    actions, _ = model.predict(obs, deterministic=True)
    assert actions.shape == (4, 2) and np.all(np.abs(actions) <= 1.0)


@pytest.mark.parametrize("name", ["mtsac_mlp", "mtsac_fixed_ent_coef", "mtsacte"])
def test_an_old_checkpoint_trains_on(name):
    """Loaded with an env, the model takes updates from its loaded optimizer states."""
    path = CHECKPOINTS / f"{name}.zip"
    model = algorithm_of(name).load(path, env=make_mt_env("toy-conflict", seed=1), device="cpu")
    before = {key: value.clone() for key, value in model.policy.state_dict().items()}
    model.learn(160)  # 100 env steps of warm-up, then updates
    assert model._n_updates > json.loads(stored_data(path))["_n_updates"]
    moved = [key for key, value in model.policy.state_dict().items() if not th.equal(value, before[key])]
    assert any(key.startswith("actor.") for key in moved) and any(key.startswith("critic.") for key in moved)
