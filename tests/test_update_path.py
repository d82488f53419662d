"""The update's two paths (:mod:`sb3_mtte.mtsac.update_path`): the CUDA-graph path runs the eager update's code on
static inputs, with tensor learning rates and the host's reads deferred to the logger's dump.

On the CPU the tests run the path minus capture (``capture=False``: the static inputs, the warm-up calls, the tensor
learning rates and the deferred reads), which gives the eager path's parameters bit for bit. That proves the
path's bookkeeping, not the graph: the side stream, the capturable optimizers, ``torch.cuda.CUDAGraph`` and its
replay run only in the CUDA tests, which compare the graph with the eager path within float tolerance."""

from __future__ import annotations

import csv
import json
from collections import namedtuple
from pathlib import Path

import numpy as np
import pytest
import torch as th
from stable_baselines3.common.logger import configure
from conftest import CUDA
from variant_statistics import CAPTURABLE_CASES, CASES, HOST_READING, VECTOR_STEPS, build_case, final_tensors

from sb3_mtte import MTSAC, make_mt_env
from sb3_mtte.common import gpu_defaults
from sb3_mtte.common.captured_update import CapturedUpdate, prepare_for_capture
from sb3_mtte.common.device_storage import resolve_storage
from sb3_mtte.evaluation import MultiTaskEvalCallback


def graph_path_without_graph(model):
    model._setup_update_path(capture=False)
    return model


def trained(model, steps: int = 4 * VECTOR_STEPS, **learn_kwargs):
    model.learn(steps, **learn_kwargs)
    return model


@pytest.mark.parametrize("case", list(CAPTURABLE_CASES))
def test_the_graph_path_minus_capture_gives_the_eager_parameters_on_the_cpu(case):
    eager = trained(build_case(case))
    assert eager.resolved_update_path() == "eager"
    other = trained(graph_path_without_graph(build_case(case)))
    assert other.update_monitor.deferred and other._update_runner.warmup_calls == other._update_runner.WARMUP
    assert other._update_runner.static_batch is not None, "the updates after the warm-up ran on the static inputs"
    expected, got = final_tensors(eager), final_tensors(other)
    assert all(np.array_equal(got[key], expected[key]) for key in expected)


def test_a_learning_rate_schedule_reaches_the_tensor_learning_rates():
    def schedule(progress_remaining: float) -> float:
        return 1e-3 * progress_remaining

    eager = trained(build_case("mt", learning_rate=schedule))
    other = trained(graph_path_without_graph(build_case("mt", learning_rate=schedule)))
    lr = other.actor.optimizer.param_groups[0]["lr"]
    assert isinstance(lr, th.Tensor) and float(lr) == eager.actor.optimizer.param_groups[0]["lr"] < 1e-3
    expected, got = final_tensors(eager), final_tensors(other)
    assert all(np.array_equal(got[key], expected[key]) for key in expected)


def progress_rows(folder) -> list[dict[str, str]]:
    with open(folder / "progress.csv", newline="") as file:
        return [{k: v for k, v in row.items() if not k.startswith("time/")} for row in csv.DictReader(file)]


def dumps_of(dumper: str) -> dict:
    """``learn``'s arguments that make the logger dump: SB3's ``log_interval``, or only an evaluation's dump."""
    if dumper == "log_interval":
        return {"log_interval": 1}
    return {
        "log_interval": 10**6,
        "callback": MultiTaskEvalCallback("toy-conflict", eval_freq=50, episodes_per_task=1),
    }


@pytest.mark.parametrize(("case", "dumper"), [("clip", "log_interval"), ("mtsacte", "log_interval"), ("clip", "eval")])
def test_deferred_reads_log_what_the_eager_path_logs(tmp_path, case, dumper):
    """Every dump carries the same train statistics on both paths, the dumps an evaluation makes included."""
    folders = []
    for name in ("eager", "graph"):  # each built right before it trains: the seed sets the global RNGs
        model = build_case(case) if name == "eager" else graph_path_without_graph(build_case(case))
        model.set_logger(configure(str(tmp_path / name), ["csv"]))
        trained(model, **dumps_of(dumper))
        folders.append(tmp_path / name)
    eager, graph = (progress_rows(folder) for folder in folders)
    assert len(eager) >= 2 and [row.keys() for row in graph] == [row.keys() for row in eager]
    for got, expected in zip(graph, eager, strict=True):  # means over updates: summed in another order
        assert {k: float(v or "nan") for k, v in got.items()} == pytest.approx(
            {k: float(v or "nan") for k, v in expected.items()}, rel=1e-6, nan_ok=True
        )
    assert sum(bool(row.get("train/critic_loss")) for row in eager) >= 2


def nan_rewards_model():
    model = graph_path_without_graph(build_case("mt"))
    model.learn(2 * VECTOR_STEPS)
    model.replay_buffer.rewards[:] = np.nan
    return model


