"""The NumPy form of the correlative search's compiled scores (lrfslam/algo/correlative_kernel.py):
the oracle its tests hold it to."""

from __future__ import annotations

import numpy as np


def scores(grid_level: np.ndarray, rows: np.ndarray, cols: np.ndarray, cand: np.ndarray) -> np.ndarray:
    """Mean of ``grid_level`` (H, W) over each candidate's (K, 3) points, cells (A, N) clipped into the grid."""
    height, width = grid_level.shape
    r = np.clip(rows[cand[:, 0]] + cand[:, 2:3], 0, height - 1)
    q = np.clip(cols[cand[:, 0]] + cand[:, 1:2], 0, width - 1)
    return grid_level.ravel().take(r * width + q).mean(axis=1, dtype=np.float64)
