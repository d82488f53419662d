"""Times every duration that the README and the zoo configs state, each with the command that it times.

Run it on a quiet machine (nothing else running); each part is a fresh process in a temporary folder, timed by
``/usr/bin/time`` (wall seconds, CPU seconds, peak resident memory):

- ``smoke``: the README's main job, MTSACTE on MT10-smoke, then ``evaluate --episodes 10``;
- ``toy``: toy-conflict at one torch thread;
- ``mt25``: MT25-smoke (time and memory);
- ``video``: ``record_video`` of the smoke model at 480 x 480 and 240 x 240, 20 and 60 frames per task's video;
  the CPU seconds per frame are the difference of the two, over the 400 frames between them;
- ``snippet``: the README's Python example (MTSACTE on MT10, class defaults, torch's default threads) over its
  first 20,000 env steps; its time to ``learning_starts`` and its rate after it give the estimate for 200,000.

The default suite's time is pytest's own summary line of ``python -m pytest`` (as ``.ci/run`` calls it).

``--progress RUN_DIR ... --since HH:MM`` instead reads the ``progress.csv`` of runs in progress (e.g. two MT10-100k
runs side by side): their env steps per second since that time, for measuring a long run's rate over an interval in
which nothing else ran.

    python benchmarks/time_claims.py --out docs/results/time_claims.json
    python benchmarks/time_claims.py --progress logs/mtsacte/MT10-100k_4 logs/mtsac_mt/MT10-100k_4 --since 09:00
"""

from __future__ import annotations

import argparse
import calendar
import csv
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
PY = sys.executable
ZOO = [PY, "-m", "sb3_mtte.zoo"]
SNIPPET_STEPS = 20_000
SNIPPET_BUDGET = 200_000
SNIPPET = f"""
from sb3_mtte import MTSACTE, make_mt_env
import json, sys, time
from stable_baselines3.common.callbacks import BaseCallback

class Clock(BaseCallback):
    def _on_training_start(self):
        self.start, self.marks = time.perf_counter(), []
    def _on_step(self):
        self.marks.append((self.num_timesteps, time.perf_counter() - self.start))
        return True

env = make_mt_env("MT10", seed=0)
model = MTSACTE("MlpPolicy", env, verbose=0, seed=0)
clock = Clock()
model.learn({SNIPPET_STEPS}, callback=clock)
json.dump({{"learning_starts": model.learning_starts, "marks": clock.marks}}, open(sys.argv[1], "w"))
"""


def timed(command: list[str], cwd: Path) -> dict[str, Any]:
    """Wall and CPU seconds and peak memory of one command (its children included)."""
    stats = cwd / "time.txt"
    subprocess.run(
        ["/usr/bin/time", "-f", "%e %U %S %M", "-o", str(stats), *command],
        cwd=cwd,
        check=True,
        stdout=subprocess.DEVNULL,
    )
    wall, user, system, rss_kb = stats.read_text().split()[-4:]
    return {
        "command": " ".join(command).replace(PY, "python"),
        "wall_s": round(float(wall), 1),
        "cpu_s": round(float(user) + float(system), 1),
        "max_rss_gb": round(int(rss_kb) / 2**20, 2),
    }


def part_smoke(tmp: Path) -> dict[str, Any]:
    train = timed(
        [*ZOO, "train", "--algo", "mtsacte", "--env", "MT10-smoke", "-f", "logs", "--seed", "0", "--exp-id", "1"], tmp
    )
    evaluate = timed(
        [
            PY,
            "-m",
            "sb3_mtte.evaluate",
            "logs/mtsacte/MT10-smoke_1/MT10-smoke.zip",
            "--episodes",
            "10",
            "--no-progress",
        ],
        tmp,
    )
    return {"train": train, "evaluate": evaluate, "total_wall_s": round(train["wall_s"] + evaluate["wall_s"], 1)}


def part_toy(tmp: Path) -> dict[str, Any]:
    return timed(
        [
            *ZOO,
            "train",
            "--algo",
            "mtsacte",
            "--env",
            "toy-conflict",
            "-f",
            "logs",
            "--seed",
            "0",
            "--num-threads",
            "1",
            "--no-progress",
        ],
        tmp,
    )


def part_mt25(tmp: Path) -> dict[str, Any]:
    return timed(
        [*ZOO, "train", "--algo", "mtsacte", "--env", "MT25-smoke", "-f", "logs", "--seed", "0", "--no-progress"], tmp
    )


