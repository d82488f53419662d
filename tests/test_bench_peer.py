"""The side-by-side summary takes medians over rounds and ratios to the reference's medians."""

from __future__ import annotations

import pytest
from script_loader import load_script

bench_peer = load_script("benchmarks/bench_peer.py")


def one_round(ref_upd: float, ref_e2e: float, shared: tuple[float, float], per_task: tuple[float, float]) -> dict:
    return {
        "reference": {"updates_per_s": ref_upd, "env_steps_per_s": ref_e2e},
        "package": {
            "updates_per_s": {"shared": shared[0], "per_task": per_task[0]},
            "env_steps_per_s": {"shared": shared[1], "per_task": per_task[1]},
        },
    }


def test_medians_and_ratios() -> None:
    rounds = [
        one_round(10.0, 100.0, (12.0, 130.0), (9.0, 90.0)),
        one_round(12.0, 90.0, (15.0, 110.0), (11.0, 80.0)),
        one_round(11.0, 200.0, (13.0, 120.0), (10.0, 85.0)),
    ]
    medians = bench_peer.summary(rounds)
    assert medians["reference"] == {"updates_per_s": 11.0, "env_steps_per_s": 100.0}
    assert medians["sb3-mtte shared critic"] == {
        "updates_per_s": 13.0,
        "env_steps_per_s": 120.0,
        "updates_ratio": round(13 / 11, 3),
        "env_steps_ratio": 1.2,
    }
    assert medians["sb3-mtte per_task critic"]["env_steps_ratio"] == 0.85


def test_the_reference_is_required() -> None:
    with pytest.raises(SystemExit):
        bench_peer.main(["--rounds", "1"])
