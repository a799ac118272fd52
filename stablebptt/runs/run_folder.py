"""Run directories: config, metrics, parameters and checkpoints, each written atomically.

A run directory holds ``config.json``, ``metrics.csv`` (one row per epoch and seed), ``params.npz``
(final or latest parameters, leading axis = seed) and ``checkpoint.npz`` (the training state, a
carried population without its pool, and all metrics so far), and for an MJCF task ``model.xml`` and ``model.mjb.gz``, the model file as given and as
compiled (self-contained: includes and meshes inside; compressed), so the run can go on
after the file moved; a grid's cells share one compressed copy per model (``keep_model``).
The checkpoint is the source of truth: resuming reads it and rewrites the rest.

Every state of a folder can go on: ``config.json`` is written first and claims
the folder (atomically: of two runs given one folder, one gets it); a folder
without a checkpoint resumes from epoch 0; files are replaced atomically, so a
signal or a full disk at any moment leaves the old file or the new one. A run
holds a lock on its folder while it lives (released by the OS however it ends).
"""
from __future__ import annotations

import contextlib
import csv
import hashlib
import io
import json
import os
import zipfile
from datetime import datetime
from pathlib import Path
from typing import Any, Callable

import jax
import numpy as np

from stablebptt.engine.checks import check_options
from stablebptt.engine.config import STOPPING_OPTIONS, TrainConfig
from stablebptt.engine.episodes import checkpointed, restored
from stablebptt.engine.metrics import COLUMNS, empty_rows, widened
from stablebptt.engine.training import TrainState
from stablebptt.errors import InputError, StorageError, plain_scalar
from stablebptt.runs.model_store import copy_model
from stablebptt.storage import atomic_write, json_bytes, read_json, write_json, write_temporary

CONFIG_FILE = "config.json"
STARTUP_FILE = "startup.json"  # each start's set-up and compile phases (``record_start``)
METRICS_FILE = "metrics.csv"
PARAMS_FILE = "params.npz"
CHECKPOINT_FILE = "checkpoint.npz"
LOCK_FILE = ".lock"


def write_metrics(path: Path, rows: np.ndarray) -> None:
    """A tidy CSV: one row per epoch and seed; floats in full precision."""
    text = io.StringIO()
    writer = csv.writer(text, lineterminator="\n")
    writer.writerow(COLUMNS)
    writer.writerows([int(row[0]), int(row[1])] + [repr(float(v)) for v in row[2:]] for row in rows)
    atomic_write(path, text.getvalue().encode())


def read_metrics(path: Path) -> list[dict[str, float]]:
    with open(path, newline="") as handle:
        return [{key: float(value) for key, value in row.items()} for row in csv.DictReader(handle)]


def _metrics_problem(path: Path) -> tuple[list[dict[str, float]], str]:
    """(rows, what is wrong with ``path`` or ""). A last line without its newline was cut mid-line
    (``write_metrics`` ends every line): it is left out, as a number cut short still parses."""
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except FileNotFoundError:
        return [], "missing"
    except OSError as error:
        return [], f"unreadable ({error.strerror})"
    cut = bool(text) and not text.endswith("\n")
    if cut:
        text = text[:text.rfind("\n") + 1]
    try:
        rows = [{key: float(value) for key, value in row.items()} for row in csv.DictReader(io.StringIO(text))]
    except (ValueError, TypeError):  # float() of an empty, missing or non-numeric cell
        return [], "damaged (a missing or non-numeric value)"
    if cut:
        return rows, "cut mid-line"
    return rows, "" if rows else "empty"


def checkpoint_rows(run_dir: Path) -> np.ndarray | None:
    """The metric rows a run's checkpoint holds (``COLUMNS`` wide), or None without a readable one."""
    try:
        with np.load(Path(run_dir) / CHECKPOINT_FILE) as data:
            rows = widened(np.array(data["metrics"]))
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
        return None
    return rows if rows.ndim == 2 and rows.shape[1] == len(COLUMNS) else None


