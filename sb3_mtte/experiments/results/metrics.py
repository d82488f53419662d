"""Measures of MTSACTE's negative-transfer weighting, from its logs: the weights' distance from uniform, and two
readings of the transfer matrix.

The transfer matrix T of Eq. 6 has entry [k, i] = J_i(theta^k) - J_i(theta). It is the change of task i's objective
after a virtual step on task k. Each function takes a stack of weight rows or of matrices, and gives one value each.
"""

from __future__ import annotations

import numpy as np


def distance_from_uniform(weights: np.ndarray) -> np.ndarray:
    """Total variation distance of each row of ``weights`` ``(..., tasks)`` from uniform weights: half the sum of
    ``|w_i - 1/N|``."""
    weights = np.asarray(weights, dtype=float)
    return 0.5 * np.abs(weights - 1.0 / weights.shape[-1]).sum(axis=-1)


def _off_diagonal(matrices: np.ndarray) -> np.ndarray:
    """``(..., N, N)`` -> ``(..., N * (N - 1))``: the off-diagonal entries of each matrix."""
    n = matrices.shape[-1]
    return matrices[..., ~np.eye(n, dtype=bool)]


def harmful_fraction(matrices: np.ndarray) -> np.ndarray:
    """Per transfer matrix ``(..., N, N)`` (entry [k, i] = J_i(theta^k) - J_i(theta)): the share of its off-diagonal
    entries below zero, the pairs Eq. 6 counts as harmful."""
    return (_off_diagonal(np.asarray(matrices, dtype=float)) < 0).mean(axis=-1)


def transfer_coupling(matrices: np.ndarray) -> np.ndarray:
    """Per transfer matrix ``(..., N, N)``: mean |T[k, i]| over k != i divided by mean |T[k, k]| (0: a virtual step on
    one task leaves the other tasks' objectives where they were)."""
    matrices = np.asarray(matrices, dtype=float)
    diagonal = np.abs(np.diagonal(matrices, axis1=-2, axis2=-1)).mean(axis=-1)
    return np.abs(_off_diagonal(matrices)).mean(axis=-1) / diagonal


__all__ = ["distance_from_uniform", "harmful_fraction", "transfer_coupling"]
