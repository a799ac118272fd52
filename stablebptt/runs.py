"""Run directories: config, metrics, parameters and checkpoints, each written atomically.

A run directory holds ``config.json``, ``metrics.csv`` (one row per epoch and
seed), ``params.npz`` (final or latest parameters, leading axis = seed) and
``checkpoint.npz`` (parameters, optimizer state and all metrics so far), and
for an MJCF task ``model.xml``, a copy of the model file. The
checkpoint is the source of truth: resuming reads it and rewrites the rest.
"""
from __future__ import annotations

import contextlib
import csv
import io
import json
import os
import signal
import time
from datetime import datetime
from pathlib import Path
from typing import Any, Callable, NamedTuple

import jax
import numpy as np

from stablebptt.errors import InputError
from stablebptt.training import METRICS, TrainConfig, Trainer, TrainState, nonfinite_names

CONFIG_FILE = "config.json"
METRICS_FILE = "metrics.csv"
PARAMS_FILE = "params.npz"
CHECKPOINT_FILE = "checkpoint.npz"
MODEL_COPY_FILE = "model.xml"  # a copy of the MJCF file a run trained on
COLUMNS = ("epoch", "seed") + METRICS + ("seconds",)


def atomic_write(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` so that readers see the old or the new file, never half of one."""
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(temporary, "wb") as handle:
        handle.write(data)
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(temporary, path)


def write_json(path: Path, payload: Any) -> None:
    atomic_write(path, (json.dumps(payload, indent=2, sort_keys=True) + "\n").encode())


def read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(f"{path} does not exist: is this a run directory?") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise InputError(f"{path} is not valid JSON ({error})") from None


def write_metrics(path: Path, rows: np.ndarray) -> None:
    """A tidy CSV: one row per epoch and seed; floats in full precision."""
    text = io.StringIO()
    writer = csv.writer(text, lineterminator="\n")
    writer.writerow(COLUMNS)
    for row in rows:
        writer.writerow([int(row[0]), int(row[1])] + [repr(float(v)) for v in row[2:]])
    atomic_write(path, text.getvalue().encode())


def read_metrics(path: Path) -> list[dict[str, float]]:
    with open(path, newline="") as handle:
        return [{key: float(value) for key, value in row.items()} for row in csv.DictReader(handle)]


def _npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    return buffer.getvalue()


def save_params(path: Path, params: Any) -> None:
    leaves = jax.tree.leaves(jax.device_get(params))
    atomic_write(path, _npz_bytes({f"leaf_{i:03d}": leaf for i, leaf in enumerate(leaves)}))


def load_params(path: Path, template: Any) -> Any:
    """Parameters saved by ``save_params``, in the structure of ``template``."""
    with np.load(path) as data:
        leaves = [data[f"leaf_{i:03d}"] for i in range(len(data.files))]
    return _unflatten_like(template, leaves, path)


def _unflatten_like(template: Any, leaves: list[np.ndarray], path: Path) -> Any:
    template_leaves, treedef = jax.tree.flatten(template)
    if len(leaves) != len(template_leaves) or any(a.shape != np.shape(b) for a, b in zip(leaves, template_leaves)):
        raise InputError(f"{path} does not match this run's configuration (different network or seeds)")
    return jax.tree.unflatten(treedef, [np.asarray(a, dtype=np.asarray(b).dtype) for a, b in zip(leaves, template_leaves)])


def save_checkpoint(run_dir: Path, epoch: int, state: TrainState, rows: np.ndarray) -> None:
    leaves = jax.tree.leaves(jax.device_get(state))
    arrays = {f"leaf_{i:03d}": leaf for i, leaf in enumerate(leaves)}
    atomic_write(run_dir / CHECKPOINT_FILE, _npz_bytes({"epoch": np.array(epoch), "metrics": rows, **arrays}))


def load_checkpoint(run_dir: Path, template: TrainState) -> tuple[int, TrainState, np.ndarray]:
    path = run_dir / CHECKPOINT_FILE
    try:
        with np.load(path) as data:
            epoch = int(data["epoch"])
            rows = np.array(data["metrics"])
            leaves = [data[f"leaf_{i:03d}"] for i in range(len(data.files) - 2)]
    except FileNotFoundError:
        raise InputError(f"{path} does not exist: the run never finished an epoch; start it again") from None
    return epoch, _unflatten_like(template, leaves, path), rows


def default_run_dir(root: Path, task_name: str) -> Path:
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    candidate, suffix = root / f"{task_name}-{stamp}", 1
    while candidate.exists():
        suffix += 1
        candidate = root / f"{task_name}-{stamp}-{suffix}"
    return candidate


def check_same_task(run_dir: Path, resolved: dict) -> None:
    """Refuse to resume a run whose model file changed since it started (it would train another task)."""
    saved = read_json(run_dir / CONFIG_FILE).get("resolved_task", {})
    if "model_sha256" in saved and saved["model_sha256"] != resolved.get("model_sha256"):
        raise InputError(f"{resolved.get('model_file', 'the model file')} changed since {run_dir} started: "
                         "restore it, or start a new run")


def claim_run_dir(path: Path) -> Path:
    """Create a fresh run directory; never write into an existing non-empty one."""
    if path.exists() and (not path.is_dir() or any(path.iterdir())):
        raise InputError(f"{path} already exists and is not empty: choose another --out, or continue it with --resume {path}")
    try:
        path.mkdir(parents=True, exist_ok=True)
        probe = path / ".write-test"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as error:
        raise InputError(f"cannot write to {path}: {error.strerror}") from None
    return path


class Outcome(NamedTuple):
    status: str  # "complete", "interrupted" or "diverged"
    epoch: int  # last epoch whose state is saved
    state: TrainState
    rows: np.ndarray
    message: str


@contextlib.contextmanager
def _stop_on_sigint():
    """Turn Ctrl-C into a flag the loop checks between epochs, so a save is never cut."""
    requested = {"stop": False}

    def handler(signum, frame):
        requested["stop"] = True

    previous = signal.signal(signal.SIGINT, handler)
    try:
        yield requested
    finally:
        signal.signal(signal.SIGINT, previous)


def epoch_rows(epoch: int, seeds: np.ndarray, metrics: dict, seconds: float) -> np.ndarray:
    columns = [np.full(len(seeds), epoch), seeds] + [np.asarray(metrics[m], dtype=np.float64) for m in METRICS]
    return np.stack(columns + [np.full(len(seeds), seconds)], axis=1)


def train_epochs(
    trainer: Trainer,
    config: TrainConfig,
    run_dir: Path,
    state: TrainState,
    start_epoch: int,
    rows: np.ndarray,
    seeds: np.ndarray,
    on_epoch: Callable[[int, dict], None] = lambda epoch, metrics: None,
    on_compiled: Callable[[float], None] = lambda seconds: None,
) -> Outcome:
    """Run epochs ``start_epoch+1 .. config.epochs``, checkpointing as configured.

    Stops early on Ctrl-C (after saving) or on a non-finite loss or update
    (keeping the last good checkpoint, which it writes if it is not on disk yet).
    ``on_compiled`` gets the seconds the epoch took to compile; ``on_epoch``
    the epoch's metrics, with its wall time under ``"seconds"``.
    """
    arguments = (trainer.batches, trainer.train_states, trainer.test_states)
    started = time.perf_counter()
    epoch_fn = trainer.epoch.lower(state, *arguments).compile()  # compile before timing epochs
    on_compiled(time.perf_counter() - started)
    saved_epoch = start_epoch if (run_dir / CHECKPOINT_FILE).exists() else -1

    def save(epoch, state, rows):
        save_checkpoint(run_dir, epoch, state, rows)
        save_params(run_dir / PARAMS_FILE, state.params)
        write_metrics(run_dir / METRICS_FILE, rows)
        return epoch

    epoch = start_epoch
    with _stop_on_sigint() as stop:
        for epoch in range(start_epoch + 1, config.epochs + 1):
            started = time.perf_counter()
            new_state, metrics = epoch_fn(state, *arguments)
            metrics = jax.device_get(metrics)
            seconds = time.perf_counter() - started
            if not np.all(metrics["finite"]):
                bad = [int(s) for s, ok in zip(seeds, metrics["finite"]) if not ok]
                what = nonfinite_names(trainer.flows, int(np.bitwise_or.reduce(np.atleast_1d(metrics["nonfinite"]))))
                if saved_epoch != epoch - 1:
                    saved_epoch = save(epoch - 1, state, rows)
                message = (f"non-finite {', '.join(what)} at epoch {epoch} (seed {', '.join(map(str, bad))}); "
                           f"stopped, the last good checkpoint (epoch {saved_epoch}) is kept in {run_dir}")
                return Outcome("diverged", saved_epoch, state, rows, message)
            state = new_state
            rows = np.concatenate([rows, epoch_rows(epoch, seeds, metrics, seconds)])
            if epoch % config.checkpoint_every == 0 or epoch == config.epochs:
                saved_epoch = save(epoch, state, rows)
            on_epoch(epoch, {**metrics, "seconds": seconds})
            if stop["stop"]:
                if saved_epoch != epoch:
                    saved_epoch = save(epoch, state, rows)
                return Outcome("interrupted", epoch, state, rows,
                               f"interrupted after epoch {epoch}; continue with --resume {run_dir}")
    if saved_epoch != epoch:
        save(epoch, state, rows)
    return Outcome("complete", epoch, state, rows, "")


def summarize(rows: np.ndarray, column: str = "test_loss") -> tuple[float, float]:
    """Mean and standard deviation over seeds of ``column`` at the last epoch."""
    last = rows[rows[:, 0] == rows[:, 0].max()]
    values = last[:, COLUMNS.index(column)]
    return float(values.mean()), float(values.std()) if len(values) > 1 else 0.0


def empty_rows() -> np.ndarray:
    return np.zeros((0, len(COLUMNS)))
