"""Learning curves as numbers: a run directory's metrics as (epoch, seed) tables, smoothed and banded over seeds.

    from stablebptt.reports.curves import aggregate, load_run, moving_average
    run = load_run("runs/repulsion-20261122-101500")
    mean, low, high = aggregate(moving_average(run.metrics["test_loss"], 30))

Nothing here draws (``stablebptt.reports.plots`` does) or imports matplotlib.
"""
from __future__ import annotations

import warnings
from pathlib import Path
from typing import NamedTuple

import numpy as np

from stablebptt.engine.metrics import env_steps_trained
from stablebptt.errors import InputError
from stablebptt.reports.choices import BANDS, X_AXES
from stablebptt.runs.run_folder import CONFIG_FILE, METRICS_FILE, STARTUP_FILE, run_metrics
from stablebptt.storage import read_json

PAPER_SMOOTH = 30  # the paper smooths its curves over 30 epochs
REQUIRED_COLUMNS = ("epoch", "seed", "test_loss", "update_norm")
LOSS = ("test loss", 1.0)
# Tasks whose test loss reads better as a score: the environment task's is the negative episode return.
SCORES = {"env": ("episode return", -1.0)}


class Run(NamedTuple):
    """One run directory, its metrics pivoted to (epoch, seed) tables.

    Attributes:
      path: the run directory.
      config: the parsed ``config.json``.
      epochs: sorted epoch numbers, shape (E,).
      seeds: sorted seeds, shape (N,).
      metrics: column name -> array (E, N); NaN where a value was not logged.
      note: what was read instead of a damaged ``metrics.csv`` (``runs.run_metrics``), else "".
    """

    path: Path
    config: dict
    epochs: np.ndarray
    seeds: np.ndarray
    metrics: dict
    note: str = ""

    @property
    def mode(self) -> str:
        return str(self.config.get("train", {}).get("mode", "?"))

    @property
    def clip(self) -> str:
        return str(self.config.get("train", {}).get("clip", "?"))


def load_run(run_dir: str | Path) -> Run:
    """Read one run directory.

    Args:
      run_dir: a directory written by ``scripts/train.py``.

    Returns:
      The ``Run``.

    Raises:
      InputError: the directory, its config or its metrics are missing or unreadable.
    """
    path = Path(run_dir)
    if not path.exists():
        raise InputError(f"{path} does not exist: give a run directory written by scripts/train.py")
    if not path.is_dir():
        raise InputError(f"{path} is not a directory: give a run directory written by scripts/train.py")
    metrics_path = path / METRICS_FILE
    config = read_json(path / CONFIG_FILE)
    if not (isinstance(config, dict) and all(isinstance(config.get(key, {}), dict) for key in ("train", "task_config"))):
        raise InputError(f"{path / CONFIG_FILE} is not a run configuration (expected 'train' and 'task_config' objects)")
    if (problem := _field_problem(config)) is not None:
        raise InputError(f"{path / CONFIG_FILE} is not a run configuration: {problem}")
    rows, note = run_metrics(path)
    missing = [column for column in REQUIRED_COLUMNS if column not in rows[0]]
    if missing:
        raise InputError(f"{metrics_path} lacks the column {missing[0]!r}: is it a metrics.csv of scripts/train.py?")
    return Run(path, config, *_pivot(rows, metrics_path), note)


# The fields a figure reads of a run's config.json (its labels, colours and line styles), with their types.
_DRAWN_FIELDS = (("task", str), ("train.mode", str), ("train.clip", str), ("train.lr", float),
                 ("train.clip_threshold", float), ("train.epochs", int), ("train.seeds", int))


def _field_problem(config: dict) -> str | None:
    """What is wrong with the fields a figure reads of ``config`` (absent ones are left out), or None."""
    for name, kind in _DRAWN_FIELDS:
        owner, _, key = name.rpartition(".")
        holder = config.get(owner, {}) if owner else config
        if key not in holder:
            continue
        value = holder[key]
        fits = isinstance(value, kind) and not isinstance(value, bool) or \
            (kind is float and isinstance(value, int) and not isinstance(value, bool))
        if not fits:
            return f"'{name}' is {value!r}, not a {'number' if kind in (int, float) else 'string'}"
    return None


