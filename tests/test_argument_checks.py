"""Every argument of MTSAC and MTSACTE is checked for its type and its range before any work: a wrong value ends with
one line that names the argument and its valid values, or the nearest valid name, from Python and from ``-params``."""

from __future__ import annotations

import inspect
import math
import re

import pytest
from conftest import ENV, TINY, small_model_kwargs
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm

from sb3_mtte import MTSAC, MTSACTE
from sb3_mtte.experiments.cli import main

# Each argument: a value of a wrong type, and one of the right type out of range (None where every value of the
# right type is valid).
MTSAC_BAD_VALUES = {
    "learning_rate": ("3e-4", -1e-3),
    "buffer_size": (1e6, 0),
    "learning_starts": (1.5, -1),
    "batch_size": (2.5, 0),
    "tau": ("0.005", 5),
    "gamma": ("0.99", 1.5),
    "train_freq": (1.5, 0),
    "gradient_steps": (1.0, 0),
    "ent_coef": ([0.1], "auto_0"),
    "target_entropy": ([-2.0], math.nan),
    "target_update_interval": (1.5, 0),
    "critic_arch": (1, "per_tsk"),
    "ent_coef_arch": (None, "per_sample"),
    "q_loss_clip": ("2000", 0.0),
    "gradient_surgery": (1, "mgda"),
    "cagrad_c": ("0.5", 1.0),
    "update_path": (None, "graph"),
    "overlap_env_step": (1, None),
    "action_noise": (0.1, None),
    "replay_buffer_class": ("ReplayBuffer", dict),
    "replay_buffer_kwargs": ([("top_k", 3)], None),
    "stats_window_size": (100.0, 0),
    "tensorboard_log": (5, None),
    "policy_kwargs": ("dict(net_arch=[8])", {"net_arch": [0]}),
    "verbose": ("1", 3),
    "seed": (1.5, -3),
    "device": (0, "gpu"),
    "_init_setup_model": ("yes", None),
}
MTSACTE_BAD_VALUES = {
    **{name: values for name, values in MTSAC_BAD_VALUES.items() if name in inspect.signature(MTSACTE).parameters},
    "critic_arch": (1, "shared"),
    "policy_kwargs": ("dict(net_arch=[8])", {"rep_learning_rate": 1e-3}),
    "n_select": ("two", 0),
    "top_k": (30.0, 0),
    "nt_step_size": ("1e-3", -1e-3),
    "c_vae": ("1e-4", -1.0),
    "rep_learning_rate": ("3e-4", 0.0),
    "iteration_length": (500.0, 0),
    "rep_gradient_steps": (10.0, 0),
    "nt_estimator": (None, "exact"),
    "use_vae": (1, None),
    "use_topk": ("yes", None),
    "nt_chunk_size": (2.5, 0),
    "nt_measure": (None, "median"),
}
BAD_VALUES = {MTSAC: MTSAC_BAD_VALUES, MTSACTE: MTSACTE_BAD_VALUES}
MTSAC_KWARGS = {"learning_starts": 40, "batch_size": 8, "buffer_size": 1_000, "policy_kwargs": {"net_arch": [8]}}
CASES = [
    pytest.param(cls, name, kind, value, id=f"{cls.__name__}-{name}-{kind}")
    for cls, table in BAD_VALUES.items()
    for name, (wrong_type, out_of_range) in table.items()
    for kind, value in (("type", wrong_type), ("range", out_of_range))
    if kind == "type" or value is not None
]


def kwargs_of(cls: type, **overrides) -> dict:
    """Small, fast arguments of ``cls`` on the CPU."""
    return small_model_kwargs(**overrides) if cls is MTSACTE else {**MTSAC_KWARGS, "device": "cpu", **overrides}


@pytest.fixture
def no_work(monkeypatch):
    """Make SB3's set-up fail, so that a check that comes after it shows."""

    def work(self, *args, **kwargs):
        raise AssertionError("the arguments were not checked before the set-up")

    monkeypatch.setattr(OffPolicyAlgorithm, "__init__", work)


@pytest.mark.parametrize("cls", [MTSAC, MTSACTE])
def test_the_table_holds_every_argument(cls):
    arguments = set(inspect.signature(cls).parameters) - {"policy", "env"}
    assert set(BAD_VALUES[cls]) == arguments


@pytest.mark.parametrize(("cls", "name", "kind", "value"), CASES)
def test_a_wrong_value_ends_with_one_line_before_any_work(toy_env, no_work, cls, name, kind, value):
    expected = TypeError if kind == "type" else ValueError
    with pytest.raises(expected) as refused:
        cls("MlpPolicy", toy_env, **kwargs_of(cls, **{name: value}))
    message = str(refused.value)
    assert "\n" not in message and f"got {name}={value!r}" in message and " must " in message, message
    if kind == "range":
        assert not isinstance(refused.value, TypeError), message
    else:
        assert isinstance(refused.value, ValueError), message  # code that catches ValueError sees it too


