"""Side by side with the JAX reference (rainx0r/metaworld-algorithms) on the same CPU, in its MT10 multi-head SAC
configuration: 3 x 400 networks, batch 128 per task, one update per vector step, 2 threads.

    python benchmarks/bench_peer.py --peer-python PATH/TO/venv/python --peer-script PATH/TO/peer_bench.py

(``--peer-python``: a virtual environment with the reference installed; ``--peer-script``: a script that times the
reference's jitted update and its training loop and prints them as JSON, as ``docs/performance.md`` describes.)

Each round runs the reference's own script (its jitted update on synthetic batches, then its training loop on real
MT10) and then this package the same way, each in a fresh process, so that drifts of the machine hit both alike;
the JSON printed at the end holds every round, the medians and the ratios (sb3-mtte over the reference).

The package's side (``--side package``): ``MTSAC("MultiHeadPolicy")`` with the shared critic (the reference's
critic is one multi-head network: the same FLOPs) and with per-task critics (the package's default kind).
(i) updates/s of ``model.train(1)`` (sampling included) on synthetic MT10-shaped replay data; (ii) env steps/s of
``learn()`` on real MT10 after ``--warmstart`` random vector steps and ``--warm`` vector steps with updates, timed
between the env.step calls that open and close a window of ``--timed`` vector steps, as the reference's script does.
The reference clips gradient norms at 1.0 (its Meta-World setting); SAC here does not.
"""

from __future__ import annotations

import argparse
import json
from importlib import metadata
import os
import platform
import statistics
import subprocess
import sys
import time

N_TASKS = 10
WIDTH, DEPTH = 400, 3
CRITICS = ("shared", "per_task")


def package_updates(repeats: int) -> dict[str, float]:
    """Updates/s of one ``model.train`` call per critic kind, timed round-robin."""
    from bench_updates import fill_buffer, interleaved_medians, quiet, synthetic_env

    from sb3_mtte import MTSAC

    updates = {}
    for critic in CRITICS:
        model = quiet(
            MTSAC(
                "MultiHeadPolicy",
                synthetic_env(N_TASKS),
                learning_starts=0,
                critic_arch=critic,
                policy_kwargs=dict(net_arch=[WIDTH] * DEPTH),
                device="cpu",
                seed=1,
            )
        )
        fill_buffer(model, 4 * model.batch_size)
        updates[critic] = lambda model=model: model.train(gradient_steps=1, batch_size=model.batch_size)
    medians = interleaved_medians(updates, repeats)
    return {critic: round(1 / seconds, 2) for critic, seconds in medians.items()}


def package_end_to_end(critic: str, warmstart: int, warm: int, timed: int) -> float:
    """Env steps/s of ``learn()`` on MT10 over ``timed`` vector steps after learning starts."""
    from stable_baselines3.common.vec_env import VecEnvWrapper

    from sb3_mtte import MTSAC, make_mt_env

    class StepTimes(VecEnvWrapper):
        """Records ``perf_counter()`` at every step call."""

        def __init__(self, venv) -> None:
            super().__init__(venv)
            self.times: list[float] = []

        def step_async(self, actions) -> None:
            self.times.append(time.perf_counter())
            self.venv.step_async(actions)

        def reset(self):
            return self.venv.reset()

        def step_wait(self):
            return self.venv.step_wait()

    env = StepTimes(make_mt_env("MT10", seed=1))
    model = MTSAC(
        "MultiHeadPolicy",
        env,
        learning_starts=warmstart * N_TASKS,
        critic_arch=critic,
        policy_kwargs=dict(net_arch=[WIDTH] * DEPTH),
        buffer_size=200_000,
        device="cpu",
        seed=1,
    )
    first = warmstart + 1 + warm
    last = first + timed
    model.learn((last + 1) * N_TASKS)
    return round(timed * N_TASKS / (env.times[last] - env.times[first]), 1)


