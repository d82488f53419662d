"""Figure of the DEV6 embedding study: the probe of sampled z and E_phi's std over env steps per task.

    python scripts/studies/plot_embedding_study.py docs/results/embedding_study_DEV6.json \
        --out docs/figures/embedding_study_DEV6.png
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

SHOWN = (
    "former_defaults",
    "z_init_std_0.1",
    "c_vae_1e-3",
    "init_0.1_c_vae_0",
    "init_0.1_c_vae_1e-4",
    "init_0.01_c_vae_1e-4",
    "mean_gain_50",
)
LABELS = {
    "init_0.01_c_vae_1e-4": " (previous defaults)",
    "mean_gain_50": " (Meta-World setting now: std 0.01, c_vae 1e-4)",
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("results", type=Path)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    data = json.loads(args.results.read_text())
    n_tasks = 6
    fig, (ax_probe, ax_std) = plt.subplots(1, 2, figsize=(11, 4))
    colors = plt.cm.tab10.colors
    for index, setting in enumerate(SHOWN):
        runs = [r for r in data["runs"] if r["setting"] == setting and r["seed"] == 0]
        run = max(runs, key=lambda r: r["per_task_steps"])  # the longest run of the setting
        steps = [p[0] / n_tasks / 1000 for p in run["probe"]]
        label = setting.replace("_", " ") + LABELS.get(setting, "")
        ax_probe.plot(steps, [p[1] for p in run["probe"]], color=colors[index], label=label)
        ax_std.plot(steps, [p[3] for p in run["probe"]], color=colors[index], label=label)
    ax_probe.axhline(1 / n_tasks, color="grey", linestyle=":", label="chance")
    ax_probe.set(xlabel="env steps per task (thousands)", ylabel="probe of the task from sampled z", ylim=(0, 1.02))
    ax_std.set(xlabel="env steps per task (thousands)", ylabel="E_phi's standard deviation (mean)", yscale="log")
    ax_probe.legend(fontsize=7, loc="center right")
    fig.suptitle("DEV6, seed 0: does z carry the task? (one run per setting)")
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110)
    print(args.out)


if __name__ == "__main__":
    main()
