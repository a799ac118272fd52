"""An epoch's metrics per seed, and the rows of numbers a run keeps of them (``COLUMNS`` wide)."""
from __future__ import annotations

import numpy as np

METRICS = ("batch_loss", "train_loss", "test_loss", "update_norm", "cosine")
# seconds: the epoch's training time; eval_seconds: its evaluation's (0 where none ran); env_steps: each
# seed's env steps trained so far (NaN where a task has no steps to count).
COLUMNS = ("epoch", "seed") + METRICS + ("seconds", "eval_seconds", "env_steps")
# Rows recorded before the last two columns came: read as rows with no evaluation time and no step count.
FORMER_WIDTH = len(COLUMNS) - 2


def empty_rows() -> np.ndarray:
    """No metric rows yet (``COLUMNS`` wide)."""
    return np.zeros((0, len(COLUMNS)))


def widened(rows: np.ndarray) -> np.ndarray:
    """``rows`` as ``COLUMNS`` wide: rows of a former width get no evaluation time and no step count."""
    if rows.ndim != 2 or rows.shape[1] != FORMER_WIDTH:
        return rows
    return np.concatenate([rows, np.zeros((len(rows), 1)), np.full((len(rows), 1), np.nan)], axis=1)


def env_steps_trained(counted: float | np.ndarray, epochs: int | np.ndarray, steps_per_epoch: int) -> np.ndarray:
    """The env steps a seed trained by each of ``epochs``' ends: the rows' own count where they keep one (a
    budget's last epoch may be cut short), else that many whole epochs (rows from before the count)."""
    return np.where(np.isfinite(counted), counted, np.asarray(epochs, dtype=float) * steps_per_epoch)


def final_mean_std(rows: np.ndarray, column: str = "test_loss") -> tuple[float, float]:
    """Mean and standard deviation over seeds of ``column`` at the last epoch that has it (an epoch
    trained without an evaluation has no train or test loss)."""
    values = final_values(rows, column)
    return float(values.mean()), float(values.std()) if len(values) > 1 else 0.0


def final_values(rows: np.ndarray, column: str = "test_loss") -> np.ndarray:
    """``column``'s numbers at the last epoch that has any, one per seed scored there (a seed stopped
    apart has none); the last epoch's NaNs where no epoch has a number."""
    known = rows[np.isfinite(rows[:, COLUMNS.index(column)])]
    last = known if len(known) else rows
    return last[last[:, 0] == last[:, 0].max(), COLUMNS.index(column)]


def epoch_rows(epoch: int, seeds: np.ndarray, metrics: dict, seconds: float, eval_seconds: float = 0.0,
               env_steps: float = np.nan) -> np.ndarray:
    columns = [np.full(len(seeds), epoch), seeds] + [np.asarray(metrics[m], dtype=np.float64) for m in METRICS]
    return np.stack(columns + [np.full(len(seeds), value) for value in (seconds, eval_seconds, env_steps)], axis=1)
