"""Epochs into a run folder: a ``Trainer`` trained to ``config.epochs``, checkpointed as it goes."""
from __future__ import annotations

import time
from datetime import datetime
from pathlib import Path
from typing import Callable, NamedTuple

import jax
import numpy as np

from stablebptt.engine.config import TrainConfig
from stablebptt.engine.divergence import nonfinite_message, zeroed_notice
from stablebptt.engine.fitting import (
    Evaluations,
    cuttable_updates,
    env_steps_per_epoch,
    epoch_runner,
    fit,
    out_of_time,
)
from stablebptt.engine.lowering import LoweredEpoch
from stablebptt.engine.program_store import compile_seconds_saved
from stablebptt.engine.starting import compiled_refill, compiled_then_made
from stablebptt.engine.training import Trainer, TrainState
from stablebptt.errors import InputError
from stablebptt.runs.run_folder import (
    METRICS_FILE,
    PARAMS_FILE,
    STARTUP_FILE,
    save_checkpoint,
    save_params,
    write_metrics,
)
from stablebptt.storage import read_json, write_json
from stablebptt.timing import machine


class Outcome(NamedTuple):
    status: str  # "complete", "interrupted", "budget" or "diverged"
    epoch: int  # last epoch whose state is saved
    state: TrainState
    rows: np.ndarray
    message: str


def train_epochs(
    trainer: Trainer,
    config: TrainConfig,
    run_dir: Path,
    state: TrainState | Callable[[], TrainState],
    start_epoch: int,
    rows: np.ndarray,
    seeds: np.ndarray,
    on_epoch: Callable[[int, dict], None] = lambda epoch, metrics: None,
    on_compiled: Callable[[float], None] = lambda seconds: None,
    should_stop: Callable[[], bool] = lambda: False,
    owner: str = "",
    program_key: dict | None = None,
    lowered: LoweredEpoch | None = None,
    started: float | None = None,
    phases: dict[str, float] | None = None,
    compile_saved_mark: float | None = None,
) -> Outcome:
    """Train one run's seeds to ``config.epochs`` from ``start_epoch``, checkpointing into ``run_dir``.

    Stops early when ``should_stop()`` (after saving; the command line sets it on a signal), where one
    more epoch would end past ``config.budget`` seconds since ``started`` (a ``time.perf_counter()``,
    default now; the command's start: ``fitting.out_of_time``), or on a non-finite loss or update (keeping the last good checkpoint). The
    last epoch trained is always evaluated. ``on_compiled`` gets the seconds the epoch and its
    evaluation took to compile; ``on_epoch`` the epoch's metrics, with its training and evaluation
    time under ``"seconds"`` and ``"eval_seconds"``. Runs in any thread. With ``program_key``
    (everything that decides the epoch's program: ``program_store``) and JAX's compile cache on, the
    traced epoch is kept there, and a run with the same key skips tracing it. ``lowered``: the epoch
    lowered already (``starting.prepare``), used where ``state`` has its shapes; ``state`` may be a
    function that makes a fresh one, made once the epoch has compiled (``Session.state``). ``phases``: the
    start-up's phases so far (``Prepared.phases``), recorded with the compile's in the run's
    ``startup.json``; ``compile_saved_mark``: ``program_store.compile_seconds_saved()`` as the start
    began (``Session.compile_saved_mark``), to record the compile the persistent cache saved it.
    """
    started = time.perf_counter() if started is None else started
    phases = dict(phases or {})
    # Before timing epochs; a fresh state that is still to be made is made once the epoch has compiled.
    epoch_fn, seconds, state, made = compiled_then_made(trainer, state, lowered, program_key)
    phases["compile"] = phases.get("compile", 0.0) + seconds  # prepare may have compiled it beside a check
    if made is not None:
        phases["init"] = made
    refill, seconds = compiled_refill(trainer, state, lowered and lowered.refill, program_key)  # beside the epoch
    phases["compile"] += seconds
    evaluations = Evaluations(trainer, config)
    phases["evaluation's compile"] = evaluations.compile(state, lowered and lowered.evaluation)
    on_compiled(phases.get("compile beside the check", 0.0) + phases["compile"] + phases["evaluation's compile"])
    record_start(run_dir, {name: seconds for name, seconds in phases.items() if seconds},
                 time.perf_counter() - started, config.budget, start_epoch + 1,
                 None if compile_saved_mark is None else compile_seconds_saved() - compile_saved_mark)
    def save(epoch, state, rows):
        save_checkpoint(run_dir, epoch, state, rows, owner)
        save_params(run_dir / PARAMS_FILE, state.params)
        write_metrics(run_dir / METRICS_FILE, rows)

    # fit's message: what failed (diverged), or how the budget's last epoch was cut short
    status, epoch, state, rows, fit_message = fit(
        epoch_runner(trainer, epoch_fn, refill), state, start_epoch, config.epochs, rows, seeds, save,
        config.checkpoint_every, should_stop, on_epoch, lambda metrics: nonfinite_message(trainer.flows, metrics),
        noticed=lambda metrics: zeroed_notice(trainer.flows, metrics, seeds), evaluate=evaluations,
        out_of_time=out_of_time(config, started), steps_per_epoch=env_steps_per_epoch(trainer, config),
        seeds_apart=True, updates_per_epoch=cuttable_updates(trainer))
    if status == "diverged":
        message = f"{fit_message}; stopped, the last good checkpoint (epoch {epoch}) is kept in {run_dir}"
    elif status == "interrupted":
        message = f"interrupted after epoch {epoch}; continue by resuming the run (--resume {run_dir})"
    elif status == "budget":
        ended = (f"ended with epoch {epoch} {fit_message}" if fit_message
                 else f"has no room for another epoch after epoch {epoch}")
        message = (f"the budget of {config.budget:g} s {ended}; train further by resuming the run with a budget "
                   f"(--resume {run_dir} --budget SECONDS)")
    else:
        message = ""
    record_end(run_dir, status, epoch, message)
    return Outcome(status, epoch, state, rows, message)


