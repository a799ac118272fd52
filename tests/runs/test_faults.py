"""Faults lose nothing and every run folder can go on: signals at any moment, two runs on one
folder, damaged folders, a full disk, a model file that moved or changed, any thread."""
from __future__ import annotations

import dataclasses
import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Callable

import jax
import numpy as np
import pytest
from conftest import ROOT
from held_compile import COMPILING, held_command, release, stderr_through, wait_for

from stablebptt import errors, storage
from stablebptt.commands import train as train_command
from stablebptt.engine import fitting, program_store, training
from stablebptt.engine.metrics import COLUMNS, METRICS, empty_rows
from stablebptt.engine.config import TrainConfig, seed_array
from stablebptt.engine.training import make_trainer
from stablebptt.errors import InputError
from stablebptt.reports import curves
from stablebptt.runs import epochs, model_store, run_folder
from stablebptt.tasks import repulsion

SMALL = ["--task", "repulsion", "--train-size", "16", "--test-size", "16", "--batch", "8", "--no-progress"]
TRAIN = [sys.executable, str(ROOT / "scripts" / "train.py")]


def train(capsys, *argv: str) -> tuple[int, list[str], str]:
    """scripts/train.py in this process: (exit code, stderr lines, stdout)."""
    try:
        code = train_command.main(list(argv))
    except SystemExit as exit_:
        code = exit_.code
    captured = capsys.readouterr()
    return code, [line for line in captured.err.splitlines() if line.strip()], captured.out


def snapshot(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.name != run_folder.LOCK_FILE}


def epochs_in(folder: Path) -> list[int]:
    return sorted({int(row["epoch"]) for row in run_folder.read_metrics(folder / run_folder.METRICS_FILE)})


@pytest.fixture(scope="module")
def finished(tmp_path_factory) -> Path:
    """A repulsion run of 2 epochs, made by the command line in this process."""
    run_dir = tmp_path_factory.mktemp("faults") / "finished"
    assert train_command.main(SMALL + ["--epochs", "2", "--out", str(run_dir)]) == 0
    return run_dir


def test_sigterm_saves_like_ctrl_c_and_resume_goes_on(tmp_path, capsys):
    run_dir = tmp_path / "terminated"
    process = subprocess.Popen(TRAIN + SMALL + ["--epochs", "1000", "--out", str(run_dir)], cwd=tmp_path,
                               stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    wait_for(run_dir / run_folder.CHECKPOINT_FILE, process)
    process.send_signal(signal.SIGTERM)
    _, stderr = process.communicate(timeout=120)
    assert process.returncode == 128 + signal.SIGTERM, stderr
    assert "SIGTERM" in stderr and f"--resume {run_dir}" in stderr and "Traceback" not in stderr
    done = epochs_in(run_dir)
    assert done == list(range(1, len(done) + 1)) and len(done) < 1000  # every epoch trained is kept
    code, err, _ = train(capsys, "--resume", str(run_dir), "--epochs", str(len(done) + 1), "--no-progress")
    assert code == 0, err
    assert epochs_in(run_dir) == list(range(1, len(done) + 2))


def test_resume_without_a_checkpoint_refuses_to_train_over_the_results_it_holds(finished, tmp_path, capsys):
    folder = tmp_path / "no-checkpoint"
    shutil.copytree(finished, folder)
    (folder / run_folder.CHECKPOINT_FILE).unlink()  # a sweep cell's folder, or a checkpoint deleted
    before = snapshot(folder)
    code, err, _ = train(capsys, "--resume", str(folder), "--no-progress")
    assert code == 2 and len(err) == 1, err
    assert "params.npz and metrics.csv (2 epochs) but no checkpoint.npz" in err[0]
    assert "another run folder (--out)" in err[0]
    assert snapshot(folder) == before  # nothing trained over, nothing rewritten


def test_a_signal_to_the_run_and_then_to_its_group_saves_and_stops_once(tmp_path):
    """What GNU timeout (and a batch scheduler's time limit) does: SIGTERM to the command, then to its
    process group. Both reach the run: one request to stop, the epoch saved. Sent once the first
    checkpoint exists, so that no machine's speed decides what the run has to save."""
    run_dir = tmp_path / "timed"
    process = subprocess.Popen(TRAIN + SMALL + ["--epochs", "100000", "--out", str(run_dir)], cwd=tmp_path,
                               stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True)
    wait_for(run_dir / run_folder.CHECKPOINT_FILE, process)
    os.kill(process.pid, signal.SIGTERM)
    os.killpg(process.pid, signal.SIGTERM)  # its own session: the group is the run's alone
    _, stderr = process.communicate(timeout=120)
    assert process.returncode == 128 + signal.SIGTERM, stderr
    assert stderr.count("SIGTERM: stopping after this epoch") == 1 and "interrupted after epoch" in stderr
    assert "Traceback" not in stderr
    assert not [p.name for p in run_dir.iterdir() if p.name.endswith(".tmp")]  # no temporary file survives
    assert epochs_in(run_dir) == list(range(1, len(epochs_in(run_dir)) + 1)) and (run_dir / run_folder.CHECKPOINT_FILE).exists()


@pytest.mark.parametrize("how", ["SIGKILL as the folder is claimed", "SIGTERM while compiling"])
def test_a_signal_at_any_moment_leaves_a_folder_that_resumes(tmp_path, capsys, how):
    run_dir, hold = tmp_path / "early", tmp_path / "hold"
    # The epoch's compile waits for the test: the run cannot reach its first epoch before the signal.
    process = subprocess.Popen(held_command(hold, *TRAIN[1:], *SMALL, "--epochs", "1", "--out", str(run_dir)),
                               cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    seen = ""
    if how.startswith("SIGKILL"):
        wait_for(run_dir / run_folder.CONFIG_FILE, process)
        process.send_signal(signal.SIGKILL)
    else:
        wait_for(hold / COMPILING, process)
        process.send_signal(signal.SIGTERM)
        # Taken while compiling, before any epoch: it stops at once, the compile not waited for (held, it never ends).
        seen = stderr_through(process, "SIGTERM: stopped before this start's first epoch")
        assert f"--resume {run_dir}" in seen
        process.wait(timeout=60)
        release(hold)
    _, stderr = process.communicate(timeout=120)
    stderr = seen + stderr
    assert process.returncode == (-signal.SIGKILL if how.startswith("SIGKILL") else 128 + signal.SIGTERM), stderr
    assert "Traceback" not in stderr
    assert not (run_dir / run_folder.CHECKPOINT_FILE).exists()
    again = train(capsys, *SMALL, "--epochs", "1", "--out", str(run_dir))  # the same command: refused, pointing on
    assert again[0] == 2 and f"--resume {run_dir}" in again[1][0], again
    code, err, _ = train(capsys, "--resume", str(run_dir), "--no-progress")
    assert code == 0, err
    assert epochs_in(run_dir) == [1]


def test_signals_are_handled_while_the_work_sits_in_one_long_native_call():
    # XLA compiles a large contact scene in one call for many minutes; Python runs a signal handler
    # only when the main thread's call returns, so the work runs in a worker thread. The native call
    # here is libc's poll of a pipe, which only the handler writes to: the signal blocked in the calling
    # thread (no EINTR ends the call early), it waits up to 60 s, so a handler that ran only once the
    # call returned (the work in the main thread) would come too late and the poll would find nothing.
    import ctypes
    from stablebptt.cli import in_worker_thread

    class PollFd(ctypes.Structure):
        _fields_ = [("fd", ctypes.c_int), ("events", ctypes.c_short), ("revents", ctypes.c_short)]

    poll = ctypes.CDLL(None, use_errno=True).poll
    readable, writable = os.pipe()
    previous = signal.signal(signal.SIGUSR1, lambda signum, frame: os.write(writable, b"x"))
    try:
        def work():
            signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGUSR1})  # the main thread takes it
            os.kill(os.getpid(), signal.SIGUSR1)
            waiting = PollFd(readable, 1, 0)  # POLLIN
            return poll(ctypes.byref(waiting), 1, 60_000)  # 1 once the pipe holds the handler's byte; 0 at 60 s
        assert in_worker_thread(work) == 1
    finally:
        signal.signal(signal.SIGUSR1, previous)
        os.close(readable), os.close(writable)
    def failing_work():
        raise InputError("raised in the worker")
    with pytest.raises(InputError, match="raised in the worker"):
        in_worker_thread(failing_work)