def test_a_non_finite_loss_stops_training_at_the_next_read_naming_the_update_and_the_env_step(tmp_path):
    model = nan_rewards_model()
    updates_before = model._n_updates
    model.train(2, 16)  # deferred: no read of the device
    with pytest.raises(
        FloatingPointError,
        match=rf"critic loss is not finite \(first at update {updates_before + 1}, env step {model.num_timesteps}\)",
    ):
        model.update_monitor.check()
    with pytest.raises(FloatingPointError, match="critic loss is not finite"):
        model.save(tmp_path / "model")  # no checkpoint of a broken model
    model = nan_rewards_model()
    with pytest.raises(FloatingPointError, match="critic loss is not finite"):
        model.learn(40, log_interval=1, reset_num_timesteps=False)


def test_a_loaded_model_names_the_update_of_its_whole_run_and_a_new_runner_keeps_what_the_old_one_saw(tmp_path):
    """The update named in the error counts from the run's start, not from the load; a non-finite loss marked
    before the runner is rebuilt (``set_parameters``) is raised, not dropped."""
    model = trained(build_case("mt"))
    model.save(tmp_path / "model")
    loaded = graph_path_without_graph(MTSAC.load(tmp_path / "model", env=make_mt_env("toy-conflict", seed=0)))
    loaded.replay_buffer = model.replay_buffer
    loaded.set_logger(configure(str(tmp_path / "log"), ["csv"]))
    loaded.replay_buffer.rewards[:] = np.nan
    loaded.train(1, 16)
    with pytest.raises(FloatingPointError, match=rf"first at update {model._n_updates + 1},"):
        loaded.update_monitor.check()
    with pytest.raises(FloatingPointError, match="critic loss is not finite"):
        loaded.set_parameters(loaded.get_parameters())


def test_a_checkpoint_of_the_graph_path_trains_on_the_cpu(tmp_path):
    """A model saved with capturable optimizers (the graph path's, tensor learning rates) loads on the CPU with its
    optimizers made plain again, and trains on."""
    model = trained(graph_path_without_graph(build_case("mt")))
    for optimizer in model._optimizers():
        for group in optimizer.param_groups:
            group["capturable"] = True
    model.save(tmp_path / "model")
    loaded = MTSAC.load(tmp_path / "model", env=make_mt_env("toy-conflict", seed=0), device="cpu")
    assert not any(g["capturable"] for o in loaded._optimizers() for g in o.param_groups)
    loaded.learn(200, reset_num_timesteps=False)


def test_a_new_batch_size_is_warmed_up_again_before_its_capture():
    """The first WARMUP calls of each batch size run eagerly on the caller's batch, the later ones on the static
    copy that the graph reads."""
    on_static_inputs = []

    def update(batch, polyak):
        on_static_inputs.append(batch is runner.static_batch)
        return {}

    runner = CapturedUpdate(update, list, th.device("cpu"), capture=False)
    batch = namedtuple("Batch", "observations")
    for size in (4, 4, 4, 4, 4, 8, 8, 8, 8):
        runner(batch(th.zeros(size)), True)
    assert runner.WARMUP == 3
    assert on_static_inputs == [False, False, False, True, True, False, False, False, True]


def test_auto_takes_the_fast_path_on_cuda_once_the_device_check_has_run(monkeypatch):
    """No default that has never run on a GPU: the fast path is the default exactly when the device check's committed
    report says its CUDA tests passed. Without it, ``"auto"`` is eager and the host's buffer on CUDA too; with it,
    the graph wherever the update's hooks allow it, and the GPU's buffer where it fits."""
    path = Path(__file__).resolve().parents[1] / "docs" / "results" / "gpu_check.json"
    tests = json.loads(path.read_text()).get("cuda_tests", {}) if path.exists() else {}
    passed = tests.get("rc") == 0 and " passed" in tests.get("summary", "") and "failed" not in tests["summary"]
    assert gpu_defaults.FAST_PATH_BY_DEFAULT == passed, tests
    monkeypatch.setattr(gpu_defaults, "FAST_PATH_BY_DEFAULT", False)
    cuda = th.device("cuda")
    for case in CASES:
        model = build_case(case)
        monkeypatch.setattr(model, "device", cuda)
        assert model.resolved_update_path() == "eager", case
    assert resolve_storage("auto", cuda, n_bytes=1) == "host"
    monkeypatch.setattr(gpu_defaults, "FAST_PATH_BY_DEFAULT", True)
    monkeypatch.setattr(th.cuda, "mem_get_info", lambda device: (100, 200))
    assert resolve_storage("auto", cuda, n_bytes=50) == "device" and resolve_storage("auto", cuda, 51) == "pinned"
    assert resolve_storage("auto", th.device("cpu"), n_bytes=1) == "host"
    for case in CASES:
        model = build_case(case)
        assert model.resolved_update_path() == "eager", case  # the CPU
        monkeypatch.setattr(model, "device", cuda)
        assert model.resolved_update_path() == ("eager" if case in HOST_READING else "cuda_graph"), case
        if case in HOST_READING:
            model.update_path = "cuda_graph"
            with pytest.raises(ValueError, match="reads the GPU on the host every step"):
                model.resolved_update_path()


