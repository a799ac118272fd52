"""An epoch's metrics per seed, and the rows of numbers a run keeps of them (``COLUMNS`` wide)."""
from __future__ import annotations

import numpy as np

METRICS = ("batch_loss", "train_loss", "test_loss", "update_norm", "cosine")
COLUMNS = ("epoch", "seed") + METRICS + ("seconds",)


def empty_rows() -> np.ndarray:
    """No metric rows yet (``COLUMNS`` wide)."""
    return np.zeros((0, len(COLUMNS)))


def final_mean_std(rows: np.ndarray, column: str = "test_loss") -> tuple[float, float]:
    """Mean and standard deviation over seeds of ``column`` at the last epoch."""
    last = rows[rows[:, 0] == rows[:, 0].max()]
    values = last[:, COLUMNS.index(column)]
    return float(values.mean()), float(values.std()) if len(values) > 1 else 0.0


def epoch_rows(epoch: int, seeds: np.ndarray, metrics: dict, seconds: float) -> np.ndarray:
    columns = [np.full(len(seeds), epoch), seeds] + [np.asarray(metrics[m], dtype=np.float64) for m in METRICS]
    return np.stack(columns + [np.full(len(seeds), seconds)], axis=1)
