"""Digests of every parameter after a short seeded run of each existing algorithm on toy-conflict.

``tests/data/variant_digests.json`` holds the digests of the code they were written with; a refactoring of the update
that keeps them keeps every algorithm's numbers bit for bit. Write them from a checkout with::

    PYTHONPATH=<checkout> python tests/variant_digests.py --write
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path
from typing import Any

import sb3_mtte  # noqa: F401  # first: the package sets OpenMP's spin-wait before torch loads

# isort: split

import torch as th

from sb3_mtte import MTSAC, MTSACTE, make_mt_env

DIGESTS = Path(__file__).resolve().parent / "data" / "variant_digests.json"
VECTOR_STEPS, START = 120, 40
SMALL = {"net_arch": [32, 32]}
_AUTHORS = {"critic_arch": "shared", "ent_coef_arch": "shared"}
_TE = {"iteration_length": 30, "rep_gradient_steps": 2, "top_k": 3}
CASES: dict[str, tuple[type, str, dict[str, Any]]] = {
    "mt": (MTSAC, "MlpPolicy", {}),
    "mh": (MTSAC, "MultiHeadPolicy", {}),
    "softmod": (MTSAC, "SoftModularPolicy", {"policy_kwargs": {**SMALL, "actor_kwargs": {"n_layers": 2}}}),
    "ind": (MTSAC, "IndependentPolicy", {}),
    "clip": (MTSAC, "MlpPolicy", {"q_loss_clip": 1.0}),
    "pcgrad": (MTSAC, "MlpPolicy", {"gradient_surgery": "pcgrad", **_AUTHORS}),
    "pcgrad_actor": (MTSAC, "MlpPolicy", {"gradient_surgery": "pcgrad"}),
    "cagrad": (MTSAC, "MlpPolicy", {"gradient_surgery": "cagrad", "cagrad_c": 0.9, **_AUTHORS}),
    "cagrad_actor": (MTSAC, "MlpPolicy", {"gradient_surgery": "cagrad"}),
    "moore": (MTSAC, "MOOREPolicy", {"policy_kwargs": {**SMALL, "n_experts": 3}}),
    "paco": (MTSAC, "PaCoPolicy", {"policy_kwargs": {**SMALL, "n_parameter_sets": 3}}),
    # A threshold the toy's critic losses cross: masks and resets take part in the run.
    "paco_collapse": (MTSAC, "PaCoPolicy", {"policy_kwargs": {**SMALL, "task_loss_threshold": 0.7}}),
    "mtsacte": (MTSACTE, "MlpPolicy", _TE),
    "mtsacte_one_pass": (MTSACTE, "MlpPolicy", {**_TE, "nt_chunk_size": None}),
    "mtsacte_gradient_dot": (MTSACTE, "MlpPolicy", {**_TE, "nt_estimator": "gradient_dot"}),
}


def train_case(name: str) -> Any:
    algorithm, policy, kwargs = CASES[name]
    kwargs = {"policy_kwargs": SMALL, **kwargs}
    env = make_mt_env("toy-conflict", seed=0)
    model = algorithm(
        policy,
        env,
        learning_starts=4 * START,
        batch_size=16,
        buffer_size=4 * VECTOR_STEPS,
        seed=0,
        device="cpu",
        **kwargs,
    )
    model.learn(4 * VECTOR_STEPS)
    return model


def parameter_digest(model: Any) -> str:
    """sha256 of every tensor of the policy (parameters and buffers), the entropy coefficients and MTSACTE's last
    transfer matrix, mu and w."""
    tensors = dict(model.policy.state_dict())
    tensors["ent_coef"] = model.entropy_coefficients
    for name in ("transfer_matrix", "mu", "task_weights"):
        if hasattr(model, name):
            tensors[name] = th.as_tensor(getattr(model, name))
    digest = hashlib.sha256()
    for key in sorted(tensors):
        digest.update(key.encode())
        digest.update(tensors[key].detach().cpu().contiguous().numpy().tobytes())
    return digest.hexdigest()


def case_digest(name: str) -> str:
    threads = th.get_num_threads()
    th.set_num_threads(1)
    try:
        return parameter_digest(train_case(name))
    finally:
        th.set_num_threads(threads)


if __name__ == "__main__":
    digests = {name: case_digest(name) for name in CASES}
    print(json.dumps(digests, indent=1))
    if "--write" in sys.argv:
        DIGESTS.write_text(json.dumps(digests, indent=1) + "\n")