@pytest.mark.parametrize("where", ["mid-write", "after the temporary"])
def test_a_claim_interrupted_at_any_point_leaves_no_folder_and_the_same_out_starts_afresh(tmp_path, monkeypatch, where):
    record = {"task": "repulsion", "task_config": {}, "train": {}}
    folder = tmp_path / "run"
    written = storage.write_temporary

    def interrupted(path, data):  # Ctrl-C inside the write (its file open), or just after it returned
        if where == "mid-write":
            monkeypatch.setattr(os, "fsync", lambda fd: (_ for _ in ()).throw(KeyboardInterrupt()))
            return written(path, data)
        written(path, data)
        raise KeyboardInterrupt

    monkeypatch.setattr(run_folder, "write_temporary", interrupted)
    with pytest.raises(KeyboardInterrupt):
        run_folder.create_run(folder, record)
    assert not folder.exists(), sorted(entry.name for entry in folder.iterdir())
    monkeypatch.undo()
    lock = run_folder.create_run(folder, record)
    assert json.loads((folder / "config.json").read_text()) == record
    lock.release()


def test_two_runs_given_one_folder_at_once_one_is_refused(tmp_path):
    record = {"task": "repulsion", "task_config": {}, "train": {}}
    for attempt in range(20):
        folder = tmp_path / f"contested-{attempt}"
        start = threading.Barrier(2)
        results: list = []

        def claim():
            start.wait()
            try:
                results.append(run_folder.create_run(folder, record))
            except InputError as error:
                results.append(error)

        threads = [threading.Thread(target=claim) for _ in range(2)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        winners = [r for r in results if isinstance(r, run_folder.RunLock)]
        losers = [r for r in results if isinstance(r, InputError)]
        assert len(winners) == 1 and len(losers) == 1, results
        assert "\n" not in str(losers[0]) and str(folder) in str(losers[0])
        winners[0].release()
    assert json.loads((tmp_path / "contested-0" / run_folder.CONFIG_FILE).read_text()) == record


def test_a_folder_in_use_is_refused_to_a_second_process(finished, capsys):
    lock = run_folder.RunLock(finished)  # as a live run holds it
    try:
        code, err, _ = train(capsys, "--resume", str(finished), "--epochs", "3", "--no-progress")
    finally:
        lock.release()
    assert code == 2 and len(err) == 1 and "in use by another run" in err[0], err


def _truncate_checkpoint(folder: Path) -> None:
    data = (folder / run_folder.CHECKPOINT_FILE).read_bytes()
    (folder / run_folder.CHECKPOINT_FILE).write_bytes(data[: len(data) // 2])


def _edit_config(change):
    def damage(folder: Path) -> None:
        record = storage.read_json(folder / run_folder.CONFIG_FILE)
        change(record)
        run_folder.write_config(folder, record)
    return damage


def _foreign_checkpoint(folder: Path) -> None:
    record = json.loads((folder / run_folder.CONFIG_FILE).read_text())
    other = {**record, "task_config": {**record["task_config"], "rc": 0.5}}  # same shapes, another task
    trainer_config = TrainConfig(**{**record["train"]})
    template = make_trainer(repulsion.make(repulsion.Config()), trainer_config).init(seed_array(trainer_config))
    epoch, state, rows = run_folder.load_checkpoint(folder, template)
    run_folder.save_checkpoint(folder, epoch, state, rows, run_folder.identity(other))


DAMAGES = {
    "truncated checkpoint": (_truncate_checkpoint, "is damaged"),
    "config.json not JSON": (lambda f: (f / run_folder.CONFIG_FILE).write_text("{\"task\": "), "not valid JSON"),
    "config.json a list": (lambda f: (f / run_folder.CONFIG_FILE).write_text("[]"), "not a run configuration"),
    "a training option of the wrong type": (_edit_config(lambda r: r["train"].update(seeds="ten")),
                                            "seeds must be a whole number"),
    "task option of the wrong type": (_edit_config(lambda r: r["task_config"].update(rc=[1])), "rc must be float"),
    "unknown task": (_edit_config(lambda r: r.update(task="pendulum")), "names the task 'pendulum'"),
    "task_config missing": (_edit_config(lambda r: r.pop("task_config")), "task_config"),
    "checkpoint of another run": (_foreign_checkpoint, "checkpoint of another run"),
}


@pytest.mark.parametrize("case", list(DAMAGES))
def test_a_damaged_folder_gets_one_line_and_is_left_as_it_was(finished, tmp_path, capsys, case):
    damage, words = DAMAGES[case]
    folder = tmp_path / "damaged"
    shutil.copytree(finished, folder)
    damage(folder)
    before = snapshot(folder)
    code, err, _ = train(capsys, "--resume", str(folder), "--epochs", "3", "--no-progress")
    assert code == 2 and len(err) == 1 and err[0].startswith("error: ") and words in err[0], err
    assert snapshot(folder) == before


def test_resume_given_a_file_or_fewer_epochs_changes_nothing(finished, capsys):
    before = snapshot(finished)
    code, err, _ = train(capsys, "--resume", str(finished / run_folder.CONFIG_FILE))
    assert code == 2 and len(err) == 1 and "is a file, not a run directory" in err[0], err
    code, err, _ = train(capsys, "--resume", str(finished), "--epochs", "1", "--no-progress")
    assert code == 2 and len(err) == 1 and "has trained 2 epochs" in err[0], err
    code, err, out = train(capsys, "--resume", str(finished), "--no-progress")
    assert code == 0 and "done already" in out, err
    assert snapshot(finished) == before


def test_a_resume_builds_no_fresh_state_and_traces_no_program_kept_by_the_first_start(finished, tmp_path, capsys,
                                                                                        monkeypatch):
    """A fresh state was built only to be replaced by the checkpoint's (its resets and their compile cost
    CheetahRun's resume on a GPU 30 s), and a resume with more --epochs than the first start traced every
    program again (80 s): how long a run trains is no part of what it compiles."""
    folder = tmp_path / "resumed"
    shutil.copytree(finished, folder)

    def fresh_state(self, seeds):
        raise AssertionError("a resume built a fresh training state")

    monkeypatch.setattr(training.Initializer, "__call__", fresh_state)
    monkeypatch.setattr(program_store, "_traced", lambda *a: pytest.fail("traced again although kept"))
    code, err, _ = train(capsys, "--resume", str(folder), "--epochs", "3", "--no-progress")
    assert code == 0, err
    assert epochs_in(folder) == [1, 2, 3]
    monkeypatch.undo()
    monkeypatch.setattr(training.Initializer, "__call__", fresh_state)
    with pytest.raises(AssertionError, match="fresh training state"):  # a new run still builds one
        train_command.main(SMALL + ["--epochs", "1", "--out", str(tmp_path / "new")])


@pytest.mark.parametrize("damage", ["cut mid-line", "empty", "missing"])
def test_plot_reads_a_damaged_metrics_file_from_the_checkpoint_and_resume_rewrites_it(finished, tmp_path, capsys, damage):
    folder = tmp_path / "damaged"
    shutil.copytree(finished, folder)
    metrics = folder / run_folder.METRICS_FILE
    whole = metrics.read_bytes()
    if damage == "missing":
        metrics.unlink()
    else:
        metrics.write_bytes(whole[:-5] if damage == "cut mid-line" else b"")
    drawn = curves.load_run(folder)
    assert list(drawn.epochs) == [1, 2] and damage in drawn.note and f"--resume {folder}" in drawn.note
    np.testing.assert_array_equal(drawn.metrics["test_loss"], curves.load_run(finished).metrics["test_loss"])
    code, err, out = train(capsys, "--resume", str(folder), "--no-progress")  # what the note advises
    assert code == 0 and "done already" in out and len(err) == 1 and run_folder.METRICS_FILE in err[0], err
    assert metrics.read_bytes() == whole and curves.load_run(folder).note == ""


def test_resume_rewrites_damaged_parameters_from_the_checkpoint(finished, tmp_path, capsys):
    folder = tmp_path / "damaged"
    shutil.copytree(finished, folder)
    (folder / run_folder.PARAMS_FILE).write_bytes(b"not a zip")
    code, err, out = train(capsys, "--resume", str(folder), "--no-progress")
    assert code == 0 and "done already" in out and len(err) == 1 and run_folder.PARAMS_FILE in err[0], err
    assert (folder / run_folder.PARAMS_FILE).read_bytes() == (finished / run_folder.PARAMS_FILE).read_bytes()


def test_a_full_disk_gets_one_line_leaves_no_temporary_and_the_run_resumes(tmp_path, capsys, monkeypatch):
    run_dir = tmp_path / "full"
    real_fsync, calls = os.fsync, []

    def fsync_until_the_disk_is_full(descriptor):
        if str(run_dir) in os.readlink(f"/proc/self/fd/{descriptor}"):  # the run's files; the compile cache's fit
            calls.append(descriptor)
            if len(calls) > 5:  # config.json, startup.json, then epoch 1's checkpoint, params and metrics fit
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        real_fsync(descriptor)

    monkeypatch.setattr(os, "fsync", fsync_until_the_disk_is_full)
    code, err, _ = train(capsys, *SMALL, "--epochs", "3", "--checkpoint-every", "1", "--out", str(run_dir))
    assert code == 1 and len(err) == 1 and "No space left on device" in err[0] and "--resume" in err[0], err
    assert not [p.name for p in run_dir.iterdir() if p.name.endswith(".tmp")]
    assert epochs_in(run_dir) == [1]
    monkeypatch.setattr(os, "fsync", real_fsync)
    code, err, _ = train(capsys, "--resume", str(run_dir), "--no-progress")
    assert code == 0, err
    assert epochs_in(run_dir) == [1, 2, 3]


def test_running_out_of_device_memory_gets_one_line_and_the_run_resumes(tmp_path, capsys, monkeypatch):
    # What a GPU shared with other processes raises mid-training (XLA's allocator, not the memory plan).
    from stablebptt.cli import EpochProgress
    run_dir, real_on_epoch, real_on_compiled = tmp_path / "oom", EpochProgress.on_epoch, EpochProgress.on_compiled
    exhausted = jax.errors.JaxRuntimeError("RESOURCE_EXHAUSTED: Out of memory while trying to allocate 238662897624 bytes.")

    def allocation_fails_in_epoch_2(self, epoch, metrics):
        if epoch == 2:
            raise exhausted
        return real_on_epoch(self, epoch, metrics)

    def allocation_fails_as_training_begins(self, seconds):
        raise exhausted

    # Before its first checkpoint (as its first epoch begins) the line says that none is kept.
    monkeypatch.setattr(EpochProgress, "on_compiled", allocation_fails_as_training_begins)
    code, err, _ = train(capsys, *SMALL, "--epochs", "3", "--checkpoint-every", "1", "--out", str(tmp_path / "first"))
    assert code == 1 and len(err) == 1 and "has no checkpoint yet" in err[0] and "keeps its last" not in err[0], err
    monkeypatch.setattr(EpochProgress, "on_compiled", real_on_compiled)
    monkeypatch.setattr(EpochProgress, "on_epoch", allocation_fails_in_epoch_2)
    code, err, _ = train(capsys, *SMALL, "--epochs", "3", "--checkpoint-every", "1", "--out", str(run_dir))
    assert code == 1 and len(err) == 1 and "out of memory on cpu" in err[0] and "--resume" in err[0], err
    assert "keeps its last checkpoint" in err[0], err
    assert "start a new run with a smaller --batch (each update rolls 8 states per seed for 60 steps) or fewer --steps" \
        in err[0], err  # one seed, on one device: nothing else would hold fewer states
    monkeypatch.setattr(EpochProgress, "on_epoch", real_on_epoch)
    code, err, _ = train(capsys, "--resume", str(run_dir), "--no-progress")
    assert code == 0, err
    assert epochs_in(run_dir) == [1, 2, 3]


def test_atomic_write_leaves_the_old_file_when_the_disk_is_full(tmp_path, monkeypatch):
    target = tmp_path / "record.json"
    storage.write_json(target, {"kept": True})

    def full(descriptor):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "fsync", full)
    with pytest.raises(errors.StorageError, match="No space left"):
        storage.write_json(target, {"kept": False})
    assert json.loads(target.read_text()) == {"kept": True}
    assert [p.name for p in tmp_path.iterdir()] == ["record.json"]


@pytest.mark.parametrize("checkpoint_seconds, stop_after, saved", [(0.0, None, [3, 6, 7]), (3600.0, None, [7]),
                                                                  (0.0, 2, [2])])
def test_the_epoch_loop_saves_on_its_cadence_at_the_end_and_at_a_stop(checkpoint_seconds, stop_after, saved):
    """Every ``checkpoint_every`` epochs at least ``checkpoint_seconds`` apart, always at the end
    and at a stop; the rows returned and saved are every epoch's, in order, whatever the cadence."""
    epochs_run, saves = [], []

    def run_epoch(state):
        epochs_run.append(state + 1)
        return state + 1, {name: np.full(2, state + 1.0) for name in METRICS}

    status, epoch, state, rows, _ = fitting.fit(
        run_epoch, 0, 0, 7, np.zeros((0, len(COLUMNS))), np.arange(2),
        lambda epoch, state, rows: saves.append((epoch, rows[:, 0].tolist())), 3,
        should_stop=lambda: stop_after is not None and len(epochs_run) >= stop_after,
        checkpoint_seconds=checkpoint_seconds)
    assert [e for e, _ in saves] == saved and epoch == state == saved[-1]
    assert status == ("interrupted" if stop_after else "complete")
    every_epoch = [float(e) for e in range(1, epoch + 1) for _ in range(2)]
    assert rows[:, 0].tolist() == every_epoch and saves[-1][1] == every_epoch

class FakeClock:
    """``fitting``'s ``time``, its clock moved by hand: each test advances ``now`` as its epochs would."""

    def __init__(self, now: float):
        self.now = now

    def perf_counter(self):
        return self.now

    monotonic = perf_counter


@pytest.fixture
def exact_plans(monkeypatch):
    """The budget's plans without the seconds they leave spare (``BUDGET_MARGIN``, tested on its own): the
    arithmetic of the plans below is then exact."""
    monkeypatch.setattr(fitting, "BUDGET_MARGIN", 0.0)


def first_and_last_evaluated(clock: FakeClock, evaluated: list) -> Callable:
    """``fit``'s ``evaluate``: the first epoch and the last (``final``) evaluated, 3 s each on ``clock``,
    their epochs appended to ``evaluated``."""
    def evaluate(state, metrics, epoch, seconds, final):
        if epoch > 1 and not final:
            return metrics, 0.0
        clock.now += 3.0
        evaluated.append(epoch)
        return metrics, 3.0
    return evaluate


def paced_fit(clock: FakeClock, paces: list[float], budget: float) -> tuple:
    """``fit`` on ``clock`` from 0 s: epochs of 10 updates, each update of epoch k taking ``paces[k]`` s, the
    first epoch and the last evaluated (3 s each), a wall-clock budget of ``budget`` s. Returns the status, the
    last epoch, the updates each epoch was asked for (None: whole), the epochs evaluated and the clock at the end."""
    clock.now, pace, asked, evaluated = 0.0, iter(paces), [], []

    def run_epoch(state, updates=None):
        asked.append(updates)
        clock.now += next(pace) * (updates or 10)
        return state + 1, {name: np.full(1, state + 1.0) for name in METRICS}

    status, epoch, *_ = fitting.fit(run_epoch, 0, 0, 20, np.zeros((0, len(COLUMNS))), np.arange(1),
                                    lambda *saved: None, 1, evaluate=first_and_last_evaluated(clock, evaluated),
                                    out_of_time=lambda ahead: clock.now + ahead > budget, updates_per_epoch=10)
    return status, epoch, asked, evaluated, clock.now


@pytest.mark.parametrize("budget, last_epoch, ends_at", [(50.0, 3, 41.0), (60.0, 4, 51.0), (1.0, 1, 18.0)])
def test_a_budget_stops_the_epoch_loop_where_one_more_epoch_and_an_evaluation_would_overrun_it(
        monkeypatch, budget, last_epoch, ends_at):
    """Epochs of 10 s after 5 s of set-up, an evaluation of 3 s at the first epoch and the last: the loop
    goes on only while one more epoch and a last evaluation end within the budget; the first always trains."""
    clock, evaluated = FakeClock(5.0), []
    monkeypatch.setattr(fitting, "time", clock)

    def run_epoch(state):
        clock.now += 10.0
        return state + 1, {name: np.full(1, state + 1.0) for name in METRICS}

    evaluate = first_and_last_evaluated(clock, evaluated)

    status, epoch, *_ = fitting.fit(run_epoch, 0, 0, 20, np.zeros((0, len(COLUMNS))), np.arange(1),
                                    lambda *saved: None, 1, evaluate=evaluate,
                                    out_of_time=lambda ahead: clock.now + ahead > budget)
    assert (status, epoch, clock.now) == ("budget", last_epoch, ends_at) and evaluated[-1] == last_epoch
    # Resumed after epoch 4, whose evaluation took 3 s: the room for the last one is kept from its first epoch on.
    clock.now, evaluated[:] = 5.0, []
    before = np.zeros((1, len(COLUMNS)))
    before[0, COLUMNS.index("eval_seconds")] = 3.0
    status, epoch, *_ = fitting.fit(run_epoch, 4, 4, 20, before, np.arange(1), lambda *saved: None, 1,
                                    evaluate=lambda state, metrics, epoch, seconds, final: evaluate(state, metrics, 2, seconds, final),
                                    out_of_time=lambda ahead: clock.now + ahead > 46.0)
    assert (status, epoch, clock.now, evaluated) == ("budget", 7, 38.0, [2])


@pytest.mark.usefixtures("exact_plans")
def test_a_budgets_last_epoch_is_cut_to_the_updates_that_fit_and_counts_its_env_steps(monkeypatch):
    """Epochs of 10 updates of 1 s after 5 s of set-up, an evaluation of 3 s at the first epoch and the
    last, a budget of 50 s: after epoch 3 (38 s) a whole epoch and an evaluation would end at 51 s, so
    epoch 4 runs its first 9 updates and ends, evaluated, at 50 s; its rows count 9 updates' env steps."""
    clock, asked, evaluated = FakeClock(5.0), [], []
    monkeypatch.setattr(fitting, "time", clock)

    def run_epoch(state, updates=None):
        asked.append(updates)
        clock.now += 1.0 * (updates or 10)
        return state + 1, {name: np.full(1, state + 1.0) for name in METRICS}

    evaluate = first_and_last_evaluated(clock, evaluated)

    fit = lambda budget, start=0, rows=np.zeros((0, len(COLUMNS))): fitting.fit(  # noqa: E731
        run_epoch, start, start, 20, rows, np.arange(1), lambda *saved: None, 1, evaluate=evaluate,
        out_of_time=lambda ahead: clock.now + ahead > budget, steps_per_epoch=400, updates_per_epoch=10)
    status, epoch, _, rows, message = fit(50.0)
    assert (status, epoch, clock.now, asked, evaluated) == ("budget", 4, 50.0, [None, None, None, 9], [1, 4])
    assert message == "cut to its first 9 of 10 updates"
    assert rows[:, COLUMNS.index("env_steps")].tolist() == [400.0, 800.0, 1200.0, 1560.0]
    # A resume after it counts on from its rows; a budget with no room for one more update stops as before.
    clock.now, asked[:], evaluated[:] = 5.0, [], []
    status, epoch, _, rows, message = fit(16.5, 4, rows)
    assert (status, epoch, asked, message) == ("budget", 5, [None], "") and rows[-1, COLUMNS.index("env_steps")] == 1960.0


@pytest.mark.usefixtures("exact_plans")
def test_a_cut_plans_each_update_as_long_as_the_slowest_epoch_after_the_first_so_the_budget_holds(monkeypatch):
    """Epochs of 10 updates of 2 s (the first: the programs' first calls), then 1.2 s, then 1 s, an evaluation of
    3 s at the first epoch and the last, a budget of 58 s: after epoch 3 (45 s) a whole epoch at the last
    epoch's pace would end, evaluated, at 58 s, but at epoch 2's at 60 s. The cut plans with epoch 2's
    1.2 s (not the first's 2 s): 8 updates, which end within the budget at that pace too."""
    clock = FakeClock(0.0)
    monkeypatch.setattr(fitting, "time", clock)
    *ended, now = paced_fit(clock, [2.0, 1.2, 1.0, 1.2], 58.0)
    assert ended == ["budget", 4, [None, None, None, 8], [1, 4]]
    assert now == pytest.approx(57.6) and now <= 58.0


@pytest.mark.usefixtures("exact_plans")
def test_the_budget_forgets_a_stalled_epoch_three_epochs_on(monkeypatch):
    """Epochs of 10 updates of 1 s after a first of 2 s, but the second stalled at 5 s (a busy host), an
    evaluation of 3 s at the first epoch and the last. With a budget of 150 s the run trains every epoch
    whole to the ninth, the stall gone from the last three, and cuts the tenth to the 4 updates that end
    at 150 s; planned with every epoch's pace it cut the sixth to 8 and stopped at 114 s. With 140 s the
    stall is still among the last three after the fourth epoch: the fifth is cut to 8 (with the last two
    alone it would train whole)."""
    clock = FakeClock(0.0)
    monkeypatch.setattr(fitting, "time", clock)
    fit = lambda budget: paced_fit(clock, [2.0, 5.0] + [1.0] * 20, budget)  # noqa: E731
    assert fit(150.0) == ("budget", 10, [None] * 9 + [4], [1, 10], pytest.approx(150.0))
    assert fit(140.0) == ("budget", 5, [None] * 4 + [8], [1, 5], pytest.approx(104.0))


@pytest.mark.usefixtures("exact_plans")
def test_a_cut_leaves_room_for_what_an_epoch_spends_whatever_its_updates_and_for_a_cadences_evaluation(monkeypatch):
    """Epochs of 10 updates of 1 s and a refill of 5 s (``fixed_seconds``): a cut keeps the refill whole.
    And an evaluation due on the cadence after the epoch whose room was planned shrinks that room."""
    clock, asked = FakeClock(0.0), []
    monkeypatch.setattr(fitting, "time", clock)

    def run_epoch(state, updates=None):
        asked.append(updates)
        clock.now += 5.0 + 1.0 * (updates or 10)
        return state + 1, {**{name: np.full(1, state + 1.0) for name in METRICS}, "fixed_seconds": 5.0}

    def fit(budget, evaluated_at):
        def evaluate(state, metrics, epoch, seconds, final):
            if not (final or epoch in evaluated_at):
                return metrics, 0.0
            clock.now += 3.0
            return metrics, 3.0
        clock.now, asked[:] = 0.0, []
        status, epoch, *_ = fitting.fit(run_epoch, 0, 0, 20, np.zeros((0, len(COLUMNS))), np.arange(1),
                                        lambda *saved: None, 1, evaluate=evaluate, steps_per_epoch=10,
                                        out_of_time=lambda ahead: clock.now + ahead > budget, updates_per_epoch=10)
        return status, epoch, clock.now
    # After epoch 2 (33 s; 15 a whole epoch, 3 its evaluation): 5 of the refill and 6 updates fit in 47 s.
    assert fit(47.0, (1,)) == ("budget", 3, 47.0) and asked == [None, None, 6]
    # Evaluated after epoch 2 as well (36 s): 3 updates fit, not the 6 planned before that evaluation.
    assert fit(47.0, (1, 2)) == ("budget", 3, 47.0) and asked == [None, None, 3]


@pytest.mark.parametrize("margin", [0.0, fitting.BUDGET_MARGIN])
def test_the_budget_holds_where_its_last_epoch_runs_slower_saves_and_evaluates_longer(monkeypatch, margin):
    """Epochs of 10 updates of 1 s after 5 s of set-up, each saved in 1.5 s, an evaluation of 3 s at the first;
    the budget's last epoch, cut short, runs its updates 7% slower and its evaluation takes 5% longer (as a cut
    epoch of FingerTurnHard's did on one H200). Planned without the margin (room for the save alone), it ends
    past a budget of 50 s; with it, within the budget, and no more than an update and the margin before it."""
    clock = FakeClock(5.0)
    monkeypatch.setattr(fitting, "time", clock)
    monkeypatch.setattr(fitting, "BUDGET_MARGIN", margin)
    asked = []

    def run_epoch(state, updates=None):
        asked.append(updates)
        clock.now += (1.0 if updates is None else 1.07) * (updates or 10)
        return state + 1, {name: np.full(1, state + 1.0) for name in METRICS}

    def evaluate(state, metrics, epoch, seconds, final):
        took = 3.0 if epoch == 1 else 3.15 if final else 0.0
        clock.now += took
        return metrics, took

    def save(*saved):
        clock.now += 1.5

    status, epoch, *_ = fitting.fit(run_epoch, 0, 0, 20, np.zeros((0, len(COLUMNS))), np.arange(1), save, 1,
                                    evaluate=evaluate, out_of_time=lambda ahead: clock.now + ahead > 50.0,
                                    updates_per_epoch=10)
    assert status == "budget" and asked[:3] == [None] * 3 and 0 < asked[-1] < 10
    if margin:
        assert 50.0 - 1.07 - margin * 13.0 <= clock.now <= 50.0
    else:
        assert clock.now > 50.0


ARM = """<mujoco model="arm">
  <option timestep="0.02"/>
  <include file="arm_body.xml"/>
  <actuator><motor joint="shoulder" gear="2"/></actuator>
  <custom><numeric name="bptt_horizon" data="8"/></custom>
  <keyframe><key name="target" qpos="0.5"/></keyframe>
</mujoco>"""
ARM_BODY = """<mujoco><worldbody><body><joint name="shoulder" type="hinge" damping="0.1"/>
  <geom type="capsule" size="0.05" fromto="0 0 0 0 0 -0.5"/></body></worldbody></mujoco>"""


def test_a_run_remembers_its_model_resumes_and_renders_after_the_file_moved(tmp_path, capsys, monkeypatch):
    source = tmp_path / "lab"
    source.mkdir()
    (source / "arm.xml").write_text(ARM)
    (source / "arm_body.xml").write_text(ARM_BODY)
    monkeypatch.chdir(source)
    options = ["--train-size", "8", "--test-size", "8", "--no-progress"]
    code, err, _ = train(capsys, "--model", "arm.xml", "--epochs", "1", "--out", str(tmp_path / "run"), *options)
    assert code == 0, err
    run_dir = tmp_path / "run"
    assert (run_dir / model_store.MODEL_PACKED_FILE).is_file() and not (run_dir / model_store.MODEL_BINARY_FILE).exists()

    (source / "arm_body.xml").write_text(ARM_BODY)  # rewritten unchanged: still the same model
    (source / "arm.xml").write_text(ARM.replace('gear="2"', 'gear="3"'))
    before = snapshot(run_dir)
    code, err, _ = train(capsys, "--resume", str(run_dir), "--epochs", "2", "--no-progress")
    assert code == 2 and len(err) == 1 and "arm.xml changed since the run" in err[0], err
    assert snapshot(run_dir) == before

    shutil.move(source, tmp_path / "elsewhere")  # the file moved, and we work in another directory
    monkeypatch.chdir(tmp_path)
    code, err, _ = train(capsys, "--resume", str(run_dir), "--epochs", "2", "--no-progress")
    assert code == 0, err
    assert any("is gone: using the run's own copy" in line for line in err)
    assert epochs_in(run_dir) == [1, 2]
    assert json.loads((run_dir / run_folder.CONFIG_FILE).read_text())["resolved_task"]["name"] == "arm"

    render = subprocess.run([sys.executable, str(ROOT / "scripts" / "render.py"), str(run_dir), "--rollouts", "1",
                             "--no-video"], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert render.returncode == 0, render.stderr
    assert list(run_dir.glob("*.png"))

    # The run's compiled copy (.mjb.gz) is a model file like any other, and so is it unpacked (.mjb):
    # each trains, and is kept as the same compiled model.
    unpacked = tmp_path / "arm.mjb"
    unpacked.write_bytes(model_store.compiled_model(run_dir / model_store.MODEL_PACKED_FILE))
    for given, again in ((run_dir / model_store.MODEL_PACKED_FILE, tmp_path / "from-gz"), (unpacked, tmp_path / "from-mjb")):
        code, err, _ = train(capsys, "--model", str(given), "--epochs", "1", "--out", str(again), *options)
        assert code == 0, err
        assert (again / model_store.MODEL_PACKED_FILE).read_bytes() == (run_dir / model_store.MODEL_PACKED_FILE).read_bytes()
        assert not (again / model_store.MODEL_COPY_FILE).exists()


SKY = """<mujoco><asset><texture type="skybox" builtin="gradient" rgb1="0.4 0.6 0.8" rgb2="0 0 0" width="256"
  height="256"/></asset>""" + ARM.split("<mujoco model=\"arm\">", 1)[1]


def test_a_grid_keeps_one_compressed_model_for_all_its_cells_and_each_cell_reopens_it(tmp_path):
    (tmp_path / "arm.xml").write_text(SKY)
    (tmp_path / "arm_body.xml").write_text(ARM_BODY)
    binary = model_store.compiled_model(tmp_path / "arm.xml")  # the skybox: 256 x 256 x 6 faces x RGB
    grid = tmp_path / "grid"
    cells = [grid / f"cell-{k}" for k in range(3)]
    for cell in cells:
        cell.mkdir(parents=True)
        model_store.link_model(cell, tmp_path / "arm.xml", model_store.share_model(grid, tmp_path / "arm.xml"))
    shared = list((grid / model_store.SHARED_MODELS).iterdir())
    assert len(shared) == 1 and shared[0].stat().st_size < len(binary) / 10  # one copy, compressed
    record = {"resolved_task": {"model_file": str(tmp_path / "gone.xml")}}
    for cell in cells:
        assert sorted(p.name for p in cell.iterdir()) == [model_store.MODEL_LINK_FILE, model_store.MODEL_COPY_FILE]
        path, note = model_store.model_to_reopen(cell, record)  # the model file is gone: the grid's copy
        assert Path(path) == cell / ".." / model_store.SHARED_MODELS / shared[0].name and "is gone" in note
        assert model_store.compiled_model(path) == binary
    moved = tmp_path / "moved"
    shutil.move(grid, moved)  # the grid moves as a whole: its cells still find their model
    assert model_store.compiled_model(model_store.model_to_reopen(moved / "cell-0", record)[0]) == binary
    shutil.rmtree(moved / model_store.SHARED_MODELS)
    with pytest.raises(InputError, match="does not exist: the grid's models folder"):
        model_store.model_to_reopen(moved / "cell-0", record)


def test_a_run_folder_of_an_earlier_version_reopens_its_uncompressed_model(tmp_path):
    (tmp_path / "arm.xml").write_text(ARM)
    (tmp_path / "arm_body.xml").write_text(ARM_BODY)
    old = tmp_path / "old"
    old.mkdir()
    (old / model_store.MODEL_BINARY_FILE).write_bytes(model_store.compiled_model(tmp_path / "arm.xml"))
    path, _ = model_store.model_to_reopen(old, {"resolved_task": {"model_file": str(tmp_path / "gone.xml")}})
    assert path == str(old / model_store.MODEL_BINARY_FILE)
    assert model_store.load_compiled_model(path).nv == 1
    (old / "damaged.mjb.gz").write_bytes(b"not gzip")
    with pytest.raises(InputError, match="damaged"):
        model_store.load_compiled_model(old / "damaged.mjb.gz")


def test_the_library_trains_in_any_thread_and_its_runs_plot(tmp_path):
    config = TrainConfig(epochs=2, train_size=16, test_size=16, seeds=1)
    task = repulsion.make(repulsion.Config())
    record = {"task": "repulsion", "task_config": dataclasses.asdict(repulsion.Config()),
              "train": dataclasses.asdict(config)}
    outcome = {}

    def work():
        lock = run_folder.create_run(tmp_path / "threaded", record)
        trainer = make_trainer(task, config)
        outcome["value"] = epochs.train_epochs(trainer, config, tmp_path / "threaded", trainer.init(seed_array(config)),
                                             0, empty_rows(), np.asarray(seed_array(config)))
        lock.release()

    worker = threading.Thread(target=work)
    worker.start()
    worker.join()
    assert outcome["value"].status == "complete" and outcome["value"].epoch == 2
    from stablebptt.reports.plots import plot_run
    figure = plot_run(tmp_path / "threaded")
    assert Path(figure).is_file()


def test_a_compile_cache_that_cannot_be_written_is_one_line_and_left_off(tmp_path, monkeypatch):
    from stablebptt.runtime import COMPILE_CACHE_ENV, use_compile_cache
    before = jax.config.jax_compilation_cache_dir
    (tmp_path / "a-file").write_text("")
    monkeypatch.setenv(COMPILE_CACHE_ENV, str(tmp_path / "a-file" / "cache"))
    notes = []
    assert use_compile_cache(note=notes.append) is None
    assert len(notes) == 1 and "cannot write to the compile cache" in notes[0] and COMPILE_CACHE_ENV in notes[0], notes
    assert jax.config.jax_compilation_cache_dir == before


def test_a_damaged_compile_cache_entry_is_compiled_again_and_replaced_with_one_line(tmp_path, monkeypatch):
    import warnings

    import jax.numpy as jnp
    from jax._src import compilation_cache, lru_cache

    from stablebptt.runtime import COMPILE_CACHE_ENV, use_compile_cache
    session_cache, minimum = os.environ[COMPILE_CACHE_ENV], jax.config.jax_persistent_cache_min_compile_time_secs
    cache, notes = tmp_path / "cache", []
    program = lambda x: jnp.tanh(x) * 3.25 - 7.5  # noqa: E731

    def run_without_warnings():
        jax.clear_caches()  # not in memory: the next call looks in the cache directory
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            return jax.jit(program)(jnp.ones(5))

    os.environ[COMPILE_CACHE_ENV] = str(cache)
    try:
        compilation_cache.reset_cache()
        assert use_compile_cache(note=notes.append) == cache
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
        expected = run_without_warnings()
        entries = sorted(cache.glob("*-cache"))
        assert entries
        for entry in entries:
            entry.write_bytes(entry.read_bytes()[:7])  # as a process killed while JAX wrote it leaves one
        for _ in range(2):  # replaced, so the second run reads it without a word
            np.testing.assert_array_equal(run_without_warnings(), expected)
        assert len(notes) == 1 and "damaged entry" in notes[0] and "replaced" in notes[0], notes
        for entry in entries:
            compilation_cache.decompress_executable(entry.read_bytes())  # whole again

        def full_disk(self, key, value):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

        monkeypatch.setattr(lru_cache.LRUCache, "put", full_disk)
        program = lambda x: jnp.tanh(x) * 1.5 + 2.5  # noqa: E731 - another program, to be written
        for _ in range(2):
            np.testing.assert_allclose(run_without_warnings(), np.tanh(1.0) * 1.5 + 2.5, rtol=1e-6)
        assert len(notes) == 2 and "cannot write to the compile cache" in notes[1], notes
    finally:
        os.environ[COMPILE_CACHE_ENV] = session_cache
        jax.config.update("jax_persistent_cache_min_compile_time_secs", minimum)
        compilation_cache.reset_cache()
        use_compile_cache()


def test_the_out_of_memory_line_offers_what_holds_fewer_states_in_the_runs_own_numbers(monkeypatch, tmp_path):
    from stablebptt.commands.train import _less_memory
    from stablebptt.engine.config import TrainConfig
    from stablebptt.tasks.env import Config

    env_config = Config(env="HopperStand", steps=16, physics_step_residuals="stored")
    line = _less_memory(env_config, TrainConfig(seeds=5, batch=256), tmp_path, horizon=16)
    assert line == (f"free memory (another process may hold it) and continue with --resume {tmp_path}, or start a new "
                    "run with a smaller --batch (each update rolls 256 states per seed for 16 steps), fewer --steps, "
                    "--seed-batching map (its 5 seeds one after another) or --physics-step-residuals recomputed")
    assert "--seed-batching" not in _less_memory(env_config, TrainConfig(seeds=5, batch=256, seed_batching="map"),
                                                 tmp_path, horizon=16)
    # Where JAX sees more devices, the resume may spread the states over the most of them that split the batch evenly.
    monkeypatch.setattr(jax, "devices", lambda: ["gpu"] * 4)
    assert f"--resume {tmp_path} --devices 4 (its states split over 4 of the 4 devices JAX sees)" in _less_memory(
        env_config, TrainConfig(batch=256), tmp_path, horizon=16)
    assert f"--resume {tmp_path} --devices 2 (its states split over 2 of the 4 devices JAX sees)" in _less_memory(
        env_config, TrainConfig(batch=10), tmp_path, horizon=16)
    assert "--devices" not in _less_memory(env_config, TrainConfig(batch=256, devices=0), tmp_path, horizon=16)


@pytest.mark.parametrize("out, words", [("file", "file is a file: give a directory"),
                                        ("file/run", "cannot create {dir}/file/run: {dir}/file is a file"),
                                        ("locked/run", "cannot create {dir}/locked/run: {dir}/locked is not writable"),
                                        ("used", "used already exists and is not empty")])
def test_an_out_that_cannot_hold_the_run_is_refused_in_one_line_before_its_set_up(tmp_path, capsys, monkeypatch, out,
                                                                                  words):
    from stablebptt.runs import session
    (tmp_path / "file").write_text("kept")
    (tmp_path / "used").mkdir()
    (tmp_path / "used" / "notes.txt").write_text("kept")
    (tmp_path / "locked").mkdir()
    writable = os.access  # as root every folder is: one that is not, as os.access would say it
    monkeypatch.setattr(os, "access", lambda path, mode: Path(path) != tmp_path / "locked" and writable(path, mode))
    monkeypatch.setattr(session, "task_of", lambda *args, **kwargs: pytest.fail("set up before --out was checked"))
    code, err, _ = train(capsys, *SMALL, "--epochs", "1", "--out", str(tmp_path / out))
    assert code == 2 and len(err) == 1 and words.format(dir=tmp_path) in err[0], err
    assert (tmp_path / "file").read_text() == (tmp_path / "used" / "notes.txt").read_text() == "kept"
    assert not (tmp_path / "locked" / "run").exists()


def test_begin_from_python_names_an_argument_of_another_kind_before_it_builds_anything(tmp_path, monkeypatch):
    from stablebptt import tasks
    from stablebptt.engine.config import TrainConfig
    from stablebptt.runs import session
    module = tasks.load("repulsion")
    monkeypatch.setattr(session, "task_of", lambda *args, **kwargs: pytest.fail("built before its arguments were read"))
    train_config = TrainConfig(epochs=1)
    good = (module, "repulsion", module.Config(), train_config)
    for arguments, words in (
            ((module, "repulsion", {"steps": 16}, train_config),
             "begin's task_config is a stablebptt.tasks.repulsion.Config, got dict"),
            ((module, "repulsion", module.Config(), {"epochs": 1}),
             "begin's train_config is a stablebptt.TrainConfig, got dict"),
            (("repulsion", "repulsion", module.Config(), train_config), "begin's task_module is a task's module"),
            ((*good, 7), "begin's run_dir is a folder's path or None, got 7"),
            ((*good, None, None, 5), "begin's runs_root is a folder's path, got 5")):
        with pytest.raises(errors.InputError, match=words.replace("(", r"\(").replace(")", r"\)")):
            session.begin(*arguments, **({} if len(arguments) > 6 else {"runs_root": tmp_path}))
    assert not list(tmp_path.iterdir())


def test_begin_from_python_refuses_a_used_folder_in_the_words_of_a_run_folder(tmp_path, monkeypatch):
    from stablebptt import tasks
    from stablebptt.engine.config import TrainConfig
    from stablebptt.runs import session
    module = tasks.load("repulsion")
    monkeypatch.setattr(session, "task_of", lambda *args, **kwargs: pytest.fail("built before its folder was checked"))
    (tmp_path / "notes.txt").write_text("kept")
    with pytest.raises(errors.InputError) as refused:
        session.begin(module, "repulsion", module.Config(), TrainConfig(epochs=1), tmp_path)
    # A Python caller gave no --out: the refusal says what to choose, the command's option beside it.
    assert f"{tmp_path} already exists and is not empty: choose another run folder (--out)" in str(refused.value)
    assert (tmp_path / "notes.txt").read_text() == "kept"
