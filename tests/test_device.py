"""``device="auto"`` picks CUDA when present, else the CPU; on a GPU machine every algorithm trains, saves and loads
there, on the default path (the fast path wherever the update allows it), on the eager path and on the fast path
asked for by name (these CUDA tests run wherever a GPU is present)."""

from __future__ import annotations

import pytest
import torch as th
from conftest import CUDA, small_model_kwargs

from sb3_mtte import MTSAC, MTSACTE, make_mt_env


def test_auto_device_is_cuda_when_present_else_cpu() -> None:
    model = MTSAC("MlpPolicy", make_mt_env("toy-conflict", seed=0), device="auto", policy_kwargs={"net_arch": [8]})
    assert model.device.type == ("cuda" if th.cuda.is_available() else "cpu")


EAGER = {"update_path": "eager", "replay_buffer_kwargs": {"storage": "host"}}
"""The eager path: each update's kernels launched one by one, the replay buffer in host memory."""
FAST_PATH = {"update_path": "cuda_graph", "replay_buffer_kwargs": {"storage": "device"}}
"""The fast path: the update replayed as a CUDA graph, the replay buffer's transitions on the GPU."""


@CUDA
@pytest.mark.parametrize(
    "cls, policy, kwargs, update_path, storage",
    [
        (MTSAC, "MlpPolicy", {}, "cuda_graph", "device"),
        (MTSAC, "MlpPolicy", {"gradient_surgery": "pcgrad"}, "eager", "device"),  # surgery reads the GPU on the host
        (MTSAC, "MOOREPolicy", {}, "cuda_graph", "device"),
        (MTSAC, "PaCoPolicy", {}, "eager", "device"),  # PaCo's reset reads the GPU on the host
        (MTSACTE, "MlpPolicy", {}, "cuda_graph", "device"),
        (MTSAC, "MlpPolicy", EAGER, "eager", "host"),
        (MTSACTE, "MlpPolicy", EAGER, "eager", "host"),
        (MTSAC, "MlpPolicy", FAST_PATH, "cuda_graph", "device"),
        (MTSACTE, "MlpPolicy", FAST_PATH, "cuda_graph", "device"),
    ],
)
def test_training_save_and_load_on_cuda(tmp_path, cls, policy: str, kwargs: dict, update_path: str, storage: str):
    base = small_model_kwargs(device="cuda")
    if cls is MTSAC:
        base = {key: base[key] for key in ("learning_starts", "batch_size", "buffer_size", "seed", "device")}
        base["policy_kwargs"] = {"net_arch": [16, 16]}
    model = cls(policy, make_mt_env("toy-conflict", seed=0), **base, **kwargs)
    model.learn(80)
    assert all(p.device.type == "cuda" for p in model.policy.parameters())
    assert model.resolved_update_path() == update_path and model.replay_buffer._storage() == storage
    model.save(tmp_path / "model")
    loaded = cls.load(tmp_path / "model", env=make_mt_env("toy-conflict", seed=0), device="cuda")
    obs = model.get_env().reset()
    assert (loaded.predict(obs, deterministic=True)[0] == model.predict(obs, deterministic=True)[0]).all()
