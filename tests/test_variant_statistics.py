"""Every existing algorithm gives the parameters that ``tests/data/variant_statistics.json`` was written with, within
what the CPU's matmul kernels change (:mod:`variant_statistics`: a short seeded run on toy-conflict, CPU, one
thread); the check holds under another instruction set and fails under a small real change."""

from __future__ import annotations

import functools
import inspect
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch as th
from variant_statistics import CASES, MTSAC, case_statistics, distance, stored_statistics, tolerance

import sb3_mtte.mtsac.mtsac as mtsac_module

HERE = Path(__file__).resolve().parent
LEARNING_RATE = inspect.signature(MTSAC.__init__).parameters["learning_rate"].default


@functools.cache
def native_statistics(case: str) -> dict:
    """The case's statistics on this CPU's own kernels (computed once per test process)."""
    return case_statistics(case)


@pytest.mark.parametrize("case", list(CASES))
def test_parameters_match_the_stored_statistics(case):
    assert distance(native_statistics(case), stored_statistics()[case]) <= tolerance(case)


def test_another_instruction_set_stays_within_tolerance():
    """ATen's kernels without vectorisation (``ATEN_CPU_CAPABILITY=default``) change the last bits of every update
    of these cases on an AVX2 or AVX512 CPU (measured on AVX512: 5e-7 for mt, 2e-6 for mtsacte, against this CPU's
    own kernels); the parameters stay within tolerance of the stored ones."""
    cases = ["mt", "softmod", "paco_collapse", "mtsacte"]
    env = {**os.environ, "ATEN_CPU_CAPABILITY": "default"}
    script = str(HERE / "variant_statistics.py")
    out = subprocess.run([sys.executable, script, *cases], env=env, capture_output=True, text=True, check=True)
    statistics = json.loads(out.stdout.strip().splitlines()[-1])
    assert sorted(statistics) == sorted(cases)
    for case, stats in statistics.items():
        assert distance(stats, stored_statistics()[case]) <= tolerance(case), case
    if th.backends.cpu.get_cpu_capability() != "DEFAULT":  # else the variable changes nothing to show
        assert max(distance(stats, native_statistics(case)) for case, stats in statistics.items()) > 0


@pytest.mark.parametrize("case", ["mt", "softmod", "moore", "mtsacte"])
def test_a_learning_rate_one_percent_off_is_caught(case):
    stats = case_statistics(case, learning_rate=LEARNING_RATE * 1.01)
    assert distance(stats, stored_statistics()[case]) > tolerance(case)


def test_a_loss_term_cut_from_the_gradient_is_caught(monkeypatch):
    """The actor objective's entropy term without its gradient (log pi detached, a classic slip of SAC's loss)."""
    objective = mtsac_module.sac_task_objective

    def cut(log_prob: th.Tensor, min_q: th.Tensor, ent_coef: th.Tensor) -> th.Tensor:
        return objective(log_prob.detach(), min_q, ent_coef)

    monkeypatch.setattr(mtsac_module, "sac_task_objective", cut)
    assert distance(case_statistics("mt"), stored_statistics()["mt"]) > tolerance("mt")
