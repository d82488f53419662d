"""Learning runs side by side on one machine, resumable across calls: train, evaluate, record.

    python scripts/gpu/learning_runs.py --runs-dir DIR --out OUT [--env MT10-100k] [--algos mtsac_mt [mtsacte]]
        [--seeds 0 1] [--budget-s 450] [--device cuda] [--episodes 50] [--cores N] [--threads-per-run 1]

Each algorithm's seeds train side by side, each run on its own block of cores (``taskset``) with its own torch
threads and its own run folder ``DIR/<algo>/<env>_<seed + 1>``. The algorithms follow one another; the next one
starts once the earlier one's runs have ended.

A call ends within ``--budget-s`` of its start. A run that cannot finish in time is stopped right after its last
checkpoint that fits, so that no training is lost. The same command in a later call, with ``DIR`` kept, resumes
it exactly (``sb3-mtte train --resume``). A run whose training finished is evaluated (``sb3-mtte evaluate``,
``--episodes`` per task, on ``--device``), then recorded (``sb3-mtte record``) into
``OUT/records/<env>-gpu/<algo>_seed<k>.json``. A run that did not finish is never evaluated or recorded.

Written into OUT after every phase: ``learning_runs.json`` (every run's state, wall time and env steps/s, in this
call and over all calls) and ``run_files.tar.gz`` (each run folder's small files: ``sb3-mtte record`` can be run
on them again elsewhere). Each run folder keeps ``learning_calls.json``, one entry per call.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from learning_folders import (
    RUN_FILES,
    SUMMARY_FILE,
    Run,
    checkpoint_markers,
    core_list,
    last_logged_fps,
    read_json,
    record_name,
    run_dir_of,
    run_state,
    steps_reached,
    write_output,
)

POLL_S = 2.0
HARD_MARGIN_S = 15.0
"""Before the deadline, a run still training is stopped whatever its checkpoints."""
RECORD_RESERVE_S = 40.0
"""Kept after the evaluations for the records and the summary."""
ETA_FACTOR, ETA_SLACK_S = 1.25, 10.0
"""How pessimistic the forecast of a run's next checkpoint and of its end is."""
FINAL_SAVE_S = 15.0
PREFLIGHT = """
import json, sb3_mtte, torch
import sb3_mtte.experiments.results.records, sb3_mtte.experiments.zoo.launcher
from sb3_mtte.experiments.zoo.configs import find_config_dir
assert (find_config_dir() / "mtsac.yml").is_file(), "no zoo_configs in " + sb3_mtte.__file__
cuda = torch.cuda.is_available()
print(json.dumps({"sb3_mtte": sb3_mtte.__version__, "sb3_mtte_at": sb3_mtte.__file__, "torch": torch.__version__,
                  "device_name": torch.cuda.get_device_name(0) if cuda else None}))
"""
"""What the runs import, checked before any starts: the installed package (its hyperparameter files inside it)."""


# ---------------------------------------------------------------------------------------------------- the plan
def plan_cores(cores: Sequence[int], n_runs: int) -> list[list[int]]:
    """``cores`` cut into ``n_runs`` contiguous blocks of nearly equal size (the first blocks one larger)."""
    if n_runs < 1 or n_runs > len(cores):
        raise ValueError(f"{n_runs} runs side by side on {len(cores)} cores: give at most one run per core.")
    size, extra = divmod(len(cores), n_runs)
    blocks, start = [], 0
    for k in range(n_runs):
        end = start + size + (k < extra)
        blocks.append(list(cores[start:end]))
        start = end
    return blocks


def plan_runs(args: argparse.Namespace, cores: Sequence[int]) -> list[list[Run]]:
    """One group of side-by-side runs per algorithm, each run with its block of ``cores``."""
    groups = []
    for algo in args.algos:
        blocks = plan_cores(cores, len(args.seeds))
        groups.append([
            Run(algo, seed, args.env, run_dir_of(args.runs_dir, algo, args.env, seed), block)
            for seed, block in zip(args.seeds, blocks, strict=True)
        ])  # fmt: skip
    return groups