def part_video(tmp: Path) -> dict[str, Any]:
    if not (tmp / "logs/mtsacte/MT10-smoke_1/MT10-smoke.zip").is_file():
        part_smoke(tmp)
    result = {}
    for size in (480, 240):
        runs = {
            frames: timed(
                [
                    *ZOO,
                    "record_video",
                    "--algo",
                    "mtsacte",
                    "--env",
                    "MT10-smoke",
                    "-f",
                    "logs",
                    "-o",
                    f"videos_{size}_{frames}",
                    "--episodes",
                    "1",
                    "-n",
                    str(frames),
                    "--width",
                    str(size),
                    "--height",
                    str(size),
                    "--exp-id",
                    "1",
                ],
                tmp,
            )
            for frames in (20, 60)
        }
        per_frame = {
            f"{kind}_per_frame": round((runs[60][kind] - runs[20][kind]) / (10 * 40), 3) for kind in ("wall_s", "cpu_s")
        }
        result[f"{size}x{size}"] = {"runs": runs, **per_frame}
    return result


def part_snippet(tmp: Path) -> dict[str, Any]:
    (tmp / "snippet.py").write_text(SNIPPET)
    run = timed([PY, "snippet.py", "marks.json"], tmp)
    data = json.loads((tmp / "marks.json").read_text())
    marks, starts = data["marks"], data["learning_starts"]
    at_starts = next(t for n, t in marks if n >= starts)
    last_n, last_t = marks[-1]
    seconds_per_step = (last_t - at_starts) / (last_n - starts)
    estimate = at_starts + (SNIPPET_BUDGET - starts) * seconds_per_step
    return {
        "run": run,
        "env_steps_timed": last_n,
        "seconds_to_learning_starts": round(at_starts, 1),
        "env_steps_per_s_after_learning_starts": round(1 / seconds_per_step, 1),
        f"estimated_minutes_for_{SNIPPET_BUDGET}": round(estimate / 60, 1),
    }


PARTS = {"smoke": part_smoke, "toy": part_toy, "mt25": part_mt25, "video": part_video, "snippet": part_snippet}


def progress_rate(run_dir: Path, since: float) -> dict[str, Any]:
    """Env steps per second of a run in progress over its ``progress.csv`` rows logged after ``since`` (epoch
    seconds) in its current learn call; a row's clock time is the file's modification time less the row's
    ``time/time_elapsed`` deficit to the last row."""
    with (run_dir / "progress.csv").open() as file:
        rows = [
            (float(r["time/total_timesteps"]), float(r["time/time_elapsed"]))
            for r in csv.DictReader(file)
            if r["time/time_elapsed"]
        ]
    last_steps, last_elapsed = rows[-1]
    wall_at = (run_dir / "progress.csv").stat().st_mtime - last_elapsed
    call_start = max((i for i in range(1, len(rows)) if rows[i][1] < rows[i - 1][1]), default=0)
    current = [row for row in rows[call_start:] if wall_at + row[1] >= since]
    if len(current) < 2:
        raise SystemExit(f"{run_dir}: fewer than two progress.csv rows since then; wait for more")
    steps, seconds = current[-1][0] - current[0][0], current[-1][1] - current[0][1]
    return {
        "from_steps": current[0][0],
        "to_steps": last_steps,
        "seconds": round(seconds, 1),
        "from": time.strftime("%H:%M:%S", time.gmtime(wall_at + current[0][1])),
        "to": time.strftime("%H:%M:%S", time.gmtime(wall_at + last_elapsed)),
        "env_steps_per_s": round(steps / seconds, 1),
    }


def machine() -> dict[str, Any]:
    model = next(
        (
            line.split(":", 1)[1].strip()
            for line in Path("/proc/cpuinfo").read_text().splitlines()
            if line.startswith("model name")
        ),
        platform.processor(),
    )
    commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=REPO, capture_output=True, text=True).stdout.strip()
    return {"cpu": model, "cores": os.cpu_count(), "commit": commit, "python": platform.python_version()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--parts", nargs="+", choices=list(PARTS), default=list(PARTS))
    parser.add_argument("--progress", type=Path, nargs="+", help="run folders in progress: print their rates")
    parser.add_argument("--since", help="with --progress: rows logged after this UTC time, HH:MM of today")
    parser.add_argument("--out", type=Path, help="write the JSON here (merged into the file's parts if it exists)")
    args = parser.parse_args()
    if args.progress:
        day = time.strftime("%Y-%m-%d", time.gmtime())
        since = calendar.timegm(time.strptime(f"{day} {args.since or '00:00'}", "%Y-%m-%d %H:%M"))
        print(json.dumps({str(d): progress_rate(d, since) for d in args.progress}, indent=1))
        return
    result = json.loads(args.out.read_text()) if args.out and args.out.is_file() else {"parts": {}}
    result["machine"] = machine()
    with tempfile.TemporaryDirectory() as folder:
        for name in args.parts:
            load_before = os.getloadavg()
            result["parts"][name] = {**PARTS[name](Path(folder)), "load_average_before": load_before}
            print(name, json.dumps(result["parts"][name]), flush=True)
            if args.out:
                args.out.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