def run_metrics(run_dir: Path) -> tuple[list[dict[str, float]], str]:
    """(every metric row of a run, a note for the user or ""): ``metrics.csv``, or where it is missing,
    empty, cut or damaged, the rows of the checkpoint, which ``--resume`` writes back into it.

    Raises:
      InputError: no rows to read, with what can be done about it.
    """
    path = Path(run_dir) / METRICS_FILE
    rows, problem = _metrics_problem(path)
    if not problem:
        return rows, ""
    saved = checkpoint_rows(run_dir)
    if saved is not None and len(saved) >= len(rows) and len(saved):
        epochs = int(saved[:, 0].max())
        return ([dict(zip(COLUMNS, map(float, row))) for row in saved],
                f"{path} is {problem}: read {epochs} epoch{'s' if epochs != 1 else ''} from {CHECKPOINT_FILE} instead "
                f"(resuming the run, --resume {run_dir}, writes them back into {METRICS_FILE})")
    if problem == "cut mid-line" and rows:
        return rows, f"{path} is cut mid-line: its last line is left out"
    if problem in ("missing", "empty", "cut mid-line"):
        raise InputError(f"{path} is {problem if problem != 'cut mid-line' else 'cut in its first row'} and "
                         f"{run_dir} has no {CHECKPOINT_FILE} with metrics: not a run directory, or its run "
                         "has not finished an epoch yet")
    raise InputError(f"{path} is {problem} and {run_dir} has no {CHECKPOINT_FILE} to read the metrics from")


def _npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    return buffer.getvalue()


def save_params(path: Path, params: Any) -> None:
    atomic_write(path, _npz_bytes(_named_leaves(params)))


def load_param_leaves(path: Path) -> list[np.ndarray]:
    """The leaves ``save_params`` saved, in ``jax.tree.leaves`` order, seeds first: no template needed."""
    try:
        with np.load(path) as data:
            return _read_leaves(data, len(data.files))  # nothing but leaves: any other array is foreign
    except FileNotFoundError:
        raise InputError(f"{path} does not exist: the run has not finished an epoch yet") from None
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as error:  # truncated or foreign
        raise InputError(f"{path} is damaged ({' '.join(str(error).split())})") from None


def load_params(path: Path, template: Any) -> Any:
    """Parameters saved by ``save_params``, in the structure of ``template``."""
    return _unflatten_like(template, load_param_leaves(path), path)


def _named_leaves(tree: Any) -> dict[str, np.ndarray]:
    """A pytree's leaves as an npz's arrays: ``leaf_000``, ``leaf_001``, ... in ``jax.tree.leaves`` order."""
    return {f"leaf_{i:03d}": leaf for i, leaf in enumerate(jax.tree.leaves(jax.device_get(tree)))}


def _read_leaves(data: Any, count: int) -> list[np.ndarray]:
    """The ``count`` leaves ``_named_leaves`` wrote into an open npz, in order; KeyError where one is missing."""
    return [data[f"leaf_{i:03d}"] for i in range(count)]


def _unflatten_like(template: Any, leaves: list[np.ndarray], path: Path) -> Any:
    template_leaves, treedef = jax.tree.flatten(template)
    if len(leaves) != len(template_leaves) or any(a.shape != b.shape for a, b in zip(leaves, template_leaves)):
        raise InputError(f"{path} does not match this run's configuration (different network or seeds), or was "
                         "saved by a version whose training state differs (carried episodes saved before "
                         "their pool of fresh states)")
    return jax.tree.unflatten(treedef, [np.asarray(a, dtype=b.dtype) for a, b in zip(leaves, template_leaves)])


def identity(record: dict) -> str:
    """What a checkpoint belongs to: the task and the training settings, except how long to train."""
    train = {k: v for k, v in record.get("train", {}).items() if k not in STOPPING_OPTIONS}
    return hashlib.sha256(json.dumps([record.get("task"), record.get("task_config"), train],
                                     sort_keys=True, default=plain_scalar).encode()).hexdigest()


def save_checkpoint(run_dir: Path, epoch: int, state: TrainState, rows: np.ndarray, owner: str = "") -> None:
    """What a resume needs after ``epoch`` (``episodes.checkpointed``), the metrics; ``owner``: the run's ``identity``."""
    atomic_write(run_dir / CHECKPOINT_FILE, _npz_bytes({"epoch": np.array(epoch), "metrics": rows,
                                                        "owner": np.array(owner), **_named_leaves(checkpointed(state))}))