def _pivot(rows: list[dict[str, float]], source: Path) -> tuple[np.ndarray, np.ndarray, dict]:
    """(epochs, seeds, column -> (E, N) table) from tidy rows; a repeated (epoch, seed) keeps its last row."""
    epoch_column = np.array([row["epoch"] for row in rows])
    seed_column = np.array([row["seed"] for row in rows])
    if not (np.all(np.isfinite(epoch_column)) and np.all(np.isfinite(seed_column))):
        raise InputError(f"{source} has a non-numeric epoch or seed")
    epochs, epoch_index = np.unique(epoch_column.astype(int), return_inverse=True)
    seeds, seed_index = np.unique(seed_column.astype(int), return_inverse=True)
    metrics = {}
    for column in rows[0]:
        if column in ("epoch", "seed"):
            continue
        table = np.full((len(epochs), len(seeds)), np.nan)
        table[epoch_index, seed_index] = [row[column] for row in rows]
        metrics[column] = table
    return epochs, seeds, metrics


def moving_average(values: np.ndarray, window: int) -> np.ndarray:
    """Centred moving average along axis 0 over ``window`` epochs, ignoring NaN and inf.

    Each point averages itself and ``window // 2`` epochs on either side. Near
    either end, where no centred window fits, a straight line is fitted to the
    ``2 * (window // 2) + 1`` epochs nearest the end and read off at the point:
    the ends are as smooth as the middle, and no trend lags or flattens there
    (inside, the centred mean is that same line fit). Constant and linear
    series pass unchanged. A window longer than the series fits one line to
    all of it; ``effective_window`` keeps short runs from that.

    Args:
      values: shape (E,) or (E, N); smoothed along the first axis.
      window: epochs to average over; 0 or 1 = no smoothing.

    Returns:
      An array of the shape of ``values``; NaN where a window has no finite value.

    Example:
      >>> moving_average(np.array([0., 3., 0., 3., 0., 3.]), 2)
      array([1., 1., 2., 1., 2., 2.])
    """
    values = np.asarray(values, dtype=float)
    if window < 0:
        raise InputError(f"the smoothing window must be zero or positive, got {window}")
    half, n = window // 2, values.shape[0]
    if half == 0 or n < 2:
        return values.copy()
    size = min(2 * half + 1, n)
    index = np.arange(n)
    low = np.clip(index - half, 0, n - size)  # centred where it fits, else flush with the nearer end
    high = low + size
    # A weighted least-squares line per window from running sums; weight 0 drops NaN and inf.
    x = (index / n).reshape((n,) + (1,) * (values.ndim - 1))  # scaled so that the sums stay well conditioned
    weight = np.isfinite(values).astype(float)
    y = np.where(weight > 0, values, 0.0)

    def window_sum(a: np.ndarray) -> np.ndarray:
        running = np.concatenate([np.zeros((1,) + a.shape[1:]), np.cumsum(a, axis=0)])
        return running[high] - running[low]

    s0, s1, s2 = window_sum(weight), window_sum(weight * x), window_sum(weight * x * x)
    t0, t1 = window_sum(y), window_sum(x * y)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_x, mean_y = s1 / s0, t0 / s0
        spread = s0 * s2 - s1 * s1  # s0^2 times the variance of x in the window
        # One finite point (or none) defines no slope: fall back to the mean. Two points 1/n apart give 0.25/n^2.
        sloped = spread > 0.01 * (s0 / n) ** 2
        slope = np.where(sloped, (s0 * t1 - s1 * t0) / np.where(sloped, spread, 1.0), 0.0)
        smoothed = mean_y + slope * (x - mean_x)
    return np.where(s0 > 0, smoothed, np.nan)


