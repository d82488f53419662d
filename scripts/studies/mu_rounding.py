"""Whether float32 rounding decided mu in a saved MTSACTE: the old transfer matrix against the exact one.

For each checkpoint (a model with its replay buffer), draws ``--batches`` representation batches as the algorithm
does (top-K when the model uses it) and reports, per batch:

- the mean |Q| of the critics at the batch's stored actions;
- how many off-diagonal signs of the float32 matrix (the computation before commit 86e62b6) differ from the float64
  one;
- mu from each.

``--shifts C ...`` repeats each batch with every critic output moved by C, which leaves the exact matrix unchanged:
it shows what the float32 computation would count at larger Q.

The rule of the study (``docs/results.md``, "mu in float64"): a checkpoint counts when the two mu differ for at
least 2 tasks in more than half of its batches; the rule holds when 2 or more checkpoints count.
Prints one JSON object; ``--out`` also writes it, ``--markdown`` writes the table of ``docs/nt_measure.md``.

    python scripts/studies/mu_rounding.py RUN/rl_model_200000_steps.zip RUN/rl_model_replay_buffer_200000_steps.pkl \
        ... --batches 10 --out docs/results/mu_rounding_seed3.json --markdown docs/results/mu_rounding_seed3.md
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import torch as th

from sb3_mtte import MTSACTE, __version__
from sb3_mtte.mtsacte.objectives import negative_transfer_measure
from sb3_mtte.mtsacte.transfer import RepresentationBatch, TaskObjectives, transfer_matrix

MIN_TASKS_DIFFERING = 2
MIN_CHECKPOINTS = 2


def batch_report(model: MTSACTE, batch_size: int, shifts: list[float]) -> dict[str, Any]:
    """The reports of one batch drawn as the algorithm draws it: the model as saved, then with every critic output
    moved by each shift."""
    buffer = model.replay_buffer
    data = buffer.sample_top_k(batch_size) if model.use_topk else buffer.sample(batch_size)  # type: ignore[union-attr]
    batch = RepresentationBatch.draw(data.observations, model.policy.z_dim, model.policy.action_dim)
    report = one_batch_report(model, data, batch)
    bias = model.policy.critic.q_net.layers[-1].bias
    for shift in shifts:
        with th.no_grad():
            bias.add_(shift)
        report.setdefault("shifted", {})[str(shift)] = one_batch_report(model, data, batch)
        with th.no_grad():
            bias.sub_(shift)
    return report


def one_batch_report(model: MTSACTE, data, batch: RepresentationBatch) -> dict[str, Any]:
    """The mean |Q|, the sign differences and both mu on one batch."""
    with th.no_grad():
        mean_abs_q = float(model.policy.critic(data.observations, data.actions).abs().mean())
        objectives = TaskObjectives(model.policy, batch, model.entropy_coefficients, chunk_size=1)
        z = objectives.embedding(objectives.phi()[0])[0]
        matrices = {
            name: transfer_matrix(objectives, z, model.nt_step_size, model.nt_estimator, dtype=dtype)
            for name, dtype in (("old", th.float32), ("exact", th.float64))
        }
    off_diagonal = ~th.eye(model.n_tasks, dtype=th.bool)
    differ = (matrices["old"] < 0) != (matrices["exact"] < 0)
    mu = {name: negative_transfer_measure(matrix).tolist() for name, matrix in matrices.items()}
    return {
        "mean_abs_q": mean_abs_q,
        "median_abs_off_diagonal": float(matrices["exact"][off_diagonal].abs().median()),
        "off_diagonal_signs_differing": int(differ[off_diagonal].sum()),
        "mu_old": mu["old"],
        "mu_exact": mu["exact"],
        "tasks_with_mu_differing": sum(a != b for a, b in zip(mu["old"], mu["exact"], strict=True)),
    }


def checkpoint_report(
    model_path: Path, buffer_path: Path, batches: int, batch_size: int, seed: int, shifts: list[float]
) -> dict:
    model = MTSACTE.load(model_path, device="cpu")
    model.load_replay_buffer(buffer_path)
    th.manual_seed(seed)
    rows = [batch_report(model, batch_size, shifts) for _ in range(batches)]
    differing = sum(row["tasks_with_mu_differing"] >= MIN_TASKS_DIFFERING for row in rows)
    return {
        "model": str(model_path),
        "timesteps": model.num_timesteps,
        "batches": rows,
        "batches_with_mu_differing": differing,
        "counts": differing > batches / 2,
    }


def markdown(reports: list[dict]) -> str:
    lines = [
        "| env steps | mean \\|Q\\| | median \\|off-diagonal T\\| | signs differing, per batch "
        "| batches with mu differing for 2+ tasks | counts |",
        "|--:|--:|--:|---|--:|---|",
    ]
    for report in reports:
        rows = report["batches"]
        mean_q = sum(row["mean_abs_q"] for row in rows) / len(rows)
        median_t = sorted(row["median_abs_off_diagonal"] for row in rows)[len(rows) // 2]
        signs = ", ".join(str(row["off_diagonal_signs_differing"]) for row in rows)
        lines.append(
            f"| {report['timesteps']:,} | {mean_q:.1f} | {median_t:.1e} | {signs} | "
            f"{report['batches_with_mu_differing']} of {len(rows)} | {'yes' if report['counts'] else 'no'} |"
        )
    shifts = list(reports[0]["batches"][0].get("shifted", {})) if reports else []
    if shifts:
        lines += [
            "",
            "| env steps | critic outputs moved by | mean \\|Q\\| | signs differing, per batch | batches with mu "
            "differing for 2+ tasks |",
            "|--:|--:|--:|---|--:|",
        ]
        for report in reports:
            for shift in shifts:
                rows = [row["shifted"][shift] for row in report["batches"]]
                mean_q = sum(row["mean_abs_q"] for row in rows) / len(rows)
                signs = ", ".join(str(row["off_diagonal_signs_differing"]) for row in rows)
                differing = sum(row["tasks_with_mu_differing"] >= MIN_TASKS_DIFFERING for row in rows)
                cells = [f"{report['timesteps']:,}", f"{float(shift):.0e}", f"{mean_q:.1f}", signs]
                lines.append(f"| {' | '.join(cells)} | {differing} of {len(rows)} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("paths", nargs="+", type=Path, help="pairs: model.zip replay_buffer.pkl, one per checkpoint")
    parser.add_argument("--batches", type=int, default=10)
    parser.add_argument("--batch-size", type=int, default=128, help="L, per task")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--shifts", type=float, nargs="*", default=[], metavar="C", help="critic outputs moved by C")
    parser.add_argument("--out", type=Path)
    parser.add_argument("--markdown", type=Path)
    args = parser.parse_args(argv)
    if len(args.paths) % 2:
        parser.error("give the checkpoints as pairs: model.zip replay_buffer.pkl")
    if args.batches < 1 or args.batch_size < 1:
        parser.error("--batches and --batch-size must be at least 1")
    pairs = list(zip(args.paths[::2], args.paths[1::2], strict=True))
    reports = [
        checkpoint_report(model, buffer, args.batches, args.batch_size, args.seed, args.shifts)
        for model, buffer in pairs
    ]
    counting = sum(report["counts"] for report in reports)
    result = {
        "sb3_mtte": __version__,
        "torch": th.__version__,
        "checkpoints": reports,
        "checkpoints_counting": counting,
        "rule_holds": counting >= MIN_CHECKPOINTS,
    }
    text = json.dumps(result, indent=2)
    print(text)
    if args.out:
        args.out.write_text(text + "\n")
    if args.markdown:
        args.markdown.write_text(markdown(reports))
    return result


if __name__ == "__main__":
    main()
