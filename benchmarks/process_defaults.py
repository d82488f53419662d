"""Env steps/s of a short training run with and without each setting of :func:`sb3_mtte.tune_process`.

The figures choose the defaults of ``tune_process``: the OpenMP spin count and glibc's malloc thresholds. Each run is
a fresh interpreter with no OpenMP or malloc variable of its own. It applies the settings of its combination, builds
MTSAC on the benchmark, trains ``--warm-steps`` env steps, then times ``--timed-steps`` more. Two scenarios:

========  =========================================================================================
scenario  what runs
========  =========================================================================================
lone      one run at torch's default number of threads
pair      two runs started together, each at torch's default threads, sharing the machine's cores
========  =========================================================================================

Each round runs every scenario and every combination once, in an order that rotates from round to round, so that a
drift of the machine hits them alike. The report holds medians, every raw figure, the machine, the versions and the
command::

    python benchmarks/process_defaults.py --out docs/results/process_defaults.json
    python benchmarks/process_defaults.py --repeats 1 --benchmark toy-conflict --warm-steps 200 --timed-steps 200
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

SCENARIOS = {"lone": 1, "pair": 2}
"""Scenario -> how many runs start together."""
COMBINATIONS = {
    f"spin {'on' if spin else 'off'}, malloc {'on' if malloc else 'off'}": (spin, malloc)
    for spin, malloc in itertools.product((False, True), repeat=2)
}
"""Label -> (spin count set, malloc thresholds raised); ``spin off, malloc off`` is libgomp's and glibc's own."""
BASELINE = "spin off, malloc off"
USER_VARIABLES = (
    "OMP_NUM_THREADS",
    "OMP_WAIT_POLICY",
    "GOMP_SPINCOUNT",
    "MKL_NUM_THREADS",
    "SB3_MTTE_MALLOC",
    "MALLOC_MMAP_THRESHOLD_",
    "MALLOC_TRIM_THRESHOLD_",
    "MALLOC_TOP_PAD_",
    "MALLOC_MMAP_MAX_",
    "GLIBC_TUNABLES",
)
"""Variables a run must not inherit: the combination alone decides its settings."""
PACKAGES = ("sb3-mtte", "torch", "stable-baselines3", "gymnasium", "metaworld", "mujoco", "numpy")


# ------------------------------------------------------------------------------------------------------------ a run
def run_once(args: argparse.Namespace) -> dict:
    """One training run in this fresh interpreter: settings first, then torch; env steps/s of the timed part."""
    import sb3_mtte

    tuning = sb3_mtte.tune_process(spin_count=args.spin, malloc_thresholds=args.malloc)
    import torch as th

    from sb3_mtte import MTSAC, make_mt_env

    env = make_mt_env(args.benchmark, seed=args.seed)
    model = MTSAC("MlpPolicy", env, learning_starts=args.warm_steps // 2, device="cpu", seed=args.seed)
    model.learn(args.warm_steps)
    wait_for_peers(args.barrier, args.peers)
    start = time.perf_counter()
    model.learn(args.timed_steps, reset_num_timesteps=False)
    seconds = time.perf_counter() - start
    return {
        "env_steps_per_s": round(args.timed_steps / seconds, 2),
        "seconds": round(seconds, 2),
        "applied": tuning._asdict(),
        "torch_threads": th.get_num_threads(),
        "torch_parallel": [line for line in th.__config__.parallel_info().splitlines() if line.strip()][:6],
    }


def wait_for_peers(barrier: str | None, peers: int) -> None:
    """Mark this run ready in the folder ``barrier``, then wait until ``peers`` runs are (so timing starts together)."""
    if barrier is None:
        return
    folder = Path(barrier)
    (folder / f"ready-{os.getpid()}").touch()
    while len(list(folder.glob("ready-*"))) < peers:
        time.sleep(0.01)


def start_runs(args: argparse.Namespace, scenario: str, combination: str) -> list[dict]:
    """Start the runs of ``scenario`` together with the settings of ``combination``; their reports."""
    spin, malloc = COMBINATIONS[combination]
    env = {k: v for k, v in os.environ.items() if k not in USER_VARIABLES}
    peers = SCENARIOS[scenario]
    with tempfile.TemporaryDirectory() as barrier:
        command = [sys.executable, __file__, "--run", "--barrier", barrier, "--peers", str(peers)]
        command += [*workload_arguments(args), *(["--spin"] if spin else []), *(["--malloc"] if malloc else [])]
        runs = [subprocess.Popen(command, env=env, stdout=subprocess.PIPE, text=True) for _ in range(peers)]
        outputs = [run.communicate()[0] for run in runs]
    if any(run.returncode for run in runs):
        raise RuntimeError(f"a run of {scenario}, {combination} failed: {' '.join(command)}")
    reports = [json.loads(output.strip().splitlines()[-1]) for output in outputs]
    if any(r["applied"] != {"spin_count": spin, "malloc_thresholds": malloc} for r in reports):
        raise RuntimeError(f"{combination}: the runs applied {[r['applied'] for r in reports]}")
    return reports


def workload_arguments(args: argparse.Namespace) -> list[str]:
    options = {"--benchmark": args.benchmark, "--warm-steps": args.warm_steps, "--timed-steps": args.timed_steps}
    options["--seed"] = args.seed
    return [text for option, value in options.items() for text in (option, str(value))]


# ------------------------------------------------------------------------------------------------------ the rounds
def measure(args: argparse.Namespace) -> dict[str, dict[str, list[dict]]]:
    """Scenario -> combination -> the reports of its runs, over ``args.repeats`` rounds in rotating order."""
    cells = [(scenario, combination) for scenario in SCENARIOS for combination in COMBINATIONS]
    runs: dict[str, dict[str, list[dict]]] = {s: {c: [] for c in COMBINATIONS} for s in SCENARIOS}
    for round_index in range(args.repeats):
        shift = round_index % len(cells)
        for scenario, combination in cells[shift:] + cells[:shift]:
            reports = start_runs(args, scenario, combination)
            for report in reports:
                report["round"] = round_index
            runs[scenario][combination] += reports
            rates = ", ".join(str(r["env_steps_per_s"]) for r in reports)
            print(f"round {round_index + 1}/{args.repeats}  {scenario:4}  {combination}: {rates} env steps/s")
    return runs


def summary(runs: dict[str, dict[str, list[dict]]]) -> dict:
    """Per scenario and combination: the median env steps/s of one run, its ratio to the baseline, every figure."""
    table = {}
    for scenario, by_combination in runs.items():
        medians = {c: statistics.median(r["env_steps_per_s"] for r in reports) for c, reports in by_combination.items()}
        table[scenario] = {
            combination: {
                "median_env_steps_per_s_per_run": round(medians[combination], 2),
                "over_baseline": round(medians[combination] / medians[BASELINE], 3),
                "median_env_steps_per_s_of_the_runs_together": round(statistics.median(round_totals(reports)), 2),
                "all_env_steps_per_s": [r["env_steps_per_s"] for r in reports],
                "runs": reports,
            }
            for combination, reports in by_combination.items()
        }
    return table


def round_totals(reports: list[dict]) -> list[float]:
    """The env steps/s of the runs of each round added up (what the machine trained, all its runs together)."""
    totals: dict[int, float] = {}
    for report in reports:
        totals[report["round"]] = totals.get(report["round"], 0.0) + report["env_steps_per_s"]
    return list(totals.values())


def cpu_model() -> str:
    cpuinfo = Path("/proc/cpuinfo")
    lines = cpuinfo.read_text().splitlines() if cpuinfo.exists() else []
    names = [line.split(":", 1)[1].strip() for line in lines if line.startswith("model name")]
    return names[0] if names else platform.processor()


def machine() -> dict:
    """What the figures were measured on."""
    return {
        "cpu": cpu_model(),
        "cpus": os.cpu_count(),
        "cpus_usable": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        "load_average_at_start": [round(v, 2) for v in os.getloadavg()] if hasattr(os, "getloadavg") else None,
        "platform": platform.platform(),
        "libc": " ".join(platform.libc_ver()),
        "python": platform.python_version(),
    }


def versions() -> dict[str, str | None]:
    found = {}
    for name in PACKAGES:
        try:
            found[name] = version(name)
        except PackageNotFoundError:
            found[name] = None
    return found


def report(args: argparse.Namespace, argv: list[str]) -> dict:
    from sb3_mtte import process

    started = time.time()
    header = {
        "command": " ".join(["python", "benchmarks/process_defaults.py", *argv]),
        "machine": machine(),
        "versions": versions(),
        "workload": {
            "algorithm": "MTSAC, its defaults (2 x 400, batch 128 per task), device cpu",
            "benchmark": args.benchmark,
            "warm_env_steps": args.warm_steps,
            "learning_starts": args.warm_steps // 2,
            "timed_env_steps": args.timed_steps,
            "seed": args.seed,
        },
        "settings": {
            "spin": f"GOMP_SPINCOUNT={process.SPIN_COUNT} (off: libgomp's default, 300,000)",
            "malloc": f"mmap threshold {process.MMAP_THRESHOLD}, trim threshold {process.TRIM_THRESHOLD} "
            "(off: glibc's own, dynamic)",
        },
        "scenarios": {"lone": "one run at torch's default threads", "pair": "two runs started together"},
        "repeats": args.repeats,
        "baseline": BASELINE,
    }
    runs = measure(args)
    parallel = [report.pop("torch_parallel") for cells in runs.values() for rs in cells.values() for report in rs]
    results = summary(runs)
    return {
        **header,
        "torch_parallel": parallel[0],
        "wall_seconds": round(time.time() - started, 1),
        "results": results,
    }


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=5, help="rounds over every scenario and combination")
    parser.add_argument("--benchmark", default="MT10", help="benchmark of make_mt_env (default MT10)")
    parser.add_argument("--warm-steps", type=int, default=600, help="env steps before timing (default 600)")
    parser.add_argument("--timed-steps", type=int, default=1500, help="env steps timed (default 1500)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, help="also write the JSON report here")
    parser.add_argument("--run", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--spin", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--malloc", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--barrier", help=argparse.SUPPRESS)
    parser.add_argument("--peers", type=int, default=1, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.repeats < 1 or args.warm_steps < 2 or args.timed_steps < 1:
        parser.error("--repeats and --timed-steps must be at least 1, --warm-steps at least 2.")
    return args


def main(argv: list[str] | None = None) -> dict:
    argv = sys.argv[1:] if argv is None else argv
    args = parse_args(argv)
    if args.run:
        result = run_once(args)
        print(json.dumps(result))
        return result
    result = report(args, argv)
    text = json.dumps(result, indent=2)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text + "\n")
    medians = {
        s: {c: v["median_env_steps_per_s_per_run"] for c, v in cells.items()} for s, cells in result["results"].items()
    }
    print(json.dumps({"median env steps/s of one run": medians}, indent=2))
    return result


if __name__ == "__main__":
    main()
