"""Statistics of every parameter after a short seeded run of each existing algorithm on toy-conflict.

``tests/data/variant_statistics.json`` holds, per case and tensor, how far training moved the tensor (the norm of
final minus initial values) and the tensor's projections on fixed random directions. A rerun matches them within
:data:`TOLERANCE` of the movement: the matmul kernels a CPU picks (AVX2, AVX512, AMX, ...) change the last bits of
every update, which stays about 1e-6 of the movement, while a real change of an algorithm's numbers (a learning rate
1% off, a term of a loss swapped) moves the parameters by 1e-3 or more of it (``tests/test_variant_statistics.py``
shows both). Write them from a checkout with::

    PYTHONPATH=<checkout> python tests/variant_statistics.py --write
"""

from __future__ import annotations

import json
import sys
import zlib
from pathlib import Path
from typing import Any

import sb3_mtte

sb3_mtte.tune_process()  # before torch loads, as the package's commands do

# isort: split

import numpy as np
import torch as th

from sb3_mtte import MTSAC, MTSACTE, make_mt_env

STATISTICS = Path(__file__).resolve().parent / "data" / "variant_statistics.json"
VECTOR_STEPS, START = 120, 40
N_PROJECTIONS = 8
TOLERANCE = 1e-4
"""Largest distance (:func:`distance`) from the stored statistics: kernel differences give about 1e-6, a learning
rate 1% off about 1e-2."""
CASE_TOLERANCE = {"softmod": 1e-2}
"""Soft modularization's actor drifts along directions its outputs do not depend on: any perturbation, a kernel's
last bit or a learning rate 1 + 1e-6 times the default, ends about 3e-3 away; a learning rate 1% off ends 4e-2 away."""
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
HOST_READING = ("pcgrad", "pcgrad_actor", "cagrad", "cagrad_actor", "paco", "paco_collapse")
"""Cases whose update reads the GPU on the host (gradient surgery's solve, PaCo's reset): no CUDA graph."""
CAPTURABLE_CASES = {name: case for name, case in CASES.items() if name not in HOST_READING}
CAPTURABLE_CASES["paco_without_reset"] = (
    MTSAC,
    "PaCoPolicy",
    {"policy_kwargs": {**SMALL, "task_loss_threshold": None}},
)
_COUNTS = "mu"  # integer counts: compared exactly


def build_case(name: str, **overrides: Any) -> Any:
    algorithm, policy, kwargs = CASES[name] if name in CASES else CAPTURABLE_CASES[name]
    kwargs = {"policy_kwargs": SMALL, "device": "cpu", **kwargs, **overrides}
    env = make_mt_env("toy-conflict", seed=0)
    return algorithm(
        policy, env, learning_starts=4 * START, batch_size=16, buffer_size=4 * VECTOR_STEPS, seed=0, **kwargs
    )


def final_tensors(model: Any) -> dict[str, np.ndarray]:
    """Every tensor of the policy (parameters and buffers), the entropy coefficients and MTSACTE's last transfer
    matrix, mu and w, in float64."""
    tensors = dict(model.policy.state_dict())
    tensors["ent_coef"] = model.entropy_coefficients
    for name in ("transfer_matrix", "mu", "task_weights"):
        if hasattr(model, name):
            tensors[name] = th.as_tensor(getattr(model, name))
    return {key: value.detach().cpu().double().numpy() for key, value in tensors.items()}


def directions(key: str, size: int) -> np.ndarray:
    """``(N_PROJECTIONS, size)`` standard normal directions, the same on every machine for a tensor name."""
    return np.random.Generator(np.random.PCG64(zlib.crc32(key.encode()))).standard_normal((N_PROJECTIONS, size))


def projections(tensors: dict[str, np.ndarray]) -> dict[str, list[float]]:
    return {key: [_short(x) for x in directions(key, value.size) @ value.ravel()] for key, value in tensors.items()}


def _short(value: float) -> float:
    return float(f"{value:.9g}")


def train_case(name: str, **overrides: Any) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Initial and final tensors of a case's run (one torch thread)."""
    threads = th.get_num_threads()
    th.set_num_threads(1)
    try:
        model = build_case(name, **overrides)
        initial = {key: value.detach().double().numpy().copy() for key, value in model.policy.state_dict().items()}
        model.learn(4 * VECTOR_STEPS)
        return initial, final_tensors(model)
    finally:
        th.set_num_threads(threads)


def case_statistics(name: str, **overrides: Any) -> dict[str, Any]:
    """Per tensor: ``moved`` (norm of final - initial; of the final value for a tensor with no initial value) and
    ``projections``; ``mu`` as it is."""
    initial, final = train_case(name, **overrides)
    moved = {key: _short(np.linalg.norm(value - initial.get(key, 0.0))) for key, value in final.items()}
    stats: dict[str, Any] = {"moved": moved, "projections": projections(final)}
    if _COUNTS in final:
        stats[_COUNTS] = final[_COUNTS].astype(int).tolist()
    return stats


def distance(stats: dict[str, Any], stored: dict[str, Any]) -> float:
    """Root-mean-square change of the projections over every tensor, relative to the norm of every tensor's
    movement: about ||final - stored final|| / ||stored final - initial||."""
    if set(stats["projections"]) != set(stored["projections"]):
        return float("inf")
    if stats.get(_COUNTS) != stored.get(_COUNTS):
        return float("inf")
    squared = sum(
        float(np.sum((np.asarray(stats["projections"][key]) - np.asarray(stored["projections"][key])) ** 2))
        for key in stored["projections"]
    )
    scale = sum(value**2 for value in stored["moved"].values())
    return float(np.sqrt(squared / N_PROJECTIONS / scale))


def tolerance(name: str) -> float:
    return CASE_TOLERANCE.get(name, TOLERANCE)


def stored_statistics() -> dict[str, Any]:
    return json.loads(STATISTICS.read_text())


if __name__ == "__main__":
    names = [arg for arg in sys.argv[1:] if arg in CASES] or list(CASES)
    statistics = {name: case_statistics(name) for name in names}
    if "--write" in sys.argv:
        lines = [f"{json.dumps(name)}: {json.dumps(stats)}" for name, stats in statistics.items()]
        STATISTICS.write_text("{\n" + ",\n".join(lines) + "\n}\n")
    else:
        print(json.dumps(statistics))
