"""Ctrl-C at any moment of a command, from its first import to its last epoch: at most two lines on
stderr, no traceback, and nothing half-made (a run folder that exists continues with --resume).
While the command loads, Ctrl-C ends it as the signal does by default (exit status -SIGINT, no line)."""
from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from conftest import ROOT
from held_compile import (CHECKPOINTED, COMPILING, STARTED, held_command, release, release_checkpoint,
                          stderr_through, wait_for)
from stablebptt.cli import STOP_SIGNALS, stopped_by

TRAIN = ["scripts/train.py", "--poles", "1", "--steps", "10", "--epochs", "3", "--train-size", "16",
         "--test-size", "16", "--batch", "8", "--no-progress"]
# Moments of a run, each one observed rather than guessed from the seconds since its start (the compile and
# the first checkpoint wait for the test: tests/held_compile.py): the imports, the claimed folder (the scene
# built and traced), the compile, its first epoch saved.
MOMENTS = ("loading", "claimed", "compiling", "checkpointed")
INTERRUPTED = stopped_by(signal.SIGINT)  # the line of a command Ctrl-C stopped at once


def no_frame_in_the_repository(traceback: str) -> bool:
    """Whether none of a traceback's frames lies in the repository: no code of the command raised it."""
    return not any(frame.startswith(str(ROOT)) for frame in re.findall(r'^  File "([^"]+)"', traceback, flags=re.MULTILINE))


def after_the_command_stopped(stderr: str) -> str:
    """The command's own output: with exit 130 its last line is INTERRUPTED, written just before
    os._exit; a traceback after it with no frame in the repository (seen on a loaded machine: a
    BrokenPipeError at "<string>") came from no code of the command and is left out."""
    head, found, tail = stderr.partition(INTERRUPTED)
    if found and tail.strip().startswith("Traceback") and no_frame_in_the_repository(tail):
        return head + found + "\n"
    return stderr


def test_ctrl_c_at_any_moment_is_one_or_two_lines_and_leaves_a_folder_that_resumes(tmp_path):
    processes, seen = {}, dict.fromkeys(MOMENTS, "")
    for index, moment in enumerate(MOMENTS):
        # An empty compile cache each: every phase, compiling included, takes its full time.
        env = {**os.environ, "STABLEBPTT_COMPILE_CACHE": str(tmp_path / f"cache{index}")}
        argv = [*TRAIN, "--out", str(tmp_path / f"run{index}")]
        if index == 1:  # the installed command's entry point
            argv = ["-m", "stablebptt.commands.main", "train", *argv[1:]]
        held = held_command(tmp_path / f"hold{index}", *argv, at_checkpoint=moment == "checkpointed")
        processes[moment] = subprocess.Popen(held, cwd=ROOT, env=env,
                                             stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                             text=True)
    for index, (moment, process) in enumerate(processes.items()):
        hold, run = tmp_path / f"hold{index}", tmp_path / f"run{index}"
        if moment == "checkpointed":  # compiled at once, then Ctrl-C once its first epoch is saved, held there
            wait_for(hold / COMPILING, process)
            release(hold)
        wait_for({"loading": hold / STARTED, "claimed": run / "config.json", "compiling": hold / COMPILING,
                  "checkpointed": hold / CHECKPOINTED}[moment], process)
        process.send_signal(signal.SIGINT)
        if moment in ("compiling", "checkpointed"):  # the run takes it before it goes on
            seen[moment] = stderr_through(process, "SIGINT: stopping")
        release(hold)
        release_checkpoint(hold)
    outcomes = {moment: (process.wait(timeout=600), seen[moment] + process.stderr.read())
                for moment, process in processes.items()}
    for moment, (code, stderr) in outcomes.items():
        assert code in (0, 130, -signal.SIGINT), f"{moment}: exit {code}: {stderr}"
        if code == 130:
            stderr = after_the_command_stopped(stderr)
        lines = [line for line in stderr.splitlines() if line.strip()]
        assert "Traceback" not in stderr and len(lines) <= 2, f"{moment}: {stderr}"
    codes = {moment: code for moment, (code, _) in outcomes.items()}
    assert codes["loading"] in (130, -signal.SIGINT), codes
    assert codes["claimed"] == codes["compiling"] == codes["checkpointed"] == 130, codes
    for index, moment in enumerate(MOMENTS):
        folder = tmp_path / f"run{index}"
        assert not folder.exists() or (folder / "config.json").is_file(), os.listdir(folder)
    with np.load(tmp_path / f"run{MOMENTS.index('checkpointed')}" / "checkpoint.npz") as checkpoint:
        assert int(checkpoint["epoch"]) == 1  # stopped after the epoch it was in, of 3
    # Both kinds of folder a stop leaves resume: a claimed one (its config.json alone) and one that trained a little.
    resumes = [subprocess.Popen([sys.executable, "scripts/train.py", "--resume", str(tmp_path / f"run{index}"),
                                 "--no-progress"], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                env={**os.environ, "STABLEBPTT_COMPILE_CACHE": str(tmp_path / f"cache-resume{index}")})
               for index in (MOMENTS.index("claimed"), MOMENTS.index("checkpointed"))]
    for process in resumes:
        _, stderr = process.communicate(timeout=600)
        assert process.returncode == 0, stderr


