"""Tests of the rl-zoo launcher's enjoy and record_video: per-task success, one video per task, and
one line naming the fix for a missing run, model or bad option."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import ENV, tiny_train

from sb3_mtte.experiments.cli import main


# ================================================================================================ enjoy, video
@pytest.fixture(scope="module")
def trained_run(tmp_path_factory):
    return tiny_train(tmp_path_factory.mktemp("zoo"), "mtsac_mt")


def test_enjoy(trained_run, capsys):
    folder = str(trained_run.parent.parent)
    main(["enjoy", "--algo", "mtsac_mt", "--env", ENV, "-f", folder, "--no-render", "-n", "110"])
    out = capsys.readouterr().out
    assert "task  3 conflict" in out and "Success rate per task" in out
    assert out.count("Loading latest experiment") == 1
    assert "No episode finished" not in out


def test_enjoy_shorter_than_an_episode_reports_the_unfinished_ones(trained_run, capsys):
    folder = str(trained_run.parent.parent)
    main(["enjoy", "--algo", "mtsac_mt", "--env", ENV, "-f", folder, "--no-render", "-n", "7"])
    out = capsys.readouterr().out
    assert "No episode finished for 4 task(s) (pass a larger -n)" in out and "Success rate per task" not in out
    assert "task  3 conflict" in out and "length    7  success so far" in out


@pytest.mark.parametrize("command", ["enjoy", "record_video"])
def test_a_missing_run_or_model_names_the_fix(trained_run, command):
    folder = str(trained_run.parent.parent)
    with pytest.raises(SystemExit, match=r"toy-conflict_9 folder was not found: give -f, --algo, --env"):
        main([command, "--algo", "mtsac_mt", "--env", ENV, "-f", folder, "--exp-id", "9", "-n", "5"])
    if command == "enjoy":
        with pytest.raises(SystemExit, match=r"toy-conflict has 4 tasks: --n-envs must be 4 \(one sub-env per task\)"):
            main([command, "--algo", "mtsac_mt", "--env", ENV, "-f", folder, "--n-envs", "four"])
    with pytest.raises(SystemExit, match=r"rl_model_999_steps.zip: load one of the models of .*_1 \(.*best_model.zip"):
        main([command, "--algo", "mtsac_mt", "--env", ENV, "-f", folder, "--load-checkpoint", "999", "-n", "5"])


def test_enjoy_and_resume_pass_over_a_newer_folder_without_a_model(tmp_path, capsys):
    """A folder a failed start left (older versions did) is not the latest run: enjoy and train --resume take the
    latest folder that holds a model, and say which."""
    run = tiny_train(tmp_path, "mtsac_mt", steps=200)
    (run.parent / f"{ENV}_2" / ENV).mkdir(parents=True)  # monitor files and a config folder, no model
    capsys.readouterr()
    main(["enjoy", "--algo", "mtsac_mt", "--env", ENV, "-f", str(tmp_path), "--no-render", "-n", "5"])
    out = capsys.readouterr().out
    assert f"Passing over {ENV}_2 (no model): the latest run with one is {run}" in out
    assert "Loading latest experiment, id=1" in out
    main(["train", "--algo", "mtsac_mt", "--env", ENV, "-f", str(tmp_path), "--resume", "-n", "400", "--no-progress"])
    out = capsys.readouterr().out
    resumed = [line for line in out.splitlines() if line.startswith("Resum")]
    assert resumed == [f"Resuming {run} from scratch: it has no checkpoint"], out


@pytest.mark.parametrize("command", ["enjoy", "record_video"])
def test_no_run_at_all_gets_its_message_alone(tmp_path, capsys, command):
    """Without any run of the algorithm on the env (no folder, or an empty one), one line naming the run folder
    looked for, and no "Loading latest experiment, id=0" before it."""
    (tmp_path / "mtsac_mt").mkdir()
    for folder in (tmp_path / "absent", tmp_path):
        with pytest.raises(SystemExit, match=r"^No run folder \S+mtsac_mt/toy-conflict_<id>: give -f, --algo, --env"):
            main([command, "--algo", "mtsac_mt", "--env", ENV, "-f", str(folder), "-n", "5"])
        assert capsys.readouterr().out == ""


def test_every_record_video_option_is_described():
    from sb3_mtte.experiments.playback.zoo_playback import _record_video_parser

    undescribed = [action.option_strings for action in _record_video_parser()._actions if not action.help]
    assert undescribed == []


def test_record_video_names_a_bad_env_kwarg_and_an_output_that_is_a_file(trained_run, tmp_path):
    args = ["record_video", "--algo", "mtsac_mt", "--env", ENV, "-f", str(trained_run.parent.parent)]
    with pytest.raises(SystemExit) as exit_info:
        main([*args, "--env-kwargs", "goal_radius:far", "-o", str(tmp_path)])
    assert str(exit_info.value.code).startswith("--env-kwargs goal_radius:far: name 'far' is not defined; each value")
    (tmp_path / "videos").write_text("")
    with pytest.raises(SystemExit) as exit_info:
        main([*args, "-o", str(tmp_path / "videos")])
    assert exit_info.value.code == f"-o {tmp_path / 'videos'} is a file: give a folder."
    assert not list(tmp_path.glob("*.mp4"))


def test_record_video_one_file_per_task(trained_run, tmp_path):
    folder = str(trained_run.parent.parent)
    written = main(["record_video", "--algo", "mtsac_mt", "--env", ENV, "-f", folder, "-o", str(tmp_path), "--tile"])
    assert sorted(written) == sorted(tmp_path.glob("*.mp4"))
    videos = sorted(p.name for p in tmp_path.glob("*.mp4"))
    assert len(videos) == 5 and any("03_conflict" in v for v in videos) and any("all_tasks" in v for v in videos)
    assert all((tmp_path / v).stat().st_size > 1000 for v in videos)


class WriterLog:
    """Stands for moviepy's ffmpeg writer: creates the (empty) file and logs every opened video (by the name it is
    renamed to when complete), written frame and close in ``events``."""

    events: list[tuple[str, str]] = []

    def __init__(self, filename: str, size: tuple[int, int], fps: float, **options: object) -> None:
        Path(filename).touch()
        self.name = Path(filename).name.removeprefix(".partial_")
        self.events.append(("open", self.name))

    def write_frame(self, frame: np.ndarray) -> None:
        self.events.append(("frame", self.name))

    def close(self) -> None:
        self.events.append(("close", self.name))

    def __enter__(self) -> WriterLog:
        return self

    def __exit__(self, *error: object) -> None:
        self.close()


def test_record_video_writes_each_task_before_filming_the_next(trained_run, tmp_path, monkeypatch, capsys):
    """Each frame goes to its file as soon as it is drawn and task i's file is closed before task i+1's first frame
    is drawn (no frames held across tasks); the tiled video streams as well; every video shows a progress bar."""
    from moviepy.video.io import ffmpeg_writer

    from sb3_mtte.envs.toy import PointGoalEnv

    events: list[tuple[str, str]] = []
    monkeypatch.setattr(WriterLog, "events", events)
    monkeypatch.setattr(ffmpeg_writer, "FFMPEG_VideoWriter", WriterLog)
    render = PointGoalEnv.render

    def logged_render(env: PointGoalEnv) -> np.ndarray:
        events.append(("render", ""))
        return render(env)

    monkeypatch.setattr(PointGoalEnv, "render", logged_render)
    folder = str(trained_run.parent.parent)
    argv = ["record_video", "--algo", "mtsac_mt", "--env", ENV, "-f", folder, "-o", str(tmp_path), "--tile"]
    written = main([*argv, "--episodes", "2"])
    names = [path.name for path in written]
    assert len(names) == 5 and names[3].endswith("-03_conflict.mp4") and names[4].endswith("-all_tasks.mp4")
    render = ("render", "")
    expected = []
    for name in names[:4]:  # 2 episodes of 50 steps: each frame written right after it is drawn
        expected += [render, ("open", name), ("frame", name), *[render, ("frame", name)] * 99, ("close", name)]
    tiled = names[4]  # every task drawn, then their tiled frame written
    expected += [*[render] * 4, ("open", tiled), ("frame", tiled), *([*[render] * 4, ("frame", tiled)] * 99)]
    assert events == [*expected, ("close", tiled)]
    err = capsys.readouterr().err
    assert all(f"{name}: 100%" in err for name in names[:4]) and err.count("100/100") == 4, err


class ZeroActions:
    """A model that always predicts the zero action (frames depend on the env alone)."""

    def predict(self, obs: np.ndarray, deterministic: bool = True) -> tuple[np.ndarray, None]:
        return np.zeros((len(obs), 4), dtype=np.float32), None


def test_record_video_draws_each_task_in_its_own_gl_context(monkeypatch):
    """Two Meta-World tasks of different scenes rendered in one run give the frames each gives rendered alone
    (before, every task drew with the OpenGL context created last: another task's meshes)."""
    from argparse import Namespace

    from sb3_mtte.envs import make_mt_env
    from sb3_mtte.experiments.playback.video import all_task_frames

    monkeypatch.setenv("MUJOCO_GL", os.environ.get("MUJOCO_GL", "egl"))
    tasks = ["door-open-v3", "drawer-close-v3"]
    kwargs = {"render_mode": "rgb_array", "width": 32, "height": 32, "max_episode_steps": 10}
    args = Namespace(episodes=1, n_timesteps=3, flip=False, tile=False, stochastic=False)
    alone = [[] for _ in tasks]
    for i, frames_alone in enumerate(alone):
        env = make_mt_env(tasks, seed=0, **kwargs)  # task i's sub-env is the only one that renders
        env.env_method("set_eval_mode", True)  # as record_video does
        obs = env.reset()
        for _ in range(args.n_timesteps):
            frames_alone.append(env.envs[i].render())
            obs, *_ = env.step(ZeroActions().predict(obs)[0])
        env.close()
    env = make_mt_env(tasks, seed=0, **kwargs)
    try:
        frames = list(all_task_frames(ZeroActions(), env, args))
    finally:
        env.close()
    for i, task in enumerate(tasks):
        np.testing.assert_array_equal(np.stack([step[i] for step in frames]), np.stack(alone[i]), err_msg=task)


def test_a_video_is_written_under_a_temporary_name_and_renamed_when_complete(tmp_path):
    """A video stopped midway leaves nothing under its name (and no partial file); a complete one is renamed."""
    from sb3_mtte.experiments.playback.video import write_video

    def frames(n: int, fail: bool):
        for _ in range(n):
            yield np.zeros((16, 16, 3), dtype=np.uint8)
        if fail:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        write_video(frames(3, fail=True), tmp_path / "stopped.mp4", fps=10)
    assert write_video(frames(3, fail=False), tmp_path / "whole.mp4", fps=10)
    assert sorted(path.name for path in tmp_path.iterdir()) == ["whole.mp4"]


def test_a_truncated_model_ends_enjoy_and_record_video_with_one_line(tmp_path, monkeypatch):
    run = tiny_train(tmp_path, "mtsac_mt", steps=200)
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.setattr(sys, "platform", "linux")
    with pytest.raises(SystemExit) as exit_info:  # a machine without a display, and no --no-render
        main(["enjoy", "--algo", "mtsac_mt", "--env", ENV, "-f", str(tmp_path), "-n", "5"])
    assert exit_info.value.code == (
        "enjoy renders in a window and this machine has no display: add --no-render, or write videos with "
        "sb3-mtte record_video."
    )
    model = run / f"{ENV}.zip"
    model.write_bytes(model.read_bytes()[: model.stat().st_size // 2])
    for command in (["enjoy", "--no-render", "-n", "5"], ["record_video", "-n", "5"]):
        with pytest.raises(SystemExit) as exit_info:
            main([command[0], "--algo", "mtsac_mt", "--env", ENV, "-f", str(tmp_path), *command[1:]])
        message = str(exit_info.value.code)
        assert message.startswith(f"{model} is not a complete SB3 checkpoint (") and "\n" not in message, message
