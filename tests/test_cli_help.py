"""The help of the commands: usage lines that name the real invocation, the valid env ids, every command under
``python -m sb3_mtte.zoo``, and ``--help | head`` without a traceback."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from sb3_mtte.experiments import cli

ROOT = Path(__file__).resolve().parents[1]


def help_text(capsys, run, argv: list[str]) -> str:
    with pytest.raises(SystemExit) as exit_info:
        run(argv)
    assert exit_info.value.code == 0
    return capsys.readouterr().out


@pytest.mark.parametrize("command", ["train", "enjoy", "record_video"])
@pytest.mark.parametrize(
    ("argv0", "expected"), [("/venv/bin/sb3-mtte", "sb3-mtte"), ("/src/sb3_mtte/zoo.py", "python -m sb3_mtte.zoo")]
)
def test_zoo_commands_name_the_invocation_in_their_usage(monkeypatch, capsys, command, argv0, expected):
    monkeypatch.setattr("sys.argv", [argv0])
    assert help_text(capsys, cli.main, [command, "--help"]).startswith(f"usage: {expected} {command} ")


@pytest.mark.parametrize("command", ["train", "enjoy"])
def test_env_help_lists_the_valid_ids(capsys, command):
    out = help_text(capsys, cli.main, [command, "--help"])
    env_help = " ".join(out.split("--env ENV", 2)[-1].split("\n  -")[0].split())
    assert env_help.startswith("env id: MT10, MT20, MT25, MT50, DEV6, toy-conflict, toy-agree"), env_help


def test_the_zoo_module_takes_every_command(capsys):
    out = help_text(capsys, cli.zoo_main, ["--help"])
    assert out.startswith("usage: python -m sb3_mtte.zoo {train,enjoy,record_video,evaluate,plot,compare,record,sweep}")
    assert help_text(capsys, cli.zoo_main, ["plot", "--help"]).startswith("usage: ")


@pytest.mark.parametrize("args", [["sb3_mtte.zoo"], ["sb3_mtte.zoo", "train"]])
def test_help_into_a_closed_pipe_ends_without_a_traceback(args):
    """``... --help | head``: the reader is gone before the help is written; the command ends quietly."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    argv = [sys.executable, "-m", *args, "--help"]
    process = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env, cwd=ROOT)
    process.stdout.close()  # before the interpreter has started: its first write meets a closed pipe
    err = process.stderr.read().decode()
    assert process.wait(timeout=120) in (0, 1) and "Traceback" not in err and "BrokenPipe" not in err, err