# ------------------------------------------------------------------------------------------------ a run's state
def should_stop(
    now: float, deadline: float, markers: Sequence[tuple[int, float]], started: float, save_freq: int, n_steps: int
) -> bool:
    """Whether to stop a training run now, right after its newest checkpoint: neither its end nor its next
    checkpoint is forecast before the deadline (a later stop would lose what it trained since)."""
    if not markers or save_freq <= 0:
        return False
    (steps, at), earlier = markers[-1], markers[:-1]
    if steps >= n_steps:
        return False  # the run is saving its final model
    since_steps, since_time = (earlier[-1][0], earlier[-1][1]) if earlier else (None, started)
    if since_steps is None:
        return False  # one checkpoint: the pace since the start includes the set-up, too slow to forecast with
    pace = (steps - since_steps) / max(at - since_time, 1e-6)
    left = deadline - now

    def eta(more_steps: float) -> float:
        return ETA_FACTOR * more_steps / pace + ETA_SLACK_S

    end_fits = eta(n_steps - steps) + FINAL_SAVE_S <= left
    next_fits = steps + save_freq < n_steps and eta(save_freq) <= left  # none is taken at the end
    return not (end_fits or next_fits)


# ---------------------------------------------------------------------------------------------------- commands
def sb3_mtte(python: str, run: Run, *args: str) -> list[str]:
    """``sb3-mtte`` on the run's cores (``taskset``, where the machine has it; its env processes inherit them)."""
    pin = ["taskset", "-c", core_list(run.cores)] if shutil.which("taskset") else []
    return [*pin, python, "-m", "sb3_mtte", *args]


def cores_of(pid: int) -> str | None:
    """The cores a process may run on, as ``taskset`` writes them (None once it has ended)."""
    try:
        return core_list(sorted(os.sched_getaffinity(pid)))
    except OSError:
        return None


def train_command(run: Run, state: str, python: str, device: str, threads: int, runs_dir: Path) -> list[str]:
    """``sb3-mtte train`` of a new run (seed, experiment id) or of the resumption of its folder."""
    args = ["train", "--algo", run.algo, "--env", run.env_id, "-f", str(runs_dir), "--no-progress"]
    if state == "new":
        args += ["--seed", str(run.seed), "--exp-id", str(run.seed + 1)]
    else:
        args += ["--resume", str(run.run_dir)]
    return sb3_mtte(python, run, *args, "--device", device, "--num-threads", str(threads))


def evaluate_command(run: Run, python: str, device: str, episodes: int) -> list[str]:
    info = read_json(run.run_dir / "run_info.json") or {}
    model = run.run_dir / str(info.get("final_model") or f"{run.env_id}.zip")
    return sb3_mtte(python, run, "evaluate", str(model), "--episodes", str(episodes), "--device", device,
                    "--no-progress")  # fmt: skip


def launch(command: list[str], log: Path, cwd: Path) -> subprocess.Popen:
    """Start ``command`` in its own process group (it and its env processes stop together), output to ``log``.

    It runs in ``cwd``, the runs' folder, so that ``python -m`` finds the installed package rather than a
    checkout's (whose ``sb3_mtte.zoo_configs`` exists only once installed)."""
    log.parent.mkdir(parents=True, exist_ok=True)
    with log.open("a") as handle:
        handle.write(f"\n$ {' '.join(command)}\n")
        handle.flush()
        return subprocess.Popen(command, cwd=cwd, stdout=handle, stderr=subprocess.STDOUT, start_new_session=True)


def preflight(python: str, runs_dir: Path) -> dict[str, Any]:
    """The package and torch the runs will use; exits with the error when an import fails."""
    result = subprocess.run([python, "-c", PREFLIGHT], cwd=runs_dir, capture_output=True, text=True, check=False)
    if result.returncode:
        sys.exit(f"the runs cannot start: {result.stderr.strip().splitlines()[-1]}")
    return json.loads(result.stdout.strip().splitlines()[-1])


def stop(process: subprocess.Popen) -> None:
    """End a process group: SIGTERM, then SIGKILL after 15 s."""
    for sig, wait in ((signal.SIGTERM, 15), (signal.SIGKILL, 5)):
        if process.poll() is not None:
            return
        try:
            os.killpg(process.pid, sig)
        except ProcessLookupError:
            return
        try:
            process.wait(wait)
        except subprocess.TimeoutExpired:
            continue


# ------------------------------------------------------------------------------------------------------ phases
def hyperparameter(run: Run, key: str, default: int) -> int:
    info = read_json(run.run_dir / "run_info.json") or {}
    value = info.get("n_timesteps") if key == "n_timesteps" else (info.get("hyperparams") or {}).get(key)
    return int(value) if value is not None else default