def load_checkpoint(run_dir: Path, template: TrainState, owner: str = "") -> tuple[int, TrainState, np.ndarray]:
    """(epoch, state, metric rows) of the checkpoint; a checkpoint of another run or a damaged one is refused."""
    path = run_dir / CHECKPOINT_FILE
    try:
        with np.load(path) as data:
            epoch = int(data["epoch"])
            rows = widened(np.array(data["metrics"]))
            saved_owner = str(data["owner"]) if "owner" in data.files else ""
            leaves = _read_leaves(data, sum(name.startswith("leaf_") for name in data.files))
    except FileNotFoundError:
        raise InputError(f"{path} does not exist: the run never finished an epoch; start it again") from None
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as error:  # truncated or foreign
        raise InputError(f"{path} is damaged ({' '.join(str(error).split())}): restore it, or delete it with "
                         f"{PARAMS_FILE} and {METRICS_FILE} and resuming (--resume) starts again at epoch 0") from None
    if owner and saved_owner and saved_owner != owner:
        raise InputError(f"{path} is the checkpoint of another run (another task or settings than "
                         f"{run_dir / CONFIG_FILE}): put the right checkpoint back, or delete it to start from epoch 0")
    if rows.ndim != 2 or rows.shape[1] != len(COLUMNS) or not 0 <= epoch <= 10**9:
        raise InputError(f"{path} is damaged (its metrics or epoch do not fit this version's run format)")
    if len(leaves) == len(jax.tree.leaves(template)):  # nothing left out (or a checkpoint that kept the pool)
        return epoch, _unflatten_like(template, leaves, path), rows
    return epoch, restored(_unflatten_like(checkpointed(template), leaves, path), template), rows


def default_run_dir(root: Path, task_name: str) -> Path:
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    candidate, suffix = root / f"{task_name}-{stamp}", 1
    while candidate.exists():
        suffix += 1
        candidate = root / f"{task_name}-{stamp}-{suffix}"
    return candidate


class RunLock:
    """An exclusive lock on a run folder for as long as this object lives (or the process does).

    ``fcntl.flock`` is released by the OS however the process ends, SIGKILL included: none stays locked.
    """

    def __init__(self, run_dir: Path):
        self.handle = None
        try:
            import fcntl
        except ImportError:  # no flock on this platform: folders are claimed by config.json alone
            return
        path = run_dir / LOCK_FILE
        try:
            handle = open(path, "a+")
        except OSError as error:
            raise InputError(f"cannot write to {run_dir}: {error.strerror}") from None
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            handle.seek(0)
            holder = handle.read().strip() or "another process"
            handle.close()
            raise InputError(f"{run_dir} is in use by another run (process {holder}): wait for it to end, "
                             "or choose another folder (--out)") from None
        handle.seek(0)
        handle.truncate()
        handle.write(str(os.getpid()))
        handle.flush()
        self.handle = handle
        for stale in run_dir.glob(".*.tmp"):  # temporaries of a process killed mid-write: only the holder writes
            stale.unlink(missing_ok=True)

    def release(self) -> None:
        if self.handle is not None:
            self.handle.close()
            self.handle = None