def test_the_graph_path_makes_its_optimizers_capturable_before_its_warm_up():
    """The warm-up's eager updates take the optimizers' capturable branch, as the graph and the CUDA test's eager
    reference do from their first step; without capture (the CPU) the optimizers stay plain."""
    model = build_case("mt")
    optimizers = model._optimizers()
    assert len(optimizers) == 3  # the actor's, the critic's, the entropy coefficients'
    CapturedUpdate(model._update, model._optimizers, th.device("cuda"), capture=True)  # nothing runs yet
    assert all(group["capturable"] for optimizer in optimizers for group in optimizer.param_groups)
    CapturedUpdate(model._update, model._optimizers, th.device("cpu"), capture=False)
    assert not any(group["capturable"] for optimizer in optimizers for group in optimizer.param_groups)


def test_bad_update_paths_are_refused():
    with pytest.raises(ValueError, match="update_path must be one of"):
        MTSAC("MlpPolicy", make_mt_env("toy-conflict", seed=0), update_path="graph", device="cpu")
    with pytest.raises(ValueError, match="needs a CUDA device"):
        MTSAC("MlpPolicy", make_mt_env("toy-conflict", seed=0), update_path="cuda_graph", device="cpu")


SMALL_TENSORS = ("ent_coef", "task_weights", "transfer_matrix")
"""Tensors of :func:`final_tensors` compared each on its own: in the policy's sum their error would vanish."""


def relative_distance(a: dict[str, np.ndarray], b: dict[str, np.ndarray], initial: dict[str, np.ndarray]) -> float:
    """||a - b|| over how far training moved b from ``initial``, over the keys of ``initial``."""
    error = sum(float(np.sum((a[k] - b[k]) ** 2)) for k in initial)
    moved = sum(float(np.sum((b[k] - initial[k]) ** 2)) for k in initial)
    return (error / moved) ** 0.5 if moved else (0.0 if error == 0 else np.inf)


def assert_near_eager(got: dict, expected: dict, initial: dict, tolerance: float) -> None:
    """The graph's final tensors against the eager path's: the policy's tensors together, the entropy coefficients,
    MTSACTE's w and transfer matrix each within ``tolerance`` of how far training moved them; mu (counts) exactly."""
    assert got.keys() == expected.keys() == initial.keys()
    groups = {"policy": [k for k in initial if k not in (*SMALL_TENSORS, "mu")]}
    groups |= {k: [k] for k in SMALL_TENSORS if k in initial}
    for name, keys in groups.items():
        distance = relative_distance({k: got[k] for k in keys}, expected, {k: initial[k] for k in keys})
        assert distance < tolerance, f"{name}: {distance:.2e} of the movement"
    if "mu" in initial:
        assert np.array_equal(got["mu"], expected["mu"]), "mu"


def test_the_comparison_with_the_eager_path_reads_the_entropy_coefficients_mu_and_w():
    rng = np.random.default_rng(0)
    initial = {"actor.weight": np.zeros(1000), "ent_coef": np.ones(4), "mu": np.zeros(4)}
    initial |= {"task_weights": np.full(4, 0.25), "transfer_matrix": np.zeros((4, 4))}
    expected = {k: v + rng.standard_normal(v.shape) * (1 if k != "mu" else 0) for k, v in initial.items()}
    expected["mu"] = np.array([0.0, 1.0, 2.0, 1.0])
    assert_near_eager({k: v.copy() for k, v in expected.items()}, expected, initial, 1e-3)
    for key in ("actor.weight", *SMALL_TENSORS, "mu"):  # each off by a hundredth of its movement, mu by one
        got = {k: v.copy() for k, v in expected.items()}
        got[key] = got[key] + (1 if key == "mu" else 0.01 * (expected[key] - initial[key]))
        with pytest.raises(AssertionError, match=key if key in (*SMALL_TENSORS, "mu") else "policy"):
            assert_near_eager(got, expected, initial, 1e-3)


@CUDA
@pytest.mark.parametrize(
    "case, overrides",
    [(case, {}) for case in CAPTURABLE_CASES]
    + [
        ("mt", {"target_update_interval": 2, "gradient_steps": 2})  # both graphs: with and without the Polyak step
    ],
)
def test_the_cuda_graph_gives_the_eager_parameters_on_cuda(case, overrides):
    """The eager reference runs its optimizers as the graph does from its first step (capturable, float32 learning
    rates): their bias corrections then round alike, so that MTSACTE's sign counts cannot flip on rounding alone."""
    eager_model = build_case(case, device="cuda", update_path="eager", **overrides)
    for optimizer in eager_model._optimizers():
        prepare_for_capture(optimizer, capturable=True)
    initial = final_tensors(eager_model)
    eager = final_tensors(trained(eager_model))
    graph_model = trained(build_case(case, device="cuda", update_path="cuda_graph", **overrides))
    assert graph_model.resolved_update_path() == "cuda_graph" and graph_model._update_runner.graphs
    assert len(graph_model._update_runner.graphs) == (2 if overrides else 1)
    assert_near_eager(final_tensors(graph_model), eager, initial, 1e-2 if case == "softmod" else 1e-3)
