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

from conftest import ROOT
from stablebptt.cli import INTERRUPTED

TRAIN = ["scripts/train.py", "--poles", "1", "--steps", "10", "--epochs", "3", "--train-size", "16",
         "--test-size", "16", "--batch", "8", "--no-progress"]
# Seconds after the start: the imports, the scene and the tracing, the compiles, training or its end.
DELAYS = (0.3, 1.5, 4.0, 8.0, 14.0)


def no_frame_in_the_repository(traceback: str) -> bool:
    """Whether none of a traceback's frames lies in the repository: no code of the command raised it."""
    return not any(frame.startswith(str(ROOT)) for frame in re.findall(r'^  File "([^"]+)"', traceback, flags=re.MULTILINE))


def interrupted_python_itself(stderr: str) -> bool:
    """A Ctrl-C that came while the interpreter was still starting (its own site imports, slow on a
    loaded machine) is Python's KeyboardInterrupt from before the program's first line: no frame of
    its traceback lies in the repository. The command cannot act before it runs, so the test does not
    count it against the command."""
    return stderr.rstrip().endswith("KeyboardInterrupt") and no_frame_in_the_repository(stderr)


def after_the_command_stopped(stderr: str) -> str:
    """The command's own output: with exit 130 its last line is INTERRUPTED, written just before
    os._exit; a traceback after it with no frame in the repository (seen on a loaded machine: a
    BrokenPipeError at "<string>") came from no code of the command and is left out."""
    head, found, tail = stderr.partition(INTERRUPTED)
    if found and tail.strip().startswith("Traceback") and no_frame_in_the_repository(tail):
        return head + found + "\n"
    return stderr


def test_ctrl_c_at_any_moment_is_one_or_two_lines_and_leaves_a_folder_that_resumes(tmp_path):
    processes = {}
    for index, delay in enumerate(DELAYS):
        # An empty compile cache each: every phase, compiling included, takes its full time.
        env = {**os.environ, "STABLEBPTT_COMPILE_CACHE": str(tmp_path / f"cache{index}")}
        command = [sys.executable, *TRAIN, "--out", str(tmp_path / f"run{index}")]
        if index == 1:  # the installed command's entry point
            command = [sys.executable, "-m", "stablebptt.commands.main", "train", *TRAIN[1:],
                       "--out", str(tmp_path / f"run{index}")]
        processes[delay] = subprocess.Popen(command, cwd=ROOT, env=env, stdin=subprocess.DEVNULL,
                                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    started = time.monotonic()
    for delay, process in sorted(processes.items()):
        time.sleep(max(0.0, started + delay - time.monotonic()))
        if process.poll() is None:
            process.send_signal(signal.SIGINT)
    outcomes = {delay: (process.wait(timeout=600), process.stderr.read()) for delay, process in processes.items()}
    for delay, (code, stderr) in outcomes.items():
        lines = [line for line in stderr.splitlines() if line.strip()]
        if code == 1 and interrupted_python_itself(stderr):  # Python's exit status for it
            continue
        assert code in (0, 130, -signal.SIGINT), f"{delay} s: exit {code}: {stderr}"
        if code == 130:
            stderr = after_the_command_stopped(stderr)
            lines = [line for line in stderr.splitlines() if line.strip()]
        assert "Traceback" not in stderr and len(lines) <= 2, f"{delay} s: {stderr}"
    stopped = [index for index, delay in enumerate(DELAYS) if outcomes[delay][0] in (130, -signal.SIGINT)]
    assert stopped, "no command was still running when its Ctrl-C came"
    for index in stopped:
        folder = tmp_path / f"run{index}"
        assert not folder.exists() or (folder / "config.json").is_file(), os.listdir(folder)
    resumable = [index for index in stopped if (tmp_path / f"run{index}" / "config.json").is_file()]
    if resumable:  # the latest one: a claimed folder, or one that trained a little
        resumed = subprocess.run([sys.executable, "scripts/train.py", "--resume", str(tmp_path / f"run{resumable[-1]}"),
                                  "--no-progress"], cwd=ROOT, capture_output=True, text=True, timeout=600,
                                 env={**os.environ, "STABLEBPTT_COMPILE_CACHE": str(tmp_path / "cache-resume")})
        assert resumed.returncode == 0, resumed.stderr


def test_the_same_stop_request_arriving_after_the_run_stopped_is_ignored_and_a_later_one_is_not():
    # timeout and batch schedulers signal the process, then its group: on a busy machine the second copy
    # may arrive after the training loop has stopped and put the handlers back.
    script = """if True:
        import os, signal, sys, time
        from stablebptt.cli import REPEAT_SECONDS, stop_on_signals
        with stop_on_signals() as should_stop:
            os.kill(os.getpid(), signal.SIGTERM)
            while not should_stop():
                time.sleep(0.01)
        os.kill(os.getpid(), signal.SIGTERM)  # the same request again, after the block: ignored
        time.sleep(0.1)
        print("survived", flush=True)
        time.sleep(REPEAT_SECONDS)
        os.kill(os.getpid(), signal.SIGTERM)  # a new request, later: the default action ends the process
        time.sleep(5)
        print("not reached", flush=True)
    """
    done = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=120,
                          env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert done.stdout.split() == ["survived"] and done.returncode == -signal.SIGTERM, (done.stdout, done.stderr)
