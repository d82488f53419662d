"""The update's two paths (:mod:`sb3_mtte.mtsac.update_path`): the CUDA-graph path runs the eager update's code on
static inputs, with tensor learning rates and the host's reads deferred to the logger's dump. On the CPU it runs
without the graph (everything else of the path) and gives the eager path's parameters bit for bit; on CUDA, with
the graph, within float tolerance."""

from __future__ import annotations

import csv
from collections import namedtuple

import numpy as np
import pytest
import torch as th
from stable_baselines3.common.logger import configure
from conftest import CUDA
from variant_statistics import CAPTURABLE_CASES, CASES, HOST_READING, VECTOR_STEPS, build_case, final_tensors

from sb3_mtte import MTSAC, make_mt_env
from sb3_mtte.common.evaluation import MultiTaskEvalCallback
from sb3_mtte.common.captured_update import CapturedUpdate, prepare_for_capture


def graph_path_without_graph(model):
    model._setup_update_path(capture=False)
    return model


def trained(model, steps: int = 4 * VECTOR_STEPS, **learn_kwargs):
    model.learn(steps, **learn_kwargs)
    return model


@pytest.mark.parametrize("case", list(CAPTURABLE_CASES))
def test_the_graph_path_gives_the_eager_parameters_on_the_cpu(case):
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


def test_auto_takes_the_graph_on_cuda_unless_the_update_reads_the_host(monkeypatch):
    for case in CASES:
        model = build_case(case)
        monkeypatch.setattr(model, "device", th.device("cuda"))
        expected = "eager" if case in HOST_READING else "cuda_graph"
        assert model.resolved_update_path() == expected, case
        if case in HOST_READING:
            model.update_path = "cuda_graph"
            with pytest.raises(ValueError, match="reads the GPU on the host every step"):
                model.resolved_update_path()


def test_bad_update_paths_are_refused():
    with pytest.raises(ValueError, match="update_path must be one of"):
        MTSAC("MlpPolicy", make_mt_env("toy-conflict", seed=0), update_path="graph", device="cpu")
    with pytest.raises(ValueError, match="needs a CUDA device"):
        MTSAC("MlpPolicy", make_mt_env("toy-conflict", seed=0), update_path="cuda_graph", device="cpu")


def relative_distance(a: dict[str, np.ndarray], b: dict[str, np.ndarray], initial: dict[str, np.ndarray]) -> float:
    error = sum(float(np.sum((a[k] - b[k]) ** 2)) for k in initial)
    moved = sum(float(np.sum((a[k] - initial[k]) ** 2)) for k in initial)
    return (error / moved) ** 0.5


@CUDA
@pytest.mark.parametrize(
    "case, overrides",
    [(case, {}) for case in CAPTURABLE_CASES]
    + [
        ("mt", {"target_update_interval": 2, "gradient_steps": 2})  # both graphs: with and without the Polyak step
    ],
)
def test_the_cuda_graph_gives_the_eager_parameters_on_cuda(case, overrides):
    """The eager reference runs its optimizers as the graph does (capturable, float32 learning rates): their bias
    corrections then round alike, so that MTSACTE's sign counts cannot flip on rounding alone."""
    eager_model = build_case(case, device="cuda", update_path="eager", **overrides)
    for optimizer in eager_model._optimizers():
        prepare_for_capture(optimizer, capturable=True)
    initial = {k: v.detach().cpu().double().numpy() for k, v in eager_model.policy.state_dict().items()}
    eager = final_tensors(trained(eager_model))
    graph_model = trained(build_case(case, device="cuda", **overrides))
    assert graph_model.resolved_update_path() == "cuda_graph" and graph_model._update_runner.graphs
    assert len(graph_model._update_runner.graphs) == (2 if overrides else 1)
    assert relative_distance(final_tensors(graph_model), eager, initial) < (1e-2 if case == "softmod" else 1e-3)
