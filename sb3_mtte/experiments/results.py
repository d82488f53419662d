"""Final results of a folder of runs: Table 1 (markdown) and one JSON record per evaluated run."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from sb3_mtte.experiments.runs import Run, label_order, success_curve
from sb3_mtte.experiments.variants import paper_table1, published_results


def final_success(run: Run) -> float | None:
    """Final mean success of a run: its ``success.json``, else its last evaluation, else its last success scalar."""
    if run.final is not None and "mean" in run.final:
        return float(run.final["mean"])
    curve = success_curve(run)
    if curve is None or not len(curve[1]):
        return None
    return float(curve[1][-1])


def results_records(runs: Sequence[Run]) -> list[dict[str, Any]]:
    """One record per run with a final evaluation (``success.json``): algo, label, benchmark, seed, env_steps and
    success ``{"mean": m, "per_task": {task: rate}}``, sorted by algorithm order and seed."""
    records = []
    for run in runs:
        if run.final is None or "per_task" not in run.final:
            continue
        records.append(
            {
                "algo": run.info.get("algo"),
                "label": run.label,
                "benchmark": run.benchmark,
                "seed": run.seed,
                "env_steps": run.final.get("timesteps"),
                "episodes_per_task": run.final.get("episodes_per_task"),
                "success": {"mean": run.final["mean"], "per_task": run.final["per_task"]},
            }
        )
    order = {label: i for i, label in enumerate(label_order([r["label"] for r in records]))}
    return sorted(records, key=lambda r: (order[r["label"]], r["seed"] if r["seed"] is not None else -1))


def table1(groups: dict[str, dict[str, list[Run]]], with_paper: bool = True) -> str:
    """Markdown Table 1: final success (%) mean +- std over seeds, per algorithm (rows) and benchmark (columns)."""
    benches = sorted(groups)
    labels = label_order(sorted({label for by_label in groups.values() for label in by_label}))
    lines = [
        "| Algorithm | " + " | ".join(benches) + " |",
        "|:--|" + "--:|" * len(benches),
    ]
    for label in labels:
        cells = []
        for bench in benches:
            values = [v for v in (final_success(r) for r in groups[bench].get(label, [])) if v is not None]
            if not values:
                cells.append("-")
            else:
                cells.append(f"{100 * np.mean(values):.1f} ± {100 * np.std(values):.1f}% (n={len(values)})")
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    text = (
        "Final success rate, mean ± std over seeds (n = number of seeds); a run's final success is its "
        "success.json (python -m sb3_mtte.evaluate) when present, else its last evaluation.\n\n" + "\n".join(lines)
    )
    shown = [b for b in ("MT10", "MT20") if any(b == bench.split("-")[0] for bench in benches)]
    if with_paper and shown:
        paper = ["| Algorithm | " + " | ".join(shown) + " |", "|:--|" + "--:|" * len(shown)]
        for label, values in paper_table1().items():
            paper.append(f"| {label} | " + " | ".join(f"{values[b]:.1f}%" for b in shown) + " |")
        text += "\n\nThe paper's Table 1 (Meta-World v2, 5 seeds), for reference:\n\n" + "\n".join(paper)
        published = ["| Algorithm | " + " | ".join(shown) + " | source |", "|:--|" + "--:|" * len(shown) + ":--|"]
        for label, (values, source) in published_results().items():
            cells = " | ".join(f"{values[b]:.1f}%" if b in values else "-" for b in shown)
            published.append(f"| {label} | {cells} | {source} |")
        if len(published) > 2:
            text += "\n\nPublished by the methods' authors, for reference:\n\n" + "\n".join(published)
    return text + "\n"
