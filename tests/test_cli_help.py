"""The help of the commands: usage lines that name the real invocation, the valid env ids, every command under
``python -m sb3_mtte``, and ``--help | head`` without a traceback."""

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
    ("argv0", "expected"), [("/venv/bin/sb3-mtte", "sb3-mtte"), ("/src/sb3_mtte/__main__.py", "python -m sb3_mtte")]
)
def test_zoo_commands_name_the_invocation_in_their_usage(monkeypatch, capsys, command, argv0, expected):
    monkeypatch.setattr("sys.argv", [argv0])
    assert help_text(capsys, cli.main, [command, "--help"]).startswith(f"usage: {expected} {command} ")


@pytest.mark.parametrize("command", ["train", "enjoy"])
def test_env_help_lists_the_valid_ids(capsys, command):
    out = help_text(capsys, cli.main, [command, "--help"])
    env_help = " ".join(out.split("--env ENV", 2)[-1].split("\n  -")[0].split())
    assert env_help.startswith("env id: MT10, MT20, MT25, MT50, DEV6, toy-conflict, toy-agree"), env_help


def test_the_zoo_module_takes_every_command(capsys, monkeypatch):
    monkeypatch.setattr("sys.argv", ["/src/sb3_mtte/__main__.py"])
    out = help_text(capsys, cli.main, ["--help"])
    assert out.startswith("usage: python -m sb3_mtte {train,enjoy,record_video,evaluate,plot,compare,record,sweep}")
    assert help_text(capsys, cli.main, ["plot", "--help"]).startswith("usage: ")


@pytest.mark.parametrize("args", [["sb3_mtte"], ["sb3_mtte", "train"]])
def test_help_into_a_closed_pipe_ends_without_a_traceback(args):
    """``... --help | head``: the reader is gone before the help is written; the command ends quietly."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    argv = [sys.executable, "-m", *args, "--help"]
    process = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env, cwd=ROOT)
    process.stdout.close()  # before the interpreter has started: its first write meets a closed pipe
    err = process.stderr.read().decode()
    assert process.wait(timeout=120) in (0, 1) and "Traceback" not in err and "BrokenPipe" not in err, err


def test_python_m_sb3_mtte_lists_the_commands_under_its_own_name():
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    done = subprocess.run([sys.executable, "-m", "sb3_mtte", "--help"], capture_output=True, text=True, env=env)
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("usage: python -m sb3_mtte {train,enjoy,record_video,evaluate,plot,compare,record,")
    assert all(f"\n    {command} " in done.stdout for command in cli.COMMANDS), done.stdout


def test_the_dispatcher_loads_no_command_module_and_no_torch_before_a_command_runs():
    """So the process settings come before torch loads, and a missing extra is named before anything imports it."""
    code = (
        "import sys, sb3_mtte.experiments.cli\n"
        "heavy = ('torch', 'rl_zoo3', 'matplotlib', 'gymnasium')\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] in heavy or m.startswith('sb3_mtte.experiments.')))"
    )
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    assert done.stdout.strip() == "['sb3_mtte.experiments.cli', 'sb3_mtte.experiments.extras']"


def test_a_command_without_its_extra_ends_with_one_line_before_its_module_loads(monkeypatch):
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # as if not installed: find_spec finds nothing
    monkeypatch.delitem(sys.modules, "sb3_mtte.experiments.results.plot", raising=False)
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["plot", "docs/records"])
    assert str(exit_info.value) == 'sb3-mtte plot needs matplotlib: pip install "sb3-mtte[plots]"'
    assert "sb3_mtte.experiments.results.plot" not in sys.modules


def test_every_command_runs_the_function_its_target_names():
    for command, target in cli.COMMAND_TARGETS.items():
        module, function = target.split(":")
        assert callable(getattr(__import__(module, fromlist=[function]), function)), command
