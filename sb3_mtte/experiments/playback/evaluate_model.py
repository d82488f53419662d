"""Per-task success of a trained model with Meta-World's official protocol.

Usage::

    sb3-mtte evaluate MODEL.zip [--env MT10] [--episodes 50] [--seed S] [--device cpu] [--out PATH] [--no-progress]

MODEL is a checkpoint of MTSAC or MTSACTE (the class is read from the zip). Each task runs ``--episodes``
episodes, one per goal variation in order, with deterministic actions (:func:`sb3_mtte.evaluate_success`).
The env and the benchmark seed default to those of the run folder holding the model (its ``run_info.json``); a
model outside its run folder is evaluated on the tasks its checkpoint names, with seed 0. The run's Meta-World
reward functions are kept (they decide success in some tasks). An env id with a budget suffix (``MT10-smoke``)
names its benchmark (``MT10``). An ``--env`` whose tasks are not the model's (``toy-agree`` for a ``toy-conflict``
model) is refused unless ``--other-benchmark`` is given, which evaluates it there with a warning.

The output path is checked before the evaluation starts. The per-task table is printed and written as JSON beside
the model: ``success.json`` for the run's final model, ``success_<model name>.json`` for any other file
(checkpoints, ``best_model.zip``), and ``success_<model name>_on_<env id>.json`` for an evaluation on another
benchmark (never read as the run's final).
"""

from __future__ import annotations

import contextlib
import json
import os
import sys
import time
import zipfile
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

from stable_baselines3.common.base_class import BaseAlgorithm

from sb3_mtte.common.checkpoints import read_checkpoint_data
from sb3_mtte.evaluation import SuccessResult, evaluate_success
from sb3_mtte.envs import MT50_TASKS, reward_function_version
from sb3_mtte.experiments import run_info
from sb3_mtte.experiments.cli import CommandParser, command_prog, device_error, output_file_error
from sb3_mtte.experiments.env_ids import benchmark_task_names, env_id_of_tasks, split_env_id
from sb3_mtte.experiments.zoo.run_checkpoints import load_model


def default_output_path(
    model_path: str | os.PathLike, info: dict[str, Any] | None, other_env_id: str | None = None
) -> Path:
    """``success.json`` beside the run's final model, ``success_<stem>.json`` beside any other model file, and
    ``success_<stem>_on_<env id>.json`` for an evaluation on another benchmark than the model's."""
    model_path = Path(model_path)
    if other_env_id is not None:
        return model_path.with_name(f"success_{model_path.stem}_on_{other_env_id}.json")
    final = (info or {}).get("final_model") or (f"{info['env_id']}.zip" if info and "env_id" in info else None)
    if final is not None and model_path.name == final:
        return model_path.with_name("success.json")
    return model_path.with_name(f"success_{model_path.stem}.json")


def format_table(result: SuccessResult, title: str | None = None) -> str:
    """The per-task success rates as a markdown table, with their mean."""
    width = max([len("task"), *(len(name) for name in result.task_names)])
    lines = [] if title is None else [title, ""]
    lines.append(f"| {'#':>2} | {'task':<{width}} | success |")
    lines.append(f"|---:|:{'-' * (width + 1)}|--------:|")
    for i, (name, rate) in enumerate(zip(result.task_names, result.success_rate, strict=True)):
        lines.append(f"| {i:>2} | {name:<{width}} | {100 * rate:6.1f}% |")
    lines.append(f"|    | {'mean':<{width}} | {100 * result.mean:6.1f}% |")
    return "\n".join(lines)