def train_group(runs: list[Run], ctx: argparse.Namespace, deadline: float) -> None:
    """Train (or resume) every unfinished run of a group side by side until each finishes or is stopped."""
    active: dict[str, tuple[Run, subprocess.Popen, float]] = {}
    for run in runs:
        if run.state_before == "new" and run.run_dir.is_dir():  # a start cut short before its run_info.json
            shutil.rmtree(run.run_dir)
        if run.state_before in ("new", "unfinished"):
            command = train_command(run, run.state_before, ctx.python, ctx.device, ctx.threads_per_run, ctx.runs_dir)
            run.call.update(steps_before=steps_reached(run.run_dir), command=" ".join(command))
            log = ctx.runs_dir / "logs" / f"{run.name}.log"
            active[run.name] = (run, launch(command, log, ctx.runs_dir), time.time())
    seen: dict[str, int] = {}
    while active:
        time.sleep(POLL_S)
        now = time.time()
        for name, (run, process, started) in list(active.items()):
            run.call.setdefault("pinned_to", cores_of(process.pid))  # once taskset has handed over to the run
            markers = checkpoint_markers(run.run_dir)
            fresh = len(markers) > seen.get(name, 0)
            seen[name] = len(markers)
            reason = None
            if process.poll() is not None:
                reason = f"exited {process.returncode}"
            elif now >= deadline - HARD_MARGIN_S:
                reason = "stopped at the deadline"
            elif fresh and should_stop(now, deadline, markers, started, hyperparameter(run, "save_freq", 0),
                                       hyperparameter(run, "n_timesteps", 0)):  # fmt: skip
                reason = f"stopped after the checkpoint at {markers[-1][0]} env steps"
            if reason is None:
                continue
            stop(process)
            end_training(run, started, reason)
            del active[name]


def end_training(run: Run, started: float, reason: str) -> None:
    wall = time.time() - started
    after = steps_reached(run.run_dir)
    gained = after - run.call.get("steps_before", 0)
    run.call.update(train_wall_s=round(wall, 1), steps_after=after, train_end=reason)
    run.call["env_steps_per_s"] = round(gained / wall, 1) if wall > 0 else None
    run.call["logged_fps"] = last_logged_fps(run.run_dir)
    run.events.append(f"training: {reason}, {run.call['steps_before']} -> {after} env steps in {wall:.0f} s")


def evaluate_group(runs: list[Run], ctx: argparse.Namespace, deadline: float) -> None:
    """The final evaluation of every run of the group whose training finished, side by side; one still running at
    the deadline is stopped and left for the next call."""
    chosen = [run for run in runs if run_state(run.run_dir) == "trained"]
    started = time.time()
    processes = [(run, launch(evaluate_command(run, ctx.python, ctx.device, ctx.episodes),
                              ctx.runs_dir / "logs" / f"{run.name}.log", ctx.runs_dir)) for run in chosen]  # fmt: skip
    for run, process in processes:
        try:
            process.wait(max(deadline - RECORD_RESERVE_S - time.time(), 1))
        except subprocess.TimeoutExpired:
            stop(process)
        wall = time.time() - started
        done = process.returncode == 0 and run_state(run.run_dir) == "evaluated"
        run.call.update(evaluate_wall_s=round(wall, 1), evaluated=done)
        run.events.append(f"evaluation: {'done' if done else f'not done (exit {process.returncode})'} in {wall:.0f} s")


def record_group(runs: list[Run], ctx: argparse.Namespace) -> None:
    """``sb3-mtte record`` of every evaluated, finished run into ``OUT/records/<env>-gpu/``."""
    for run in runs:
        target = ctx.out / "records" / record_name(run.env_id, run.algo, run.seed)
        if run_state(run.run_dir) != "evaluated" or target.is_file():
            continue
        staging = ctx.runs_dir / "records_staging" / run.name
        command = [ctx.python, "-m", "sb3_mtte", "record", str(run.run_dir), "--out", str(staging)]
        result = subprocess.run(command, cwd=ctx.runs_dir, capture_output=True, text=True, check=False)
        written = [Path(line) for line in result.stdout.split() if line.endswith(".json")]
        if result.returncode or len(written) != 1:
            run.events.append(f"record: failed (exit {result.returncode}): {result.stderr.strip()[-300:]}")
            continue
        record = json.loads(written[0].read_text())
        if not (record.get("budget") or {}).get("finished"):
            run.events.append("record: refused, the record says the run did not finish")
            continue
        info = read_json(run.run_dir / "run_info.json") or {}
        if ctx.commit and not (record.get("git") or {}).get("commit"):  # the installed package is no git tree
            record["git"] = {"commit": ctx.commit, "branch": None, "dirty": None}
        if "device" not in record:  # the record format names no device: the run's own, from run_info.json
            trained_on = (info.get("zoo_args") or {}).get("device")
            record["device"] = {**(info.get("device") or {}), "host": info.get("host"), "trained_on": trained_on}
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_text(json.dumps(record, indent=1) + "\n")
        run.call["record"] = str(target.relative_to(ctx.out))
        run.events.append(f"record: {target.relative_to(ctx.out)} (final {record['final']['mean']:.3f})")


