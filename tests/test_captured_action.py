"""Acting replayed as a CUDA graph (:mod:`sb3_mtte.common.captured_action`): the policy's eager ``act``, captured.

On the CPU the tests run the wrapper without capture (``capture=False``: the warm-up calls, the static inputs and the
copy out), which gives the eager path's actions bit for bit, and check that the defaults capture acting only on
CUDA. The graph itself, its pinned copy and the advance of its random draws between replays run only in the CUDA
tests, which compare it with the eager path."""

from __future__ import annotations

import numpy as np
import pytest
import torch as th
from conftest import CUDA
from variant_statistics import VECTOR_STEPS, build_case, final_tensors

from sb3_mtte import MTSAC, make_mt_env
from sb3_mtte.common import captured_action, gpu_defaults
from sb3_mtte.common.captured_action import CapturedAction, action_runner, resolve_action_path

ACTING_CASES = ("mt", "mh", "softmod", "ind", "moore", "paco", "mtsacte")
"""Every actor: shared, multi-head, soft modular, independent, MOORE, PaCo, and E_phi then the actor (MTSACTE)."""
MODES = [False] * 6 + [True] * 5 + [False] * 2
"""``deterministic`` of successive calls: each mode past its warm-up, captured, replayed, and back."""


def observations(model) -> list[np.ndarray]:
    """One batch of observations per call of :data:`MODES`, each with other states (the same one-hots)."""
    first = model.get_env().reset()
    n = model.n_tasks
    return [np.concatenate([first[:, :-n] + 0.05 * i, first[:, -n:]], axis=1) for i in range(len(MODES))]


def actions(model, runner, batches: list[np.ndarray]) -> list[np.ndarray]:
    """The actions ``predict`` gives for ``batches`` in :data:`MODES`, from one seed, with ``runner`` acting."""
    model.policy.action_runner = runner
    th.manual_seed(5)
    return [model.predict(obs, deterministic=mode)[0] for obs, mode in zip(batches, MODES, strict=True)]


@pytest.mark.parametrize("case", ACTING_CASES)
def test_the_wrapper_without_capture_gives_the_eager_actions_bit_for_bit(case):
    model = build_case(case)
    batches = observations(model)
    eager = actions(model, None, batches)
    runner = CapturedAction(model.policy.act, model.device, capture=False)
    wrapped = actions(model, runner, batches)
    assert all(np.array_equal(got, expected) for got, expected in zip(wrapped, eager, strict=True))
    assert len(runner.static_observations) == 2, "both modes ran on the static inputs after their warm-up"
    assert set(runner.warmup_calls.values()) == {runner.WARMUP} == {3}


def test_the_wrapper_hands_back_actions_of_their_own():
    model = build_case("mt")
    runner = CapturedAction(model.policy.act, model.device, capture=False)
    obs = th.as_tensor(model.get_env().reset())
    returned = [runner(obs) for _ in range(runner.WARMUP + 2)]
    host = next(iter(runner.host_actions.values()))
    assert all(a.device.type == "cpu" and a.data_ptr() != host.data_ptr() for a in returned)
    assert not th.equal(returned[-2], returned[-1]), "a later call leaves an earlier one's actions alone"


@pytest.mark.parametrize("case", ["mt", "mtsacte"])
def test_the_graph_path_without_the_graph_acts_through_the_wrapper_and_trains_as_the_eager_path(case):
    eager = build_case(case)
    assert eager.policy.action_runner is None
    eager.learn(4 * VECTOR_STEPS)
    other = build_case(case)
    other._setup_update_path(capture=False)
    runner = other.policy.action_runner
    assert isinstance(runner, CapturedAction) and not runner.capture
    other.learn(4 * VECTOR_STEPS)
    assert runner.static_observations, "acting ran on the static inputs"
    expected, got = final_tensors(eager), final_tensors(other)
    assert all(np.array_equal(got[key], expected[key]) for key in expected)


def test_the_fast_path_defaults_capture_acting_only_on_cuda(monkeypatch):
    assert captured_action.CAPTURE_ACTING is False, "opt-in until measured on a GPU"
    monkeypatch.setattr(captured_action, "CAPTURE_ACTING", True)
    cpu, cuda = th.device("cpu"), th.device("cuda")
    for fast in (True, False):
        monkeypatch.setattr(gpu_defaults, "FAST_PATH_BY_DEFAULT", fast)
        assert [resolve_action_path(path, cpu) for path in ("auto", "eager", "cuda_graph")] == ["eager"] * 3
        assert resolve_action_path("auto", cuda) == ("cuda_graph" if fast else "eager")
        assert resolve_action_path("cuda_graph", cuda) == "cuda_graph"
        assert resolve_action_path("eager", cuda) == "eager"
    monkeypatch.setattr(captured_action, "CAPTURE_ACTING", False)
    assert [resolve_action_path(path, cuda) for path in ("auto", "eager", "cuda_graph")] == ["eager"] * 3
    act = build_case("mt").policy.act
    assert action_runner("eager", act, cuda) is None
    runner = action_runner("cuda_graph", act, cuda)
    assert isinstance(runner, CapturedAction) and runner.capture and runner.device == cuda
    model = MTSAC("MlpPolicy", make_mt_env("toy-conflict", seed=0), device="cpu", policy_kwargs={"net_arch": [8]})
    assert model.update_path == "auto" and model.policy.action_runner is None


# ---------------------------------------------------------------------------------------------------------- CUDA
@CUDA
@pytest.mark.parametrize("case", ACTING_CASES)
def test_the_acting_graph_gives_the_eager_actions_on_cuda(case):
    """From one seed the replays draw the noise the eager calls draw, so the actions agree to float rounding."""
    model = build_case(case, device="cuda", update_path="eager")
    assert model.policy.action_runner is None
    batches = observations(model)
    eager = actions(model, None, batches)
    runner = CapturedAction(model.policy.act, model.device)
    graph = actions(model, runner, batches)
    assert len(runner.graphs) == 2 and all(host.is_pinned() for host in runner.host_actions.values())
    for got, expected in zip(graph, eager, strict=True):
        np.testing.assert_allclose(got, expected, rtol=0, atol=1e-5)
    obs = th.as_tensor(batches[0], device="cuda")
    first, second = runner(obs), runner(obs)
    assert (first - second).abs().max() > 1e-3, "each replay draws new noise"


@CUDA
@pytest.mark.parametrize("case", ["mt", "moore", "mtsacte"])
def test_the_fast_path_acts_through_its_graph_while_it_trains_on_cuda(case, tmp_path, monkeypatch):
    monkeypatch.setattr(captured_action, "CAPTURE_ACTING", True)  # opt-in
    model = build_case(case, device="cuda")
    runner = model.policy.action_runner
    assert isinstance(runner, CapturedAction) and runner.capture
    model.learn(4 * VECTOR_STEPS)
    assert runner.graphs and model.resolved_update_path() == "cuda_graph"
    model.save(tmp_path / "model")
    loaded = type(model).load(tmp_path / "model", env=make_mt_env("toy-conflict", seed=0), device="cuda")
    obs = model.get_env().reset()
    for _ in range(CapturedAction.WARMUP + 2):  # warm-up, capture, replay
        assert np.array_equal(loaded.predict(obs, deterministic=True)[0], model.predict(obs, deterministic=True)[0])
    assert loaded.policy.action_runner.graphs
