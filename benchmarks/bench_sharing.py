"""Throughput of training processes that share the machine: one alone, then two side by side.

Each worker is a fresh interpreter started the way users start scripts (no OpenMP or malloc variables of their own
unless a setting gives some): it builds MTSAC (2 x 400, N = 10, batch 128 per task) on synthetic replay data, waits for
a common start time and counts updates for ``--seconds``. For every setting the benchmark reports updates/s of one
process alone, of each of two processes started together, and each one's fraction of the solo figure; rounds alternate
the settings so that drift of the machine hits them alike (medians over rounds).

    python benchmarks/bench_sharing.py --rounds 4 --seconds 10 --out docs/results/sharing_cpu.json
    python benchmarks/bench_sharing.py --setting "libgomp default=GOMP_SPINCOUNT=300000" \
        --setting "spin 3000=GOMP_SPINCOUNT=3000"

A setting is ``label=VAR=value,VAR=value`` (``label=`` alone: no variables). ``default`` is what the package's
commands do (``sb3_mtte.tune_process()`` before torch loads); ``torch-first`` imports torch first, so the spin count
stays libgomp's; ``libgomp default``
is the runtime's own spin count, the package's behaviour before it set one; ``glibc malloc=SB3_MTTE_MALLOC=default``
keeps glibc's malloc thresholds (the package's behaviour before it raised them).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

from process_defaults import USER_VARIABLES as PROCESS_VARIABLES  # the variables a worker starts without

DEFAULT_SETTINGS = (
    "default=",
    "torch-first=",
    "libgomp default=GOMP_SPINCOUNT=300000",
)


def worker(start_at: float, seconds: float, torch_first: bool) -> None:
    """Train on synthetic data from ``start_at`` for ``seconds``; print updates/s as JSON."""
    if torch_first:
        import torch  # noqa: F401  # a script that imports torch before the package
    import sb3_mtte

    sb3_mtte.tune_process()  # as the package's commands do; after torch it leaves the spin count alone
    from bench_updates import fill_buffer, quiet, synthetic_env

    model = quiet(sb3_mtte.MTSAC("MlpPolicy", synthetic_env(10), buffer_size=5120, device="cpu", seed=0))
    fill_buffer(model, 512)
    for _ in range(3):
        model.train(1, 128)
    time.sleep(max(0.0, start_at - time.time()))
    updates, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        model.train(1, 128)
        updates += 1
    print(json.dumps({"updates_per_s": updates / (time.perf_counter() - start)}))


def parse_setting(text: str) -> tuple[str, dict[str, str]]:
    label, _, assignments = text.partition("=")
    variables = dict(item.split("=", 1) for item in assignments.split(",") if item)
    return label, variables


def run_processes(label: str, variables: dict[str, str], count: int, seconds: float) -> list[float]:
    env = {k: v for k, v in os.environ.items() if k not in PROCESS_VARIABLES}
    env.update(variables)
    start_at = time.time() + 10.0  # room for every worker to build its model first
    command = [sys.executable, __file__, "--worker", str(start_at), "--seconds", str(seconds)]
    if label == "torch-first":
        command.append("--torch-first")
    processes = [subprocess.Popen(command, env=env, stdout=subprocess.PIPE, text=True) for _ in range(count)]
    outputs = [process.communicate()[0] for process in processes]
    return [json.loads(output.strip().splitlines()[-1])["updates_per_s"] for output in outputs]


def measure(settings: list[str], rounds: int, seconds: float) -> dict:
    solo: dict[str, list[float]] = {s: [] for s in settings}
    pair: dict[str, list[float]] = {s: [] for s in settings}
    for _ in range(rounds):
        for setting in settings:
            label, variables = parse_setting(setting)
            solo[setting] += run_processes(label, variables, 1, seconds)
            pair[setting] += run_processes(label, variables, 2, seconds)
    results = {}
    for setting in settings:
        label, variables = parse_setting(setting)
        alone, shared = statistics.median(solo[setting]), statistics.median(pair[setting])
        results[label] = {
            "variables": variables,
            "alone_updates_per_s": round(alone, 2),
            "each_of_two_updates_per_s": round(shared, 2),
            "each_of_two_over_alone": round(shared / alone, 3),
            "all_alone": [round(v, 2) for v in solo[setting]],
            "all_each_of_two": [round(v, 2) for v in pair[setting]],
        }
    return results


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--setting", action="append", help="label=VAR=value,... (repeatable)")
    parser.add_argument("--rounds", type=int, default=4)
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--out", type=Path, help="also write the JSON report here")
    parser.add_argument("--worker", type=float, help=argparse.SUPPRESS)
    parser.add_argument("--torch-first", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker is not None:
        worker(args.worker, args.seconds, args.torch_first)
        return {}
    settings = args.setting or list(DEFAULT_SETTINGS)
    report = {"cpus": os.cpu_count(), "rounds": args.rounds, "seconds": args.seconds}
    report["settings"] = measure(settings, args.rounds, args.seconds)
    baseline = report["settings"].get("libgomp default")
    if baseline:
        for entry in report["settings"].values():
            entry["alone_over_libgomp_default"] = round(
                entry["alone_updates_per_s"] / baseline["alone_updates_per_s"], 3
            )
    text = json.dumps(report, indent=2)
    print(text)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text + "\n")
    return report


if __name__ == "__main__":
    main()
