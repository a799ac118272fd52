"""A command line whose training loop's first compile waits for the test: a signal sent then provably
arrives while the epoch program compiles, on a machine of any speed (no test bets on how long the
set-up takes). With --at-checkpoint it waits again once its first checkpoint is written: a signal then
arrives after an epoch is saved and before the next begins, however fast the epochs run.

    python tests/held_compile.py FOLDER scripts/train.py ARGS...
    python tests/held_compile.py FOLDER -m stablebptt.commands.main train ARGS...
    python tests/held_compile.py FOLDER --at-checkpoint scripts/train.py ARGS...

runs ``python scripts/train.py ARGS...`` (or ``python -m ...``) as it is, its Ctrl-C handling included,
except that it writes FOLDER/started as the command starts loading, and the first
``jax.stages.Lowered.compile`` inside the training loop's signal block (``cli.stop_on_signals``, which
holds SIGTERM) writes FOLDER/compiling and then waits for FOLDER/go (``release``) before it compiles.
JAX's own layer is patched, not the library's, so the hold stays where the training loop is rebuilt.
With --at-checkpoint, the first ``os.replace`` onto the run's checkpoint file (every file is written whole
and then renamed) writes FOLDER/checkpointed once it is done and waits for FOLDER/go-on (``release_checkpoint``).
A test waits for those files (``wait_for``) and for the line that says the run took its signal
(``stderr_through``); its sleeps are polling intervals under a deadline, never a guess at a duration.
"""
from __future__ import annotations

import signal

# First, as scripts/train.py does: a Ctrl-C while the command loads ends it quietly (`python -m
# stablebptt.commands.main` raises KeyboardInterrupt until its main starts; no test signals it then).
if __name__ == "__main__":
    signal.signal(signal.SIGINT, signal.SIG_DFL)

import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

STARTED = "started"  # written as the command starts loading (its imports)
COMPILING = "compiling"  # written as the epoch's compile starts; it waits for GO
GO = "go"
CHECKPOINTED = "checkpointed"  # written once the first checkpoint is in place (--at-checkpoint); it waits for GO_ON
GO_ON = "go-on"
WAIT_SECONDS = 300  # then it compiles anyway: a test that never releases it fails, it does not hang


def held_command(folder: Path, *argv: str, at_checkpoint: bool = False) -> list[str]:
    """The command line that runs ``python argv`` (a script or ``-m module``, and its arguments) with its
    first training compile held in ``folder``, and its first checkpoint too where ``at_checkpoint``."""
    return [sys.executable, __file__, str(folder), *(["--at-checkpoint"] if at_checkpoint else []), *map(str, argv)]


def wait_for(path: Path, process, seconds: float = 300) -> None:
    """Return once ``path`` exists; fail, with what ``process`` wrote, if it ends or ``seconds`` pass first."""
    deadline = time.monotonic() + seconds
    while not path.exists() and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)  # a polling interval
    assert path.exists(), process.communicate(timeout=60)


def stderr_through(process, words: str) -> str:
    """What ``process`` wrote on stderr up to its first line holding ``words`` (all of it, should it end first)."""
    lines = []
    for line in iter(process.stderr.readline, ""):
        lines.append(line)
        if words in line:
            break
    return "".join(lines)


def release(folder: Path) -> None:
    """Let the held compile go on."""
    (Path(folder) / GO).write_text("")


def release_checkpoint(folder: Path) -> None:
    """Let the run go on past its first checkpoint."""
    (Path(folder) / GO_ON).write_text("")


def _wait_for(path: Path) -> None:
    deadline = time.monotonic() + WAIT_SECONDS
    while not path.exists() and time.monotonic() < deadline:
        time.sleep(0.01)  # a polling interval: the test says when


def _hold_the_first_training_compile(folder: Path) -> None:
    import jax.stages
    original = jax.stages.Lowered.compile
    held = []

    def compile(self, *args, **kwargs):
        # A Python handler of SIGTERM: inside stop_on_signals, where a signal asks to stop after the epoch.
        if not held and callable(signal.getsignal(signal.SIGTERM)):
            held.append(True)
            (folder / COMPILING).write_text("")
            _wait_for(folder / GO)
        return original(self, *args, **kwargs)

    jax.stages.Lowered.compile = compile


def _hold_after_the_first_checkpoint(folder: Path) -> None:
    import os

    from stablebptt.runs.run_folder import CHECKPOINT_FILE
    original = os.replace
    held = []

    def replace(source, destination, *args, **kwargs):
        original(source, destination, *args, **kwargs)
        if not held and Path(destination).name == CHECKPOINT_FILE:
            held.append(True)
            (folder / CHECKPOINTED).write_text("")
            _wait_for(folder / GO_ON)

    os.replace = replace


if __name__ == "__main__":
    import runpy
    folder, argv = Path(sys.argv[1]), sys.argv[2:]
    folder.mkdir(parents=True, exist_ok=True)
    _hold_the_first_training_compile(folder)
    if argv[0] == "--at-checkpoint":
        argv = argv[1:]
        _hold_after_the_first_checkpoint(folder)
    (folder / STARTED).write_text("")
    if argv[0] == "-m":  # as `python -m module` has it
        sys.argv, sys.path[0] = argv[1:], str(Path.cwd())
        runpy.run_module(argv[1], run_name="__main__", alter_sys=True)
    else:  # as `python script` has it
        sys.argv, sys.path[0] = argv, str(Path(argv[0]).resolve().parent)
        runpy.run_path(argv[0], run_name="__main__")
