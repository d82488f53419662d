"""Reading a folder of runs for the figures and tables: run folders, their scalars and curves.

A run folder holds:

- ``run_info.json``: algorithm, env, seed, task names (required);
- ``evaluations.npz``: ``timesteps`` (T,), ``success_rate`` (T, N), ``task_names`` (periodic evaluations);
- ``progress.csv``: SB3's csv log (``eval/success/NN_task``, ``rollout/success/NN_task``,
  ``train/critic_loss/NN_task``, ``nt/mu/NN_task``, ...); tensorboard events are read instead when it is missing;
- ``negative_transfer.jsonl`` (MTSACTE): per recomputation ``timesteps``, ``mu``, ``selected``, ``weights``,
  ``transfer_matrix``;
- ``success.json`` (``sb3-mtte evaluate``): the final evaluation.
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tensorboard.backend.event_processing import event_accumulator

from sb3_mtte.common.utils import task_log_key
from sb3_mtte.envs import MT50_TASKS, REWARD_FUNCTION_VERSIONS
from sb3_mtte.experiments.run_info import RUN_INFO_FILE, read_json, read_npz
from sb3_mtte.experiments.variants import variant_labels
from sb3_mtte.mtsacte.callbacks import NT_LOG_FILE

Series = tuple[np.ndarray, np.ndarray]


def read_progress_csv(path: Path) -> dict[str, Series]:
    """Scalars of an SB3 ``progress.csv``: tag -> (total timesteps, values), rows without the value dropped."""
    with open(path, newline="") as file:
        rows = list(csv.DictReader(file))
    if not rows:
        return {}

    def number(text: str | None) -> float:
        try:
            return float(text) if text not in (None, "") else math.nan
        except ValueError:
            return math.nan

    steps = np.array([number(row.get("time/total_timesteps")) for row in rows])
    scalars = {}
    for key in rows[0]:
        if key is None or key == "time/total_timesteps":
            continue
        values = np.array([number(row.get(key)) for row in rows])
        keep = np.isfinite(values) & np.isfinite(steps)
        if keep.any():
            scalars[key] = (steps[keep], values[keep])
    return scalars


def read_tensorboard(run_dir: Path) -> dict[str, Series]:
    """Scalars of the tensorboard events under ``run_dir``: tag -> (steps, values)."""
    scalars: dict[str, Series] = {}
    folders = sorted({p.parent for p in run_dir.rglob("events.out.tfevents.*")})
    for folder in folders:
        accumulator = event_accumulator.EventAccumulator(str(folder), size_guidance={event_accumulator.SCALARS: 0})
        accumulator.Reload()
        for tag in accumulator.Tags().get("scalars", []):
            events = accumulator.Scalars(tag)
            steps = np.array([e.step for e in events], dtype=float)
            values = np.array([e.value for e in events], dtype=float)
            if tag in scalars:  # several event folders: keep the later folder's values at equal steps
                old_steps, old_values = scalars[tag]
                keep = ~np.isin(old_steps, steps)
                steps, values = np.concatenate([old_steps[keep], steps]), np.concatenate([old_values[keep], values])
            order = np.argsort(steps, kind="stable")
            scalars[tag] = (steps[order], values[order])
    return scalars


@dataclass
class Run:
    """One run folder."""

    path: Path
    info: dict[str, Any]
    evaluations: dict[str, np.ndarray] | None = None
    scalars: dict[str, Series] = field(default_factory=dict)
    nt_records: list[dict[str, Any]] = field(default_factory=list)
    final: dict[str, Any] | None = None

    @property
    def label(self) -> str:
        return str(self.info.get("label") or self.info.get("algo") or self.path.parent.name)

    @property
    def benchmark(self) -> str:
        return str(self.info.get("env_id") or self.info.get("benchmark") or "unknown")

    @property
    def seed(self) -> int | None:
        return self.info.get("seed")

    @property
    def reward_function_version(self) -> str | None:
        """Meta-World's reward functions of the run (runs and records that predate the field used the default,
        ``"v2"``); None off Meta-World."""
        version = self.info.get("reward_function_version")
        if version is None and self.task_names and set(self.task_names) <= set(MT50_TASKS):
            return REWARD_FUNCTION_VERSIONS[0]
        return version

    @property
    def env_protocol(self) -> dict[str, Any] | None:
        """How the training envs differ from Meta-World's benchmark (:func:`sb3_mtte.envs.env_protocol`); None for
        a toy, and for runs and records that predate the field (Meta-World's own envs)."""
        return self.info.get("env_protocol")

    @property
    def mu_computation(self) -> str | None:
        """The precision MTSACTE's transfer matrix, hence mu, was computed in: ``"float64"``, or ``"float32"`` for
        runs and records that predate the field (where rounding can decide mu at large Q); ``"mixed"`` for a run
        resumed across the change; None for an algorithm without mu."""
        if "mu_computation" in self.info:
            return self.info["mu_computation"]
        dtypes = {record.get("transfer_matrix_dtype", "float32") for record in self.nt_records}
        return (dtypes.pop() if len(dtypes) == 1 else "mixed") if dtypes else None

    @property
    def device_type(self) -> str | None:
        """What the run trained on (``"cuda"``, ``"cpu"``; :func:`device_type_of`)."""
        return device_type_of(self.info)

    @property
    def task_names(self) -> list[str]:
        names = self.info.get("task_names")
        if not names and self.evaluations is not None:
            names = [str(n) for n in self.evaluations["task_names"]]
        return list(names or [])

    @property
    def n_tasks(self) -> int:
        return int(self.info.get("n_tasks") or len(self.task_names) or 1)

    def scalar(self, key: str) -> Series | None:
        return self.scalars.get(key)


def load_run(path: Path) -> Run:
    """Read a run folder (see the module docstring)."""
    run = Run(path, read_json(path / RUN_INFO_FILE))
    if (path / "evaluations.npz").is_file():
        run.evaluations = read_npz(path / "evaluations.npz")
    if (path / "progress.csv").is_file():
        run.scalars = read_progress_csv(path / "progress.csv")
    elif any(path.rglob("events.out.tfevents.*")):
        run.scalars = read_tensorboard(path)
    if (path / NT_LOG_FILE).is_file():
        for line in (path / NT_LOG_FILE).read_text().splitlines():
            try:
                run.nt_records.append(json.loads(line))
            except json.JSONDecodeError:
                continue
    if (path / "success.json").is_file():
        run.final = read_json(path / "success.json")
    return run


def discover_runs(runs_dir: str | Path) -> list[Run]:
    """Every run folder (one holding ``run_info.json``) under ``runs_dir``, sorted by path."""
    paths = sorted(p.parent for p in Path(runs_dir).rglob(RUN_INFO_FILE))
    return [load_run(p) for p in paths]


def device_type_of(info: Mapping[str, Any]) -> str | None:
    """What a run trained on (``"cuda"``, ``"cpu"``), from its ``run_info.json`` or record: the device's
    ``trained_on`` (a record's), else the ``--device`` it was given, ``"auto"`` read as CUDA where CUDA was found;
    None when neither says (records that predate the field, all trained on CPUs)."""
    device = info.get("device") or {}
    asked = device.get("trained_on") or (info.get("zoo_args") or {}).get("device")
    if asked is None:
        return None
    asked = str(asked).lower()
    if asked == "auto":
        return "cuda" if device.get("cuda") else "cpu"
    return "cuda" if asked.startswith("cuda") else asked


GPU_SUFFIX = "-gpu"
"""What follows the env id of runs trained on CUDA (``MT10-100k-gpu``), drawn apart from the CPU runs."""
EXACT_MU_SUFFIX = "-exact-mu"
"""What follows the env id of MTSACTE runs whose mu was counted from a float64 transfer matrix
(``MT10-100k-exact-mu``), drawn apart from the float32 runs before them."""


def results_benchmark(
    env_id: str,
    reward_function_version: str | None,
    env_protocol: Mapping[str, Any] | None = None,
    device_type: str | None = None,
    mu_computation: str | None = None,
) -> str:
    """The benchmark a run's results are drawn under: its env id, followed by what sets its runs apart, so that
    they never share a table with the others: its Meta-World reward functions when not the default
    (``MT10-cpu-reward-v1``), its backend when it is not the benchmark's protocol (``MT10-100k-envpool``), and
    :data:`EXACT_MU_SUFFIX` when MTSACTE's mu was not counted in float32, and :data:`GPU_SUFFIX` when it trained
    on CUDA."""
    bench = env_id
    if reward_function_version not in (None, REWARD_FUNCTION_VERSIONS[0]):
        bench += f"-reward-{reward_function_version}"
    if env_protocol and env_protocol.get("benchmark_protocol") is False:
        bench += f"-{env_protocol.get('backend')}"
    if mu_computation not in (None, "float32"):
        bench += EXACT_MU_SUFFIX if mu_computation == "float64" else f"-{mu_computation}-mu"
    return bench + GPU_SUFFIX if device_type == "cuda" else bench


def run_results_benchmark(run: Run) -> str:
    """:func:`results_benchmark` of a run."""
    return results_benchmark(
        run.benchmark, run.reward_function_version, run.env_protocol, run.device_type, run.mu_computation
    )


def group_runs(runs: Sequence[Run]) -> dict[str, dict[str, list[Run]]]:
    """benchmark (:func:`results_benchmark`) -> algorithm label -> runs (its seeds).

    The runs of an algorithm without mu (SAC-MT, say) also stand in the exact-mu group of their benchmark
    (:data:`EXACT_MU_SUFFIX`): how mu is counted does not touch them. A benchmark whose group would then hold only
    such runs is drawn in its exact-mu group alone.
    """
    groups: dict[str, dict[str, list[Run]]] = {}
    for run in runs:
        groups.setdefault(run_results_benchmark(run), {}).setdefault(run.label, []).append(run)
    for bench in [bench for bench in groups if EXACT_MU_SUFFIX in bench]:
        base = bench.replace(EXACT_MU_SUFFIX, "")
        for label, members in groups.get(base, {}).items():
            without_mu = [run for run in members if run.mu_computation is None]
            if without_mu and label not in groups[bench]:
                groups[bench][label] = without_mu
        if all(run.mu_computation is None for members in groups.get(base, {}).values() for run in members):
            groups.pop(base, None)
    return groups


def label_order(labels: Sequence[str]) -> list[str]:
    """``labels`` in the order of the variants (Table 1, then Fig. 7), then anything else alphabetically."""
    known = variant_labels()
    return [label for label in known if label in labels] + sorted(label for label in labels if label not in known)


def table_order(groups: dict[str, list[Run]]) -> list[Run]:
    """The runs of ``groups`` in label order (:func:`label_order`), each label's by seed (unknown seed first)."""
    return [
        run
        for label in label_order(list(groups))
        for run in sorted(groups[label], key=lambda r: -1 if r.seed is None else r.seed)
    ]


def success_curve(run: Run, task: int | None = None, training_episodes: bool = True) -> Series | None:
    """Success over time (mean over tasks, or of task ``task``): evaluations, else eval/ scalars, else (with
    ``training_episodes``) the stochastic training episodes' rollout/ scalars."""
    if run.evaluations is not None and len(run.evaluations.get("timesteps", [])):
        rates = np.asarray(run.evaluations["success_rate"], dtype=float)
        values = rates.mean(axis=1) if task is None else rates[:, task]
        return np.asarray(run.evaluations["timesteps"], dtype=float), values
    for prefix in ("eval", "rollout") if training_episodes else ("eval",):
        if task is None:
            series = run.scalar(f"{prefix}/success_rate")
        else:
            series = run.scalar(task_log_key(f"{prefix}/success", task, run.task_names[task]))
        if series is not None:
            return series
    if task is None:  # mean of the per-task curves
        curves = [success_curve(run, i, training_episodes) for i in range(run.n_tasks)]
        if all(c is not None for c in curves) and curves:
            return mean_std([c for c in curves if c is not None])[:2]
    return None


def task_scalar(run: Run, prefix: str, task: int) -> Series | None:
    return run.scalar(task_log_key(prefix, task, run.task_names[task] if task < len(run.task_names) else None))


def smooth(values: np.ndarray, window: int) -> np.ndarray:
    """Trailing moving average over ``window`` points (1 = none)."""
    if window <= 1 or len(values) < 2:
        return values
    cumsum = np.cumsum(np.insert(np.asarray(values, dtype=float), 0, 0.0))
    out = np.empty(len(values))
    for j in range(len(values)):
        lo = max(0, j + 1 - window)
        out[j] = (cumsum[j + 1] - cumsum[lo]) / (j + 1 - lo)
    return out


def mean_std(curves: Sequence[Series]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean and std over curves (seeds) on a common x grid (their shared range; interpolated where needed)."""
    curves = [(np.asarray(x, float), np.asarray(y, float)) for x, y in curves if len(x)]
    if not curves:
        return np.zeros(0), np.zeros(0), np.zeros(0)
    if len(curves) == 1:
        x, y = curves[0]
        return x, y, np.zeros_like(y)
    grid = common_grid(curves)
    stacked = np.stack([np.interp(grid, x, y) for x, y in curves])
    return grid, stacked.mean(axis=0), stacked.std(axis=0)


def common_grid(curves: Sequence[Series]) -> np.ndarray:
    """The x values of all ``curves`` within their shared range (the first curve's x when they share none)."""
    lo, hi = max(x.min() for x, _ in curves), min(x.max() for x, _ in curves)
    grid = np.unique(np.concatenate([x[(x >= lo) & (x <= hi)] for x, _ in curves]))
    return grid if len(grid) else np.asarray(curves[0][0], float)


def nt_arrays(run: Run, key: str) -> tuple[np.ndarray, np.ndarray]:
    steps = np.array([record["timesteps"] for record in run.nt_records], dtype=float)
    values = np.array([record[key] for record in run.nt_records], dtype=float)
    return steps, values


def train_frequency(run: Run, window_steps: float) -> tuple[np.ndarray, np.ndarray]:
    """Fraction of the recomputations within the last ``window_steps`` (total env steps) in which each task was
    in C_s: ``(steps (R,), frequency (R, N))``."""
    steps, selected = nt_arrays(run, "selected")
    freq = np.empty_like(selected)
    start = 0
    for j, t in enumerate(steps):
        while steps[start] <= t - window_steps:
            start += 1
        freq[j] = selected[start : j + 1].mean(axis=0)
    return steps, freq


def episode_length(run: Run) -> int:
    length = run.info.get("episode_length")
    if length:
        return int(length)
    return 50 if str(run.info.get("benchmark", "")).startswith("toy") else 500


def nt_series(run: Run, key: str, task: int) -> Series:
    steps, values = nt_arrays(run, key)
    return steps, values[:, task]