def refuse_used(path: Path) -> None:
    """``InputError`` where ``create_run`` would refuse ``path`` as it stands (a file, a folder holding
    anything but hidden files, or one that cannot be made there), checked without creating anything: a
    command refuses such an ``--out`` at once, and claims the folder once its set-up is done."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise InputError(f"{path} is a file: give a directory for the run")
    if path.is_dir() and any(not entry.name.startswith(".") for entry in path.iterdir()):
        raise InputError(f"{path} already exists and is not empty: choose another run folder (--out), or continue "
                         f"its run (--resume {path})")
    above = next(folder for folder in (path.absolute(), *path.absolute().parents) if folder.exists())  # made in it
    if not (above.is_dir() and os.access(above, os.W_OK | os.X_OK)):
        raise InputError(f"cannot create {path}: {above} is {'not writable' if above.is_dir() else 'a file'}")


def create_run(path: Path, record: dict) -> RunLock:
    """Claim a fresh run folder by writing its ``config.json`` (``record``); returns the folder's lock.

    Never writes into a folder that holds anything but hidden files (a lock, or
    temporaries of a start that was killed). Of two runs given one folder at once,
    one gets it and the other an ``InputError``.
    """
    path = Path(path)
    refuse_used(path)  # before the lock: a folder that is not ours is left untouched
    made = not path.exists()
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise InputError(f"cannot create {path}: {error.strerror}") from None
    lock = RunLock(path)
    try:
        refuse_used(path)  # again under the lock: another run may have claimed it in between
        temporary = write_temporary(path / CONFIG_FILE, json_bytes(record))
        try:
            os.link(temporary, path / CONFIG_FILE)  # fails if the name exists: an atomic claim
        except FileExistsError:
            raise InputError(f"{path} was just claimed by another run: choose another run folder (--out)") from None
        except OSError as error:
            raise StorageError(error.errno, f"cannot write {path / CONFIG_FILE}: {error.strerror}") from None
        finally:
            temporary.unlink(missing_ok=True)
    except BaseException:
        # A claim left incomplete (a refusal, a signal anywhere in it) leaves no temporary, nor a folder it made.
        for temporary in path.glob(".*.tmp"):  # under the lock: only the holder writes them
            temporary.unlink(missing_ok=True)
        lock.release()
        if made and not (path / CONFIG_FILE).exists():
            with contextlib.suppress(OSError):  # another start put something there meanwhile: it is theirs
                (path / LOCK_FILE).unlink(missing_ok=True)
                path.rmdir()
        raise
    return lock


RECORD_FIELDS = {"task": str, "task_config": dict, "train": dict}


def open_run(path: Path) -> dict:
    """The ``config.json`` of the run folder ``path``, with 'task' (str), 'task_config' and 'train' (objects)."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path} does not exist: give a run directory")
    if not path.is_dir():
        raise InputError(f"{path} is a file, not a run directory: give the folder the run wrote")
    record = read_json(path / CONFIG_FILE)
    wrong = [f"'{key}' ({kind.__name__})" for key, kind in RECORD_FIELDS.items()
             if not isinstance(record, dict) or not isinstance(record.get(key), kind)]
    if wrong:
        raise InputError(f"{path / CONFIG_FILE} is not a run configuration: it lacks {', '.join(wrong)}")
    return record


def run_record(task_name: str, task_config: Any, train_config: Any, task: Any = None, **extra: Any) -> dict:
    """A run folder's ``config.json``: the one schema of single runs, grid cells and test folders.

    Args:
      task_name: the registry's name of the task.
      task_config: the task's options (a dataclass, whose options set apart from their defaults are
        recorded too, as ``task_options_set``: what a figure's title names; a dict where it is one already).
      train_config: the ``TrainConfig`` (a dict where it is one already).
      task: the task built from them; when given, it is recorded as resolved (``resolved_task``).
      **extra: further top-level entries: the ``environment`` of a single run, the ``sweep`` of a grid cell.
    """
    import dataclasses

    as_dict = lambda config: config if isinstance(config, dict) else dataclasses.asdict(config)  # noqa: E731
    resolved = {} if task is None else {"resolved_task": {"name": task.name, **task.resolved}}
    given = {} if isinstance(task_config, dict) else {"task_options_set": sorted(
        item.name for item in dataclasses.fields(task_config) if getattr(task_config, item.name) != item.default)}
    return {"task": task_name, "task_config": as_dict(task_config), **given, **resolved,
            "train": as_dict(train_config), **extra}


def write_config(directory: Path, record: dict) -> None:
    """Write (or replace) a run folder's ``config.json``; ``create_run`` claims a fresh folder with it instead."""
    write_json(Path(directory) / CONFIG_FILE, record)


def new_record(task_name: str, task_config: Any, task: Any, train_config: TrainConfig, **extra: Any) -> dict:
    """The config.json of a new run: the task as configured and as resolved, training, versions, device.

    Raises:
      InputError: options set together where one makes the other meaningless (``checks.check_options``).
    """
    import platform

    check_options(train_config, task_config)
    environment = {"python": platform.python_version(), "jax": jax.__version__, "device": str(jax.devices()[0])}
    return run_record(task_name, task_config, train_config, task, environment=environment, **extra)