def evaluate_model(
    model_path: str | os.PathLike,
    env: str | None = None,
    episodes: int = 50,
    seed: int | None = None,
    device: str = "auto",
    out: str | os.PathLike | None = None,
    stochastic: bool = False,
    other_benchmark: bool = False,
    progress: bool = False,
) -> dict[str, Any]:
    """Evaluate a saved model, print the table, write the JSON and return its content.

    :param model_path: the model zip (MTSAC or MTSACTE).
    :param env: benchmark or env id; default: the run's (``run_info.json`` beside the model).
    :param episodes: episodes per task.
    :param seed: benchmark seed; default: the run's benchmark seed, else 0.
    :param device: torch device.
    :param out: JSON path (default: :func:`default_output_path`).
    :param stochastic: sample actions instead of the deterministic ones.
    :param other_benchmark: evaluate a model on a benchmark other than the one it was trained on (else refused).
    :param progress: show a progress bar per task (rich, as SB3's ``progress_bar``).
    """
    model_path = Path(model_path)
    data = _checkpoint_data(model_path)
    info = run_info.read_run_info(model_path.parent) or {}
    env_id = env or info.get("env_id") or _env_id_of_checkpoint(model_path, data, seed)
    check_counts(episodes, seed)
    benchmark = _benchmark_of(env_id)
    seed = int(info.get("benchmark_seed", 0)) if seed is None else seed
    _check_task_count(model_path, data, env_id, benchmark)
    elsewhere = _check_benchmark(model_path, data, info, env_id, benchmark, other_benchmark)
    out_path = Path(out) if out is not None else default_output_path(model_path, info, env_id if elsewhere else None)
    problem = output_file_error("--out", out_path)
    if problem:
        raise ValueError(problem)
    model = _load_model_of_run(model_path, info, device)
    version = info.get("reward_function_version")
    env_kwargs = {} if version is None else {"reward_function_version": version}
    start = time.time()
    tasks = benchmark if isinstance(benchmark, list) else benchmark_task_names(benchmark)
    with task_progress(tasks, episodes, progress) as on_episode:
        result = evaluate_success(
            model,
            benchmark,
            episodes_per_task=episodes,
            deterministic=not stochastic,
            seed=seed,
            env_kwargs=env_kwargs,
            on_episode=on_episode,
        )
    record = {
        **result.as_dict(),
        "success_rate": [float(r) for r in result.success_rate],
        "task_names": list(result.task_names),
        "model": str(model_path),
        "algorithm": data.get("algorithm_name"),
        "algo": info.get("algo"),
        "label": info.get("label"),
        "env_id": env_id,
        "benchmark": benchmark,
        "reward_function_version": reward_function_version(benchmark, env_kwargs),
        "seed": seed,
        "run_seed": info.get("seed"),
        "episodes_per_task": episodes,
        "deterministic": not stochastic,
        "timesteps": int(data.get("num_timesteps", 0)),
        "evaluation_seconds": round(time.time() - start, 2),
        "time": run_info.now(),
    }
    _report(record, result, out_path)
    return record


@contextlib.contextmanager
def task_progress(task_names: Sequence[str], episodes: int, enabled: bool) -> Iterator[Callable[[int], None] | None]:
    """A progress bar per task (rich, as SB3's ``progress_bar``) for the time of a ``with`` block; it yields the
    function that counts an episode of task ``i`` (None when not ``enabled``)."""
    if not enabled:
        yield None
        return
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
    with Progress(*columns) as bars:
        ids = [bars.add_task(name, total=episodes) for name in task_names]
        yield lambda i: bars.advance(ids[i])


def evaluation_title(record: dict[str, Any]) -> str:
    """The header of an evaluation's table: model, env id (the run's, e.g. ``MT10-smoke``), benchmark seed, steps,
    episodes and Meta-World's reward functions (a benchmark's success differs between them)."""
    episodes, env_id = record["episodes_per_task"], record.get("env_id") or record["benchmark"]
    title = (
        f"{record['label'] or record['algorithm']} on {env_id} (seed {record['seed']}), "
        f"{record['timesteps']} steps, {episodes} episode{'' if episodes == 1 else 's'} per task"
    )
    version = record.get("reward_function_version")
    return title if version is None else f"{title}, Meta-World reward functions {version}"


def _report(record: dict[str, Any], result: SuccessResult, out_path: Path) -> None:
    """Write ``record`` as JSON at ``out_path`` and print its per-task table."""
    out_path.parent.mkdir(parents=True, exist_ok=True)
    out_path.write_text(json.dumps(record, indent=2) + "\n")
    print(format_table(result, evaluation_title(record)))
    print(f"\nWritten to {out_path}")


def check_counts(episodes: int, seed: int | None) -> None:
    """Refuse no episode and a negative benchmark seed, naming the flag, before anything is drawn."""
    if isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 1:
        raise ValueError(f"--episodes {episodes}: give at least 1 episode per task (e.g. --episodes 50).")
    if seed is not None and not 0 <= seed < 2**32:
        raise ValueError(f"--seed {seed}: the benchmark seed is an int from 0 to 2**32 - 1, e.g. --seed 0.")


def _env_id_of_checkpoint(model_path: Path, data: dict[str, Any], seed: int | None) -> str:
    """The benchmark of a model without its run folder, read from the task names its checkpoint holds."""
    task_names = data.get("task_names")
    env_id = None if not task_names else env_id_of_tasks(task_names)
    if env_id is None:
        raise ValueError(f"No run_info.json beside {model_path}, and its checkpoint names no benchmark: pass --env.")
    print(
        f"No run_info.json beside {model_path}: evaluating on {env_id}, the tasks of its checkpoint, with benchmark "
        f"seed {0 if seed is None else seed} (--env and --seed choose others).",
        file=sys.stderr,
    )
    return env_id


