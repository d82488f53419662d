"""Final results of a folder of runs: Table 1 (markdown) and one JSON record per evaluated run."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from sb3_mtte.experiments.runs import Run, label_order, success_curve
from sb3_mtte.experiments.variants import paper_sources, paper_table1


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


def _success_cell(values: list[float]) -> str:
    """'mean ± std% (n=...)' over seeds; one seed has no spread to show."""
    if not values:
        return "-"
    if len(values) == 1:
        return f"{100 * values[0]:.1f}% (n=1)"
    return f"{100 * np.mean(values):.1f} ± {100 * np.std(values):.1f}% (n={len(values)})"


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
            cells.append(_success_cell(values))
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    text = (
        "Final success rate, mean ± std over seeds (n = number of seeds; no std for one seed); a run's final "
        "success is its success.json (python -m sb3_mtte.evaluate) when present, else its last evaluation.\n\n"
        + "\n".join(lines)
    )
    shown = [b for b in ("MT10", "MT20") if any(b == bench.split("-")[0] for bench in benches)]
    if with_paper and shown:
        paper = ["| Algorithm | " + " | ".join(shown) + " |", "|:--|" + "--:|" * len(shown)]
        for label, values in paper_table1().items():
            cells = (f"{values[b]:.1f}%" if b in values else "-" for b in shown)
            paper.append(f"| {label} | " + " | ".join(cells) + " |")
        sources = "".join(f"\n- {label}: {source}." for label, source in paper_sources().items())
        text += "\n\nPublished success, for reference: the paper's Table 1 (Meta-World v2, 5 seeds)"
        text += (", except the rows of another source:" + sources) if sources else ":"
        text += "\n\n" + "\n".join(paper)
    return text + "\n"
