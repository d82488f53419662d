"""A run stopped by Ctrl-C says where it stopped and how to resume, exits 130, keeps a checkpoint and no final model,
and its ``run_info.json`` says ``finished: false``."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import ENV, TINY
from stable_baselines3.common.callbacks import BaseCallback

from sb3_mtte.experiments.cli import main
from sb3_mtte.experiments.run_info import read_run_info
from sb3_mtte.experiments.zoo.run_checkpoints import find_checkpoints, load_model

ALGO = "mtsac_mt"
STOPPED = re.compile(r"^Stopped at ([\d,]+) of ([\d,]+) env steps; resume with: (.+) --resume (\S+)(.*)$")


class InterruptAt(BaseCallback):
    """Stands for a second Ctrl-C, which stops at once: raise ``KeyboardInterrupt`` at ``timesteps`` env steps."""

    def __init__(self, timesteps: int) -> None:
        super().__init__()
        self.timesteps = timesteps

    def _on_step(self) -> bool:
        if self.num_timesteps >= self.timesteps:
            raise KeyboardInterrupt
        return True


def _wait_for_training(run: Path, process: subprocess.Popen, timeout: float = 300) -> None:
    """Wait until the run has logged a row of ``progress.csv`` (training is under way)."""
    deadline = time.monotonic() + timeout
    progress = run / "progress.csv"
    while not (progress.is_file() and len(progress.read_text().splitlines()) > 1):
        assert process.poll() is None, "the run ended before it was stopped"
        assert time.monotonic() < deadline, "the run did not start training"
        time.sleep(0.2)


def test_ctrl_c_stops_at_a_checkpoint_says_how_to_resume_and_exits_130(tmp_path):
    command = [sys.executable, "-m", "sb3_mtte", "train", "--algo", ALGO, "--env", ENV, "-f", str(tmp_path)]
    command += ["-n", "200000", "--eval-freq", "-1", *TINY]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    with open(tmp_path / "stdout.txt", "w") as out, open(tmp_path / "stderr.txt", "w") as err:
        process = subprocess.Popen(command, stdout=out, stderr=err, env=env, cwd=tmp_path)
        run = tmp_path / ALGO / f"{ENV}_1"
        try:
            _wait_for_training(run, process)
            process.send_signal(signal.SIGINT)
            returncode = process.wait(timeout=120)
        finally:
            if process.poll() is None:
                process.kill()
    stderr = (tmp_path / "stderr.txt").read_text()
    assert returncode == 130, stderr
    assert "Traceback" not in stderr
    match = STOPPED.match(stderr.strip().splitlines()[-1])
    assert match, stderr
    steps = int(match.group(1).replace(",", ""))
    assert match.group(2) == "200,000" and match.group(3) == "python -m sb3_mtte train"
    assert Path(match.group(4)) == run and match.group(5) == ""  # resumes from the checkpoint at the stop
    assert 0 < steps < 200_000
    assert not (run / f"{ENV}.zip").exists()  # the final model's name is a finished run's only
    (checkpoint,) = find_checkpoints(run)
    assert checkpoint.timesteps == steps and checkpoint.replay_buffer is not None
    info = read_run_info(run)
    assert info["finished"] is False and info["timesteps"] == steps
    assert info["stopped"]["timesteps"] == steps and info["stopped"]["checkpoint"] == checkpoint.model.name
    assert not list(run.glob(".tmp_*"))

    # the command it names continues from there
    main(["train", "--resume", str(run), "-n", str(steps + 200)])
    info = read_run_info(run)
    assert info["finished"] and info["stopped"] is None and info["resumes"][-1]["timesteps"] == steps
    assert load_model(run / f"{ENV}.zip").num_timesteps == steps + 200


@pytest.mark.parametrize(
    ("save_freq", "from_where"),
    [("200", " (from the checkpoint at 200)"), ("-1", " (no checkpoint yet: it starts over)")],
)
def test_a_second_ctrl_c_stops_at_once_and_names_the_checkpoint_a_resume_starts_from(
    tmp_path, capsys, save_freq, from_where
):
    interrupt = f"callback:{{'{InterruptAt.__module__}.InterruptAt': dict(timesteps=300)}}"
    with pytest.raises(SystemExit) as stopped:
        main(["train", "--algo", ALGO, "--env", ENV, "-f", str(tmp_path), "-n", "800", "--eval-freq", "-1", *TINY,
              "--save-freq", save_freq, "-params", interrupt])  # fmt: skip
    run = tmp_path / ALGO / f"{ENV}_1"
    assert stopped.value.code == 130
    assert capsys.readouterr().err.strip().splitlines() == [
        f"Stopped at 300 of 800 env steps; resume with: sb3-mtte train --resume {run}{from_where}"
    ]
    assert not (run / f"{ENV}.zip").exists()
    info = read_run_info(run)
    assert info["finished"] is False and info["timesteps"] == 300 and info["stopped"]["timesteps"] == 300
    assert [c.timesteps for c in find_checkpoints(run)] == ([200] if save_freq == "200" else [])