def effective_window(window: int, epochs: int) -> int:
    """The smoothing window for a run of ``epochs`` epochs: at most a third of the run.

    A window of 30 averages away the shape of a 40-epoch curve; capping it at a
    third keeps at least three windows per run, as ``default_smooth`` does.
    """
    return min(window, epochs // 3)


def aggregate(values: np.ndarray, band: str = "minmax") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean over seeds and the band around it, per epoch, ignoring NaN.

    Args:
      values: shape (E, N): epochs by seeds.
      band: ``"minmax"`` (the band spans every seed) or ``"std"`` (mean +- standard deviation).

    Returns:
      ``(mean, low, high)``, each of shape (E,); NaN at epochs with no value.
    """
    if band not in BANDS:
        raise InputError(f"unknown band {band!r}: choose one of {', '.join(BANDS)}")
    values = np.asarray(values, dtype=float)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN epochs give NaN, which is what we want
        mean = np.nanmean(values, axis=1)
        if band == "minmax":
            return mean, np.nanmin(values, axis=1), np.nanmax(values, axis=1)
        spread = np.nanstd(values, axis=1)
    return mean, mean - spread, mean + spread


def default_smooth(epochs: int) -> int:
    """The paper's 30-epoch smoothing for runs of at least 90 epochs; none for shorter runs."""
    return PAPER_SMOOTH if epochs >= 3 * PAPER_SMOOTH else 0


def score_of(run: Run) -> tuple[str, float]:
    """(name, sign) of what a run's test loss means: ``sign * test_loss`` is the named number."""
    return SCORES.get(str(run.config.get("task")), LOSS)


def x_values(run: Run, axis: str) -> tuple[np.ndarray, str]:
    """A run's epochs as ``axis`` (``X_AXES``) and the axis label.

    ``env-steps``: the steps each seed simulated in training (``steps_per_epoch`` of its config.json,
    which runs record since they train on carried episodes); ``seconds``: the training wall time,
    compiling excluded, summed over the epochs drawn; ``wall-clock``: the seconds from the command's start
    as ``--budget`` counts them, summed over its starts (a resumed run's set-ups and compiles too) and
    the epochs' evaluations.
    """
    if axis == "epoch":
        return run.epochs.astype(float), "epoch"
    if axis == "seconds":
        return np.cumsum(_epoch_seconds(run, "seconds")), "training wall time, s (compiling excluded)"
    if axis == "wall-clock":
        return wall_clock(run), "wall clock, s (set-up, compile and evaluations included)"
    if axis == "env-steps":
        steps = run.config.get("steps_per_epoch")
        if not isinstance(steps, int) or isinstance(steps, bool) or steps <= 0:
            raise InputError(f"{run.path / CONFIG_FILE} does not record its env steps per epoch (runs record them "
                             "since they train on carried episodes): draw it against epochs or seconds")
        # The rows' own count where they keep one: a budget's last epoch may have been cut short.
        counted = np.nanmax(run.metrics.get("env_steps", np.full((len(run.epochs), 1), np.nan)), axis=1, initial=-np.inf)
        return env_steps_trained(counted, run.epochs, steps), "env steps per seed"
    raise InputError(f"unknown x axis {axis!r}: choose one of {', '.join(X_AXES)}")


def wall_clock(run: Run) -> np.ndarray:
    """The seconds at each epoch's end since the run's first command started, as ``--budget`` counts them:
    every start's seconds to its first epoch (``startup.json``: the epoch each start trained first, or
    in records without it the epoch after the one its predecessor ended on), and each epoch's training
    and evaluation seconds."""
    path = run.path / STARTUP_FILE
    starts = read_json(path) if path.exists() else None
    if not (isinstance(starts, list) and starts and all(isinstance(start, dict) and "seconds_to_training" in start
                                                        for start in starts)):
        raise InputError(f"{run.path} has no record of its starts ({STARTUP_FILE}, written since runs time their "
                         "set-up): draw it against seconds or epochs")
    set_up, after = np.zeros(len(run.epochs)), 0  # after: the epoch the start before ended on
    for number, start in enumerate(starts):
        first = start.get("first_epoch")
        if first is None and after is None:
            raise InputError(f"{path} does not say where its start {number + 1} began (the one before it has no end "
                             "recorded): draw it against seconds or epochs")
        set_up[run.epochs >= (after + 1 if first is None else int(first))] += float(start["seconds_to_training"])
        after = start.get("ended", {}).get("epoch")
    return set_up + np.cumsum(_epoch_seconds(run, "seconds") + _epoch_seconds(run, "eval_seconds"))


def _epoch_seconds(run: Run, column: str) -> np.ndarray:
    """Each epoch's seconds of ``column`` (the same for every seed of one program; 0 where not logged)."""
    return np.nan_to_num(np.nanmax(run.metrics.get(column, np.full((len(run.epochs), 1), np.nan)), axis=1))