@pytest.mark.parametrize(
    ("cls", "policy", "expected"),
    [
        (MTSAC, "MultiHeadPolicyy", r"^policy 'MultiHeadPolicyy' is not a policy of MTSAC: did you mean "
         r"MultiHeadPolicy\? valid: MlpPolicy, MultiHeadPolicy, "),
        (MTSACTE, "MultiHeadPolicy", r"^policy 'MultiHeadPolicy' is not a policy of MTSACTE: it is MTSAC's; "
         r"valid: MlpPolicy, or a policy class\.$"),
        (MTSACTE, "MlpPolicyy", r"^policy 'MlpPolicyy' is not a policy of MTSACTE: did you mean MlpPolicy\? valid: "),
        (MTSAC, dict, r"^policy must be a policy name of MTSAC or an SB3 policy class, got <class 'dict'>: valid: "),
    ],
)  # fmt: skip
def test_a_wrong_policy_names_the_valid_ones(toy_env, no_work, cls, policy, expected):
    with pytest.raises(ValueError, match=expected):
        cls(policy, toy_env, **kwargs_of(cls))


@pytest.mark.parametrize(
    ("name", "value", "expected"),
    [
        ("tau", 5, r"^tau \(.*\) must be a number in \(0, 1\] such as 0\.005, got tau=5\.$"),
        ("gamma", 1.5, r"^gamma \(the discount factor\) must be a number in \[0, 1\] such as 0\.99, got gamma=1\.5\.$"),
        ("nt_measure", "medain", r"^nt_measure must be one of \('per_batch', 'mean', '.*did you mean mean\?$"),
        ("n_select", "two", r"^n_select \(M, .*\) must be None \(N // 2\) or an int with 1 <= M < N, got n_select="),
        ("policy_kwargs", {"net_arch": [0]}, r"^policy_kwargs must be a dict or None, its net_arch positive widths "),
        ("policy_kwargs", {"net_arch": {"pi": [-5]}}, r"^policy_kwargs must .* net_arch positive widths .*got poli"),
        ("policy_kwargs", {"z_dim": 0}, r"^policy_kwargs must .* its z_dim a positive int"),
    ],
)  # fmt: skip
def test_the_issue_cases_name_the_range(toy_env, no_work, name, value, expected):
    with pytest.raises(ValueError, match=expected):
        MTSACTE("MlpPolicy", toy_env, **small_model_kwargs(**{name: value}))


@pytest.mark.parametrize("cls", [MTSAC, MTSACTE])
def test_a_buffer_without_room_for_one_batch_per_task_is_refused(toy_env, cls):
    with pytest.raises(ValueError, match=r"^buffer_size=10 holds 2 transitions per task, fewer than one batch "
                       r"\(batch_size=8 per task\): give buffer_size >= N \* batch_size = 32\.$"):  # fmt: skip
        cls("MlpPolicy", toy_env, **kwargs_of(cls, buffer_size=10))
    cls("MlpPolicy", toy_env, **kwargs_of(cls, buffer_size=32))  # one batch per task: accepted


def test_the_checks_run_without_an_env_and_with_the_task_count():
    """The command line checks its hyperparameters before it builds the envs, the task count known."""
    from sb3_mtte.mtsac.checks import check_arguments

    check_arguments(MTSACTE, {"policy": "MlpPolicy", "n_select": 3, "tau": 0.01}, n_tasks=4)
    with pytest.raises(ValueError, match=r"n_select \(M\) must satisfy 1 <= M < N = 4, got 7"):
        check_arguments(MTSACTE, {"n_select": 7}, n_tasks=4)
    with pytest.raises(TypeError, match="n_select"):
        check_arguments(MTSACTE, {"n_select": "two"})
    with pytest.raises(ValueError, match="did you mean MultiHeadPolicy"):
        check_arguments(MTSAC, {"policy": "MultiHeadPolicyy", "unknown_key": 1})
    with pytest.raises(ValueError, match=r"buffer_size=400 holds 100 transitions per task"):
        check_arguments(MTSAC, {"buffer_size": 400}, n_tasks=4)  # batch_size: the class's 128


@pytest.mark.parametrize(
    ("algo", "params", "expected"),
    [
        ("mtsacte", "n_select:'two'", r"^n_select \(M, .*\) must be None \(N // 2\) or an int"),
        ("mtsac_mt", "policy:'MultiHeadPolicyy'", r"^policy 'MultiHeadPolicyy' is not a policy of MTSAC: did you "),
        ("mtsacte", "tau:5", r"^tau \(.*\) must be a number in \(0, 1\]"),
        ("mtsacte", "gamma:1.5", r"^gamma \(the discount factor\) must be a number in \[0, 1\]"),
        ("mtsac_mt", "buffer_size:10", r"^buffer_size=10 holds 2 transitions per task, fewer than one batch"),
        ("mtsacte", "policy_kwargs:'dict(net_arch=[-5])'", r"^policy_kwargs must be a dict or None, its net_arch "),
        ("mtsac_mt", "learning_rate:'\"abc\"'", r"^learning_rate must be a positive number such as 3e-4, or 'lin_"),
    ],
)
def test_params_of_the_wrong_type_or_range_end_with_one_line(tmp_path, algo, params, expected):
    with pytest.raises(SystemExit) as exit_info:
        main(["train", "--algo", algo, "--env", ENV, "-f", str(tmp_path), "--eval-freq", "-1", *TINY, "-n", "40",
              "-params", params])  # fmt: skip
    message = str(exit_info.value.code)
    prefix = f"{algo} on {ENV}: "
    assert "\n" not in message and message.startswith(prefix), message
    assert re.search(expected, message.removeprefix(prefix)), message
    assert not list((tmp_path / algo).glob(f"{ENV}_*")), "a refused start left a run folder"