def test_the_same_stop_request_arriving_after_the_run_stopped_is_ignored_and_a_later_one_is_not():
    # timeout and batch schedulers signal the process, then its group: on a busy machine the second copy
    # may arrive after the training loop has stopped and put the handlers back.
    # raise_signal runs the signal's handler (or its default action) before it returns: no wait for it.
    script = """if True:
        import signal, time
        from stablebptt.cli import REPEAT_SECONDS, stop_on_signals
        with stop_on_signals() as should_stop:
            signal.raise_signal(signal.SIGTERM)
            assert should_stop()
        signal.raise_signal(signal.SIGTERM)  # the same request again, after the block: ignored
        print("survived", flush=True)
        time.sleep(REPEAT_SECONDS)  # the window of the same request, gone by
        signal.raise_signal(signal.SIGTERM)  # a new request, later: the default action ends the process
        print("not reached", flush=True)
    """
    done = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=120,
                          env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert done.stdout.split() == ["survived"] and done.returncode == -signal.SIGTERM, (done.stdout, done.stderr)


# A stop signal an instant before a training loop sets its own handler: the process-wide handler has taken it.
SIGNAL_BEFORE_THE_LOOP = """
import os, signal, sys
from stablebptt.cli import stop_at_once_on_signals, stop_on_signals
stop_at_once_on_signals()
os.kill(os.getpid(), int(sys.argv[1]))
with stop_on_signals() as should_stop:
    print("went on; stop asked:", should_stop())
"""


@pytest.mark.parametrize("signum", STOP_SIGNALS)
def test_a_stop_signal_just_before_a_training_loop_ends_the_command_and_is_not_lost(signum):
    """Python's handler runs in the main thread just after the signal, before the loop begins; the watcher
    thread, woken by the same signal, may look only once the loop's handler is set and leave the signal to
    it. The handler ends the command itself: one line and the shell's exit code for the signal (130 for
    Ctrl-C), never training on."""
    done = subprocess.run([sys.executable, "-c", SIGNAL_BEFORE_THE_LOOP, str(int(signum))], cwd=ROOT,
                          capture_output=True, text=True, timeout=120)
    assert (done.returncode, done.stdout, done.stderr) == (128 + signum, "", f"{stopped_by(signum)}\n")
    said = {signal.SIGINT: "Ctrl-C", signal.SIGTERM: "SIGTERM", signal.SIGHUP: "SIGHUP"}[signum]  # as a user knows it
    assert done.stderr.startswith(f"stopped by {said}: files are written whole")