class Run:
    """A run folder in use, held under its lock until ``close``: its record and where training stands.

    ``Run.create`` claims a fresh folder (and keeps the model file, for an MJCF
    task); ``Run.open`` continues one. ``start`` loads the checkpoint, if any;
    ``train_epochs`` trains into the folder.
    """

    def __init__(self, directory: Path, record: dict, lock: RunLock, resuming: bool):
        self.directory, self.record, self.lock, self.resuming = Path(directory), record, lock, resuming
        self.repaired: list[str] = []  # results ``start`` rewrote from the checkpoint

    @classmethod
    def create(cls, directory: Path, record: dict) -> "Run":
        lock = create_run(directory, record)  # from here on the folder resumes
        model_file = record.get("resolved_task", {}).get("model_file")
        try:
            if model_file:
                copy_model(Path(directory), model_file)
        except BaseException:
            lock.release()
            raise
        return cls(directory, record, lock, resuming=False)

    @classmethod
    def open(cls, directory: Path, record: dict | None = None) -> "Run":
        record = open_run(directory) if record is None else record
        return cls(directory, record, RunLock(Path(directory)), resuming=True)

    @property
    def owner(self) -> str:
        return identity(self.record)

    @property
    def name(self) -> str:
        return self.record.get("resolved_task", {}).get("name", self.record["task"])

    def start(self, fresh: Callable[[], TrainState], shapes: Callable[[], Any], config: TrainConfig) -> tuple:
        """(epoch, state, metric rows) to train on from: the checkpoint's, read into ``shapes()`` (traced, not
        run: a fresh state's resets cost CheetahRun's resume 30 s on a GPU), else ``fresh()`` at epoch 0. A resumed
        run's record takes ``config.epochs`` and ``config.budget`` when it trains further; fewer epochs are refused."""
        if (self.directory / CHECKPOINT_FILE).exists():
            start_epoch, state, rows = load_checkpoint(self.directory, shapes(), self.owner)
        else:
            if self.resuming:
                self._refuse_results_without_checkpoint()
            start_epoch, state, rows = 0, fresh(), empty_rows()
        if config.epochs < start_epoch:
            raise InputError(f"{self.directory} has trained {start_epoch} epochs: ask for that many or more (--epochs)")
        recorded = self.record["train"]
        if self.resuming and config.epochs > start_epoch and (config.epochs, config.budget) != (
                recorded["epochs"], recorded.get("budget", 0.0)):
            import dataclasses
            self.record = {**self.record, "train": dataclasses.asdict(config)}
            write_config(self.directory, self.record)
        if self.resuming and start_epoch > 0:
            self.repaired = self._repair(state, rows)
        return start_epoch, state, rows

    def _repair(self, state: TrainState, rows: np.ndarray) -> list[str]:
        """Rewrite from the checkpoint the results that are missing, cut or damaged (a run that is done
        already would otherwise keep them so); returns the names of the files rewritten."""
        repaired = []
        saved, problem = _metrics_problem(self.directory / METRICS_FILE)
        if problem or len(saved) != len(rows):
            write_metrics(self.directory / METRICS_FILE, rows)
            repaired.append(METRICS_FILE)
        try:
            load_params(self.directory / PARAMS_FILE, state.params)
        except InputError:
            save_params(self.directory / PARAMS_FILE, state.params)
            repaired.append(PARAMS_FILE)
        return repaired

    def _refuse_results_without_checkpoint(self) -> None:
        """A folder with trained results but no checkpoint cannot continue: training from epoch 0
        would overwrite them (a sweep cell, or a run whose checkpoint was deleted)."""
        results = [name for name in (PARAMS_FILE, METRICS_FILE) if (self.directory / name).exists()]
        if not results:
            return  # stopped before its first epoch: nothing to lose, it starts from epoch 0
        try:
            epochs = len({row["epoch"] for row in read_metrics(self.directory / METRICS_FILE)})
            held = f"{' and '.join(results)} ({epochs} epoch{'s' if epochs != 1 else ''})"
        except (OSError, ValueError, KeyError):
            held = " and ".join(results)
        raise InputError(f"{self.directory} holds {held} but no {CHECKPOINT_FILE}: resuming (--resume) would train "
                         f"over them from epoch 0; use another run folder (--out) or move {' and '.join(results)} away")

    def close(self) -> None:
        self.lock.release()