def _benchmark_of(env_id: str) -> str | list[str]:
    """The benchmark an env id names: a benchmark (``MT10-smoke`` -> ``MT10``) or one Meta-World env name."""
    benchmark = split_env_id(env_id)[0]
    if benchmark in MT50_TASKS:
        return [benchmark]
    benchmark_task_names(benchmark)  # a clear ValueError for an unknown name
    return benchmark


def _check_benchmark(
    model_path: Path,
    data: dict[str, Any],
    info: dict[str, Any] | None,
    env_id: str,
    benchmark: str | list[str],
    allowed: bool,
) -> bool:
    """Whether the model's tasks (from its checkpoint, else its run) are not those of ``benchmark``: refused unless
    ``allowed``, then warned about in one line naming both benchmarks."""
    trained = data.get("task_names") or (info or {}).get("task_names")
    tasks = benchmark if isinstance(benchmark, list) else benchmark_task_names(benchmark)
    if not trained or list(trained) == list(tasks):
        return False
    trained_on = (info or {}).get("env_id") or f"the tasks {', '.join(trained)}"
    if not allowed:
        raise ValueError(
            f"{model_path} was trained on {trained_on}, not {env_id}: pass the --env it was trained on, or "
            "--other-benchmark to evaluate it there anyway."
        )
    print(f"Warning: {model_path} was trained on {trained_on}; evaluating it on {env_id}.", file=sys.stderr)
    return True


def _checkpoint_data(model_path: Path) -> dict[str, Any]:
    if not model_path.is_file():
        raise FileNotFoundError(f"No model at {model_path}: pass the path of a model zip (e.g. <run>/<env>.zip).")
    try:
        return read_checkpoint_data(model_path)
    except (zipfile.BadZipFile, KeyError, ValueError) as error:
        raise ValueError(
            f"{model_path} is not a complete SB3 checkpoint ({error}): it may be truncated; evaluate another "
            "checkpoint of the run (rl_model_<steps>_steps.zip, best_model.zip)."
        ) from None


def _check_task_count(model_path: Path, data: dict[str, Any], env_id: str, benchmark: str | list[str]) -> None:
    n_tasks = data.get("n_tasks")
    n_env = len(benchmark) if isinstance(benchmark, list) else len(benchmark_task_names(benchmark))
    if n_tasks is not None and n_tasks != n_env:
        raise ValueError(
            f"{model_path} was trained on {n_tasks} tasks; {env_id} has {n_env}: pass --env with the benchmark "
            "the model was trained on."
        )


def _load_model_of_run(model_path: Path, info: dict[str, Any] | None, device: str) -> BaseAlgorithm:
    """Load a model zip, checking its task count against its run's."""
    if not model_path.is_file():
        raise FileNotFoundError(f"No model at {model_path}.")
    model = load_model(model_path, device=device)
    if model.n_tasks and info and info.get("n_tasks") not in (None, model.n_tasks):
        raise ValueError(f"{model_path} has {model.n_tasks} tasks, its run {info['n_tasks']}.")
    return model


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """``sb3-mtte evaluate MODEL [--env ENV] [--episodes 50] [--seed S] [--device D] [--out PATH]``"""
    parser = CommandParser(prog=command_prog("evaluate"), description=__doc__.split("\n\n")[0])
    parser.add_argument("model", help="model zip (MTSAC or MTSACTE)")
    parser.add_argument("--env", default=None, help="benchmark or env id (default: the run's)")
    parser.add_argument("--episodes", type=int, default=50, help="episodes per task (default 50)")
    parser.add_argument("--seed", type=int, default=None, help="benchmark seed (default: the run's, else 0)")
    parser.add_argument("--device", default="auto", help="torch device (default auto)")
    parser.add_argument("--out", default=None, help="JSON path (default: success.json beside the model)")
    parser.add_argument("--stochastic", action="store_true", help="sample actions")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars (default: one per task)")
    parser.add_argument(
        "--other-benchmark",
        action="store_true",
        help="evaluate on --env although the model was trained on another benchmark (default: refused)",
    )
    args = parser.parse_args(list(sys.argv[1:] if argv is None else argv))
    out_error = None if args.out is None else output_file_error("--out", args.out)
    out_error = device_error("--device", args.device) or out_error
    try:
        check_counts(args.episodes, args.seed)
    except ValueError as error:
        out_error = str(error)
    if out_error:
        parser.exit(2, f"{parser.prog}: error: {out_error}\n")
    try:
        return evaluate_model(
            args.model,
            args.env,
            args.episodes,
            args.seed,
            args.device,
            args.out,
            args.stochastic,
            args.other_benchmark,
            progress=not args.no_progress,
        )
    except (FileNotFoundError, ValueError) as error:
        parser.exit(2, f"{parser.prog}: error: {error}\n")