# The signal's line cannot be written (a closed terminal, a pipe whose reader ended): the command ends all the same.
STDERR_GONE = """
import os, signal
from stablebptt.cli import stop_at_once_on_signals
stop_at_once_on_signals()
os.close(2)
os.kill(os.getpid(), signal.SIGTERM)
print("went on", flush=True)
"""


def test_a_stop_signal_ends_the_command_where_its_line_cannot_be_written():
    done = subprocess.run([sys.executable, "-c", STDERR_GONE], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert (done.returncode, done.stdout) == (128 + signal.SIGTERM, "")


# A command started under nohup, which ignores SIGHUP so that the command outlives its terminal.
UNDER_NOHUP = """
import signal
from stablebptt.cli import stop_at_once_on_signals, stop_on_signals
stop_at_once_on_signals()
signal.raise_signal(signal.SIGHUP)
with stop_on_signals() as should_stop:
    signal.raise_signal(signal.SIGHUP)
    print("stop asked:", should_stop())
"""


def test_a_signal_the_command_was_started_ignoring_stays_ignored():
    done = subprocess.run([sys.executable, "-c", UNDER_NOHUP], cwd=ROOT, capture_output=True, text=True,
                          timeout=120, preexec_fn=lambda: signal.signal(signal.SIGHUP, signal.SIG_IGN))
    assert (done.returncode, done.stdout, done.stderr) == (0, "stop asked: False\n", "")


# A second Ctrl-C while the first one ends the process (its line being written): the lock is taken.
CTRL_C_WHILE_ENDING = """
import os, signal
from stablebptt import cli
cli.stop_at_once_on_signals()
cli._ENDING.acquire()
os.kill(os.getpid(), signal.SIGINT)
print("returned", end="")
"""


def test_a_second_ctrl_c_while_the_first_ends_the_command_does_not_hang_it():
    """Timeout signals the process, then its group; a signal that interrupts the first one's write runs the
    handler within itself. Its second run finds the process ending and returns: waiting for the lock,
    which its own thread holds, it would wait forever."""
    done = subprocess.run([sys.executable, "-c", CTRL_C_WHILE_ENDING], cwd=ROOT, capture_output=True, text=True,
                          timeout=120)
    assert (done.returncode, done.stdout, done.stderr) == (0, "returned", "")


@pytest.mark.parametrize("signum", (signal.SIGINT, signal.SIGTERM))
def test_a_stop_signal_to_bench_ends_the_run_it_times_in_a_session_of_its_own(tmp_path, signum):
    # The timed run is in a session of its own (a timeout stops it whole), where the terminal's Ctrl-C or a
    # SIGTERM to the bench does not reach it: the bench's stop at once ends it first. Here the run is a script
    # that says it has begun, then waits.
    waiter, began = tmp_path / "waiter.py", tmp_path / "began"
    waiter.write_text(f"import os, pathlib, time\npathlib.Path({str(began)!r}).write_text(str(os.getpid()))\n"
                      "time.sleep(300)\n")
    script = (f"from pathlib import Path\nfrom stablebptt import cli\nfrom stablebptt.commands import bench\n"
              f"cli.stop_at_once_on_signals()\nbench._time_run([{str(waiter)!r}], Path({str(tmp_path)!r}), 300)\n")
    process = subprocess.Popen([sys.executable, "-c", script], cwd=ROOT, stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True)
    wait_for(began, process)
    child = int(began.read_text())
    process.send_signal(signum)
    assert process.wait(timeout=60) == 128 + signum
    deadline = time.monotonic() + 60
    try:
        while running(child) and time.monotonic() < deadline:
            time.sleep(0.05)  # a polling interval
        assert not running(child)
    finally:
        if running(child):  # left by a failure: not by the test run
            os.kill(child, signal.SIGKILL)


def running(pid: int) -> bool:
    """Whether process ``pid`` is there and not a zombie (its parent gone, it may wait to be reaped)."""
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False