def package_side(args: argparse.Namespace) -> dict:
    import sb3_mtte

    sb3_mtte.tune_process()  # before torch loads, as the package's commands do
    import torch as th

    th.set_num_threads(2)
    report = {"updates_per_s": package_updates(args.repeats)}
    report["env_steps_per_s"] = {
        critic: package_end_to_end(critic, args.warmstart, args.warm, args.timed) for critic in CRITICS
    }
    return report


def run_json(command: list[str]) -> dict:
    """Run a command and parse the JSON of its last ``RESULT`` line (or its whole output)."""
    out = subprocess.run(command, capture_output=True, text=True, env={**os.environ, "MUJOCO_GL": "egl"})
    if out.returncode != 0:
        raise RuntimeError(f"{' '.join(command)} failed:\n{out.stderr[-3000:]}")
    lines = [line for line in out.stdout.splitlines() if line.startswith("RESULT ")]
    return json.loads(lines[-1].removeprefix("RESULT ") if lines else out.stdout)


def timing_args(args: argparse.Namespace) -> list[str]:
    """The options that set what both sides time, as command-line arguments."""
    options = {"--repeats": args.repeats, "--warmstart": args.warmstart, "--warm": args.warm, "--timed": args.timed}
    return [text for option, value in options.items() for text in (option, str(value))]


def reference_round(args: argparse.Namespace) -> dict:
    peer = [args.peer_python, args.peer_script, "--what", "both", "--variants", "mtmhsac"]
    report = run_json([*peer, *timing_args(args)])
    return {
        "updates_per_s": report["updates"]["updates_per_s"]["peer-mtmhsac-train_iter"],
        "env_steps_per_s": report["e2e"]["env_steps_per_s"],
        "raw": report,
    }


def package_round(args: argparse.Namespace) -> dict:
    return run_json([sys.executable, __file__, "--side", "package", *timing_args(args)])


def summary(rounds: list[dict]) -> dict:
    ref_upd = statistics.median(r["reference"]["updates_per_s"] for r in rounds)
    ref_e2e = statistics.median(r["reference"]["env_steps_per_s"] for r in rounds)
    medians: dict[str, dict[str, float]] = {"reference": {"updates_per_s": ref_upd, "env_steps_per_s": ref_e2e}}
    for critic in CRITICS:
        upd = statistics.median(r["package"]["updates_per_s"][critic] for r in rounds)
        e2e = statistics.median(r["package"]["env_steps_per_s"][critic] for r in rounds)
        medians[f"sb3-mtte {critic} critic"] = {
            "updates_per_s": upd,
            "env_steps_per_s": e2e,
            "updates_ratio": round(upd / ref_upd, 3),
            "env_steps_ratio": round(e2e / ref_e2e, 3),
        }
    return medians


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--peer-python", help="the reference's venv python (setup.sh prints it)")
    parser.add_argument("--peer-script", help="peer_bench.py of the reference's snapshot")
    parser.add_argument("--side", choices=["both", "package"], default="both")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--warmstart", type=int, default=256, help="vector steps of random actions")
    parser.add_argument("--warm", type=int, default=25, help="vector steps with updates before the window")
    parser.add_argument("--timed", type=int, default=800, help="vector steps in the timed window")
    args = parser.parse_args(argv)
    if args.side == "package":
        print("RESULT " + json.dumps(package_side(args)))
        return
    if not (args.peer_python and args.peer_script):
        parser.error("--peer-python and --peer-script are required")
    rounds = []
    for index in range(args.rounds):
        rounds.append({"reference": reference_round(args), "package": package_round(args)})
        print(
            f"round {index + 1}: {json.dumps({k: {**v, 'raw': None} for k, v in rounds[-1].items()})}",
            file=sys.stderr,
            flush=True,
        )
    print(
        json.dumps(
            {
                "machine": {
                    "cpu_count": os.cpu_count(),
                    "platform": platform.platform(),
                    "python": platform.python_version(),
                },
                "versions": {name: metadata.version(name) for name in ("sb3-mtte", "torch", "stable-baselines3")},
                "time": time.strftime("%Y-%m-%d %H:%M:%S"),
                "settings": vars(args),
                "medians": summary(rounds),
                "rounds": rounds,
            },
            indent=1,
        )
    )


if __name__ == "__main__":
    main()
