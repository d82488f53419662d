"""The negative-transfer log of MTSACTE: one JSON line per iteration (its final mu, C_s, w and transfer matrix)."""

from __future__ import annotations

import json
import os

from stable_baselines3.common.callbacks import BaseCallback

NT_LOG_FILE = "negative_transfer.jsonl"


class NegativeTransferLogCallback(BaseCallback):
    """Append the records that MTSACTE queues in ``negative_transfer_records`` to ``negative_transfer.jsonl``.

    The file lives in the logger's folder (``logger.get_dir()``); without one, the records are dropped. Each record
    holds ``timesteps``, ``mu``, ``selected``, ``weights``, ``transfer_matrix``, ``transfer_matrix_dtype`` (the
    precision mu was counted in: ``"float64"``; a record without it counted in float32), ``task_probe_accuracy``,
    ``task_probe_accuracy_of_mean`` and ``z_std``. MTSACTE attaches this callback in ``learn`` by itself.
    Records are written at every event of the training loop, so they reach the file before the next checkpoint.
    """

    def _on_training_start(self) -> None:
        self._write_records()

    def _on_rollout_start(self) -> None:
        self._write_records()

    def _on_step(self) -> bool:
        self._write_records()
        return True

    def _on_training_end(self) -> None:
        self._write_records()

    def _write_records(self) -> None:
        records = self.model.negative_transfer_records  # type: ignore[attr-defined]
        if not records:
            return
        log_dir = self.logger.get_dir()
        if log_dir:
            with open(os.path.join(log_dir, NT_LOG_FILE), "a") as file:
                file.writelines(json.dumps(record) + "\n" for record in records)
        records.clear()