# ---------------------------------------------------------------------------------------------------- the call
def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs-dir", type=Path, required=True, help="run folders (kept between calls to resume)")
    parser.add_argument("--out", type=Path, required=True, help="records, summary and the run folders' small files")
    parser.add_argument("--env", default="MT10-100k", help="env id (default MT10-100k)")
    parser.add_argument("--algos", nargs="+", default=["mtsac_mt"], help="zoo keys, one after another")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1], help="seeds side by side (default 0 1)")
    parser.add_argument("--budget-s", type=float, default=450.0, help="seconds this call may take (default 450)")
    parser.add_argument("--device", default="cuda", help="torch device of training and evaluation (default cuda)")
    parser.add_argument("--episodes", type=int, default=50, help="final evaluation episodes per task (default 50)")
    parser.add_argument("--cores", type=int, default=None, help="cores to use (default: all this process may use)")
    parser.add_argument("--threads-per-run", type=int, default=1, help="torch threads of each run (default 1)")
    parser.add_argument("--python", default=sys.executable, help="interpreter of the runs (default: this one)")
    parser.add_argument("--commit", default=None, help="the checkout's commit, for records that name none")
    args = parser.parse_args(argv)
    available = sorted(os.sched_getaffinity(0))
    problem = None
    if len(set(args.seeds)) != len(args.seeds) or min(args.seeds) < 0:
        problem = f"--seeds {' '.join(map(str, args.seeds))}: give distinct seeds of 0 or more"
    elif len(set(args.algos)) != len(args.algos):
        problem = f"--algos {' '.join(args.algos)}: an algorithm is given twice"
    elif args.budget_s <= 2 * HARD_MARGIN_S:
        problem = f"--budget-s {args.budget_s:g}: give more than {2 * HARD_MARGIN_S:g} seconds"
    elif args.episodes < 1 or args.threads_per_run < 1:
        problem = "--episodes and --threads-per-run: give 1 or more"
    elif args.cores is not None and not len(args.seeds) <= args.cores <= len(available):
        problem = f"--cores {args.cores}: give from {len(args.seeds)} (one per run) to {len(available)} (this machine)"
    elif len(args.seeds) > len(available):
        problem = f"--seeds: {len(args.seeds)} runs side by side need as many cores; this machine has {len(available)}"
    if problem:
        parser.error(problem)
    args.core_ids = available[: args.cores or len(available)]
    args.runs_dir, args.out = args.runs_dir.resolve(), args.out.resolve()
    return args


def main(argv: Sequence[str] | None = None) -> int:
    call_started = time.time()
    ctx = parse_args(argv)
    deadline = call_started + ctx.budget_s
    ctx.out.mkdir(parents=True, exist_ok=True)
    ctx.runs_dir.mkdir(parents=True, exist_ok=True)
    ctx.software = preflight(ctx.python, ctx.runs_dir)
    print(f"sb3_mtte {ctx.software['sb3_mtte']} at {ctx.software['sb3_mtte_at']}, torch {ctx.software['torch']}, "
          f"device {ctx.software['device_name'] or ctx.device}")  # fmt: skip
    groups = plan_runs(ctx, ctx.core_ids)
    for runs in groups:
        for run in runs:
            run.state_before = run_state(run.run_dir)
        if time.time() < deadline - 2 * HARD_MARGIN_S:
            train_group(runs, ctx, deadline)
            evaluate_group(runs, ctx, deadline)
            record_group(runs, ctx)
        write_output(groups, ctx, call_started, final=False)
    write_output(groups, ctx, call_started, final=True)
    for run in (run for group in groups for run in group):
        print(f"{run.name}: {run.state_before} -> {run_state(run.run_dir)}; " + "; ".join(run.events))
    print(f"wrote {ctx.out / SUMMARY_FILE} and {ctx.out / RUN_FILES} after {time.time() - call_started:.0f} s")
    crashed = [run.name for group in groups for run in group if run.call.get("train_end", "").startswith("exited ")
               and run.call["train_end"] != "exited 0"]  # fmt: skip
    if crashed:
        print(f"training failed: {', '.join(crashed)} (their logs: {ctx.runs_dir / 'logs'})", file=sys.stderr)
    return 1 if crashed else 0


if __name__ == "__main__":
    sys.exit(main())
