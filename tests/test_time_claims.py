"""Every time the README and the zoo configs state is the one measured in docs/results/time_claims.json
(benchmarks/time_claims.py), and the rate of a run in progress is read from its current learn call only."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
from script_loader import load_script

ROOT = Path(__file__).resolve().parents[1]
time_claims = load_script("benchmarks/time_claims.py")

MEASURED = json.loads((ROOT / "docs/results/time_claims.json").read_text())["parts"]
README = " ".join((ROOT / "README.md").read_text().split())


def _s(seconds: float) -> str:
    return f"{round(seconds)} s"


def _minutes(seconds: float) -> str:
    minutes, rest = divmod(round(seconds / 10) * 10, 60)
    return f"{minutes} min {rest} s"


def test_readme_states_the_measured_times():
    smoke, video = MEASURED["smoke"], MEASURED["video"]
    expected = [
        f"{_s(smoke['train']['wall_s'])} + {_s(smoke['evaluate']['wall_s'])}",
        f"{_minutes(MEASURED['suite']['wall_s'])} ({_s(MEASURED['suite']['wall_s'])})",
        f"{_s(MEASURED['toy']['wall_s'])}, {MEASURED['toy']['max_rss_gb']:.1f} GB",
        f"{_s(MEASURED['mt25']['wall_s'])}, {MEASURED['mt25']['max_rss_gb']:.1f} GB",
        f"{video['480x480']['wall_s_per_frame']:.2f} s ({video['480x480']['cpu_s_per_frame']:.2f} CPU-s) at 480 x 480",
        f"{video['240x240']['wall_s_per_frame']:.2f} s ({video['240x240']['cpu_s_per_frame']:.2f} CPU-s) at 240 x 240",
        f"about {round(MEASURED['snippet']['estimated_minutes_for_200000'] / 5) * 5} min",
        f"{round(MEASURED['snippet']['env_steps_per_s_after_learning_starts'])} env steps/s after `learning_starts`",
        f"{MEASURED['mt10_100k_side_by_side']['Ours (mtsacte)']['env_steps_per_s']} (Ours) and "
        f"{MEASURED['mt10_100k_side_by_side']['SAC-MT (mtsac_mt)']['env_steps_per_s']} (SAC-MT) env steps/s",
    ]
    missing = [text for text in expected if text not in README]
    assert not missing, f"README lacks the measured {missing}: python benchmarks/time_claims.py"


@pytest.mark.parametrize("family", ["mtsac", "mtsacte"])
def test_configs_state_the_measured_times(family):
    text = " ".join(line.lstrip("# ") for line in (ROOT / f"zoo_configs/{family}.yml").read_text().splitlines())
    smoke = MEASURED["smoke"]
    for expected in (
        f"MT10-smoke train {_s(smoke['train']['wall_s'])} + evaluate {_s(smoke['evaluate']['wall_s'])}",
        f"MT25-smoke {_s(MEASURED['mt25']['wall_s'])} and {MEASURED['mt25']['max_rss_gb']:.1f} GB",
        f"{_s(MEASURED['toy']['wall_s'])} at one torch thread",
    ):
        assert expected in text, f"zoo_configs/{family}.yml lacks {expected!r}"


def test_progress_rate_reads_the_current_learn_call(tmp_path):
    """A run resumed at 20,000 steps: its earlier call's rows (larger time_elapsed) are not part of the rate, and rows
    logged before ``since`` are left out."""
    rows = [
        (5_000, 100.0),
        (10_000, 200.0),
        (15_000, 300.0),
        (20_000, 400.0),
        (25_000, 10.0),
        (30_000, 60.0),
        (35_000, 110.0),
        (40_000, 135.0),
    ]
    csv_text = "time/total_timesteps,time/time_elapsed,other\n" + "".join(f"{n},{t},\n" for n, t in rows)
    csv_text += ",,1.0\n"  # a row of training values only, as SB3 writes between episode rows
    (tmp_path / "progress.csv").write_text(csv_text)
    end = 1_000_000.0
    os.utime(tmp_path / "progress.csv", (end, end))
    # the call started at end - 135: rows at 10, 60, 110, 135 s; since = end - 135 + 50 keeps 60, 110, 135
    rate = time_claims.progress_rate(tmp_path, since=end - 135 + 50)
    assert rate["from_steps"] == 30_000 and rate["to_steps"] == 40_000
    assert rate["seconds"] == 75.0
    assert rate["env_steps_per_s"] == round(10_000 / 75, 1)
    with pytest.raises(SystemExit, match="fewer than two"):
        time_claims.progress_rate(tmp_path, since=end - 1)
