"""Logs of a run folder: SB3 logger (stdout, ``progress.csv``, tensorboard) and their trimming on resume."""

from __future__ import annotations

import csv
import json
import os
import re
import sys
from pathlib import Path

from stable_baselines3.common.logger import (
    CSVOutputFormat,
    HumanOutputFormat,
    KVWriter,
    Logger,
    TensorBoardOutputFormat,
)
from torch.utils.tensorboard import SummaryWriter

PROGRESS_FILE = "progress.csv"
STEP_KEY = "time/total_timesteps"


class _TensorBoardFormat(TensorBoardOutputFormat):
    """SB3's tensorboard writer with a purge step: events of a killed run after the resumed step are hidden."""

    def __init__(self, folder: str, purge_step: int | None = None) -> None:
        self.writer = SummaryWriter(log_dir=folder, purge_step=purge_step)
        self._is_closed = False


def _trim_progress_csv(path: Path, up_to_timesteps: int) -> tuple[list[str], list[str]]:
    """Header and raw data lines of an SB3 ``progress.csv`` whose step is at most ``up_to_timesteps``."""
    if not path.is_file():
        return [], []
    lines = path.read_text().splitlines()
    if not lines:
        return [], []
    header = lines[0].split(",")
    column = header.index(STEP_KEY) if STEP_KEY in header else None
    kept = []
    for line in lines[1:]:
        if column is not None:
            row = next(csv.reader([line]), [])
            try:
                if float(row[column]) > up_to_timesteps:
                    continue
            except (IndexError, ValueError):
                pass
        kept.append(line)
    return header, kept


def make_run_logger(
    run_dir: str | os.PathLike,
    verbose: int = 1,
    tensorboard_dir: str | None = None,
    resume_step: int | None = None,
    tensorboard: bool = True,
) -> Logger:
    """SB3 logger of a run folder: stdout (verbose >= 1), ``progress.csv`` and tensorboard events.

    :param run_dir: the run folder (``logger.get_dir()``, where MTSACTE writes ``negative_transfer.jsonl``).
    :param verbose: 1 adds stdout.
    :param tensorboard_dir: folder of the events (the run folder when None).
    :param resume_step: for a resumed run, the checkpoint step: ``progress.csv`` keeps its rows up to this step
        and continues, tensorboard hides the events logged after it.
    :param tensorboard: write tensorboard events.
    """
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    formats: list[KVWriter] = []
    if verbose >= 1:
        formats.append(HumanOutputFormat(sys.stdout))
    path = run_dir / PROGRESS_FILE
    header, lines = _trim_progress_csv(path, resume_step) if resume_step is not None else ([], [])
    csv_format = CSVOutputFormat(str(path))
    if header:
        csv_format.keys = header
        csv_format.file.write(",".join(header) + "\n")
        for line in lines:
            csv_format.file.write(line + "\n")
        csv_format.file.flush()
    formats.append(csv_format)
    if tensorboard:
        purge = None if resume_step is None else resume_step + 1
        formats.append(_TensorBoardFormat(str(tensorboard_dir or run_dir), purge_step=purge))
    return Logger(folder=str(run_dir), output_formats=formats)


def trim_jsonl(path: Path, up_to_timesteps: int) -> None:
    """Drop the records of a JSON-lines log whose ``timesteps`` exceed ``up_to_timesteps``."""
    if not path.is_file():
        return
    kept = []
    for line in path.read_text().splitlines():
        if not line.strip():
            continue
        try:
            if json.loads(line).get("timesteps", 0) > up_to_timesteps:
                continue
        except json.JSONDecodeError:
            continue  # a line cut by the kill
        kept.append(line + "\n")
    tmp = path.with_name(f".tmp_{path.name}")
    try:
        tmp.write_text("".join(kept))
        os.replace(tmp, path)
    except BaseException:  # the log stays as it was, with no partial copy beside it
        tmp.unlink(missing_ok=True)
        raise


def set_aside_monitor_files(run_dir: Path) -> None:
    """Rename the Monitor files of the previous segments (``0.monitor.csv`` -> ``0.seg<k>.monitor.csv``)."""
    files = sorted(run_dir.glob("[0-9]*.monitor.csv"))
    files = [f for f in files if re.fullmatch(r"\d+\.monitor\.csv", f.name)]
    if not files:
        return
    segment = 1 + len({m.group(1) for f in run_dir.glob("*.seg*.monitor.csv") if (m := re.search(r"seg(\d+)", f.name))})
    for path in files:
        path.rename(path.with_name(path.name.replace(".monitor.csv", f".seg{segment}.monitor.csv")))
