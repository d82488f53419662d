"""``train``'s output folders: one that cannot be written is refused in one line before any env is built; a start
refused at set-up leaves no folder behind; a checkpoint or final model whose write fails leaves no partial file."""

from __future__ import annotations

import errno
import os
from pathlib import Path

import pytest
from conftest import ENV, TINY

from sb3_mtte.experiments.cli import main
from sb3_mtte.experiments.zoo.manager import MultiTaskExperimentManager

ALGO = "mtsac_mt"


def train(log_folder: str | Path, *flags: str, algo: str = ALGO) -> None:
    main(["train", "--algo", algo, "--env", ENV, "-f", str(log_folder), "-n", "200", *TINY, *flags])


@pytest.fixture
def no_envs(monkeypatch):
    """Building an env fails the test: a refusal must come before."""

    def refuse(*args, **kwargs):
        raise AssertionError("envs were built before the output folder was checked")

    monkeypatch.setattr(MultiTaskExperimentManager, "create_envs", refuse)


# ============================================================================================ unwritable folders
def test_a_log_folder_that_is_a_file_is_refused_before_envs_are_built(tmp_path, no_envs):
    afile = tmp_path / "afile"
    afile.write_text("")
    with pytest.raises(SystemExit) as refused:
        train(afile)
    assert str(refused.value.code) == f"-f {afile} is a file: give a folder."


def test_a_log_folder_inside_a_file_is_refused_before_envs_are_built(tmp_path, no_envs):
    afile = tmp_path / "afile"
    afile.write_text("")
    with pytest.raises(SystemExit) as refused:
        train(afile / "logs")
    assert str(refused.value.code) == f"-f {afile / 'logs'}: {afile} is a file, not a folder; give a path in a folder."


def test_a_log_folder_where_nothing_can_be_written_is_refused_before_envs_are_built(no_envs):
    with pytest.raises(SystemExit) as refused:
        train("/proc/xyz")
    message = str(refused.value.code)
    assert message.startswith("-f /proc/xyz: nothing can be written in /proc (") and "\n" not in message
    assert message.endswith("); give a folder you can write to.")
    assert not Path("/proc/xyz").exists()


@pytest.mark.skipif(os.name != "posix" or os.geteuid() == 0, reason="root writes in a read-only folder")
def test_a_log_folder_without_write_permission_is_refused_before_envs_are_built(tmp_path, no_envs):
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o500)
    try:
        with pytest.raises(SystemExit, match=r"^-f .*locked/logs: nothing can be written in .*locked \("):
            train(locked / "logs")
    finally:
        locked.chmod(0o700)


def test_a_tensorboard_folder_that_is_a_file_is_refused_before_envs_are_built(tmp_path, no_envs):
    afile = tmp_path / "afile"
    afile.write_text("")
    with pytest.raises(SystemExit) as refused:
        train(tmp_path / "logs", "-tb", str(afile))
    assert str(refused.value.code) == f"-tb {afile} is a file: give a folder."
    assert sorted(path.name for path in tmp_path.iterdir()) == ["afile"]


# ======================================================================================= a start refused at set-up
@pytest.mark.parametrize(
    "flags",
    [
        ["-params", "learning_rate:-0.001"],
        ["-params", "batch_size:0"],
        ["-params", "buffer_size:-10"],
        ["--eval-episodes", "0"],
    ],
    ids=["learning_rate", "batch_size", "buffer_size", "eval_episodes"],
)
def test_a_start_refused_at_set_up_leaves_no_folder(tmp_path, flags):
    with pytest.raises(SystemExit) as refused:
        train(tmp_path / "new" / "logs", *flags, algo="mtsacte")
    assert "\n" not in str(refused.value.code)
    assert not list(tmp_path.iterdir()), "a refused start left a folder"
    (tmp_path / "logs").mkdir()
    with pytest.raises(SystemExit):
        train(tmp_path / "logs", *flags, algo="mtsacte")
    assert not list((tmp_path / "logs").iterdir()), "a refused start left <-f>/<algo>/"


def test_a_failed_start_keeps_the_folders_it_did_not_make(tmp_path):
    other = tmp_path / "logs" / "mtsacte" / "other_run"
    other.mkdir(parents=True)
    with pytest.raises(SystemExit):
        train(tmp_path / "logs", "-params", "batch_size:0", algo="mtsacte")
    assert [path.name for path in (tmp_path / "logs" / "mtsacte").iterdir()] == ["other_run"]


# ===================================================================================================== a full disk
def _full_disk(path, *args, **kwargs):
    """Stands for a full disk: write part of the file, then fail as the system does."""
    Path(str(path)).write_bytes(b"partial")
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def test_a_replay_buffer_write_that_fails_leaves_no_partial_file(tmp_path, monkeypatch):
    import stable_baselines3.common.off_policy_algorithm as off_policy

    monkeypatch.setattr(off_policy, "save_to_pkl", _full_disk)
    with pytest.raises(OSError, match="No space left on device"):
        train(tmp_path, "--save-freq", "100")
    run = tmp_path / ALGO / f"{ENV}_1"
    assert not list(run.glob(".tmp_*")) and not list(run.glob("*.pkl"))
    assert not list(run.glob("rl_model_*"))


def test_a_checkpoint_whose_model_write_fails_leaves_no_buffer_without_its_model(tmp_path, monkeypatch):
    import stable_baselines3.common.base_class as base_class

    monkeypatch.setattr(base_class, "save_to_zip_file", _full_disk)
    with pytest.raises(OSError, match="No space left on device"):
        train(tmp_path, "--save-freq", "100")
    run = tmp_path / ALGO / f"{ENV}_1"
    assert not list(run.glob(".tmp_*")) and not list(run.glob("rl_model_*")) and not list(run.glob("*.zip"))


def test_a_final_model_write_that_fails_leaves_no_final_model(tmp_path, monkeypatch):
    import stable_baselines3.common.base_class as base_class

    monkeypatch.setattr(base_class, "save_to_zip_file", _full_disk)
    with pytest.raises(OSError, match="No space left on device"):
        train(tmp_path, "--save-freq", "-1", "--eval-freq", "-1")
    run = tmp_path / ALGO / f"{ENV}_1"
    assert not list(run.glob(".tmp_*")) and not (run / f"{ENV}.zip").exists()


def test_a_run_info_write_that_fails_keeps_the_old_file_and_no_partial_one(tmp_path, monkeypatch):
    from sb3_mtte.experiments import run_info

    run_info.write_run_info(tmp_path, {"finished": False})
    monkeypatch.setattr(run_info.os, "replace", _full_disk)
    with pytest.raises(OSError, match="No space left on device"):
        run_info.update_run_info(tmp_path, finished=True)
    assert sorted(path.name for path in tmp_path.iterdir()) == ["run_info.json"]
    assert run_info.read_run_info(tmp_path) == {"finished": False}