def _starts(run_dir: Path) -> list[dict]:
    path = Path(run_dir) / STARTUP_FILE
    try:
        return read_json(path) if path.exists() else []
    except (OSError, InputError):
        return []  # a damaged record of earlier starts does not stop this one


def record_start(run_dir: Path, phases: dict[str, float], seconds: float, budget: float = 0.0,
                 first_epoch: int = 1, compile_seconds_from_cache: float | None = None) -> None:
    """Add a start of the run (its first, or a ``--resume``) to its ``startup.json``: when ("started", the
    moment its programs had compiled and its first epoch was to begin: the command began
    ``seconds_to_training`` before), on which device and host, the seconds of each start-up phase and
    from the command's start to its first epoch's start, the budget it was given (none: left out), the
    epoch it trains first and the seconds of compile that JAX's persistent cache saved it (where
    measured: a fresh machine's start saves none, a start after the same programs ran on the machine
    most of its compile)."""
    path, starts = Path(run_dir) / STARTUP_FILE, _starts(run_dir)
    device = jax.devices()[0]
    # The host too: the same start on two H200 hosts differed by a third (docs/performance.md).
    starts.append({"started": datetime.now().isoformat(timespec="seconds"), "device": f"{device.platform} ({device.device_kind})",
                   "host": machine(),
                   "seconds_to_training": round(seconds, 3), "phases": {name: round(value, 3) for name, value in phases.items() if round(value, 3)},
                   "first_epoch": first_epoch, **({"budget": budget} if budget else {}),
                   **({} if compile_seconds_from_cache is None
                      else {"compile_seconds_from_cache": round(compile_seconds_from_cache, 3)})})
    write_json(path, starts)


def record_end(run_dir: Path, status: str, epoch: int, message: str) -> None:
    """Say in the run's latest start (``record_start``) how it ended: its status (complete, interrupted,
    budget, diverged), its last saved epoch and the message the command printed."""
    starts = _starts(run_dir)
    if starts:
        starts[-1]["ended"] = {"status": status, "epoch": epoch, "message": message}
        write_json(Path(run_dir) / STARTUP_FILE, starts)
