"""Command-line plumbing shared by the scripts: options built from typed dataclasses.

Every option is a dataclass field with a ``help`` in its metadata, so the
dataclass is the one source of truth. Errors are one line on stderr and exit
code 2, never a traceback.
"""
from __future__ import annotations

import argparse
import contextlib
import dataclasses
import importlib
import os
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any, Callable, Iterator, NoReturn

_TYPES = {"int": int, "float": float, "str": str, "bool": bool}  # how an option's text is read, by its field's kind


def fail(message: str, code: int = 2) -> NoReturn:
    """Print one line on stderr and exit (2 = bad input); config fields are named as their options."""
    from stablebptt.errors import as_options
    # One line whatever the message holds: a user's module or factory may raise with line breaks in its words.
    one_line = " / ".join(part.strip() for part in str(message).splitlines() if part.strip())
    print(f"error: {as_options(one_line)}", file=sys.stderr)
    leave(code)


# Set where this process is a command's (``stop_at_once_on_signals``): only there may it end without unwinding.
_COMMAND_PROCESS = threading.Event()


def leave(code: int) -> NoReturn:
    """Exit with ``code``. In a command's process where work still runs in another thread (a compile
    begun beside, which XLA cannot stop, and which a plain exit waits for: a run refused on the 2-core
    CPU waited 31 s for its reward check's compile to end), the process ends at once without
    unwinding, its output flushed first: every file is written atomically and run folders resume from
    any state, so nothing is lost. A library user's process exits as Python does (``SystemExit``)."""
    working = [thread for thread in threading.enumerate()
               if thread.is_alive() and not thread.daemon and thread is not threading.main_thread()]
    if working and _COMMAND_PROCESS.is_set() and threading.current_thread() is threading.main_thread():
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    sys.exit(code)


class Parser(argparse.ArgumentParser):
    """argparse whose errors are one line on stderr, exit code 2."""

    def error(self, message: str) -> NoReturn:
        fail(f"{message} (see --help)")


def path_named(text: str) -> Path:
    """A path given on the command line (argparse's ``type``): an empty one, which ``Path`` reads as the
    folder the command runs in, is refused rather than written into."""
    if not text.strip():
        raise argparse.ArgumentTypeError("an empty path: give a file's or folder's name")
    return Path(text)


def option_name(field_name: str) -> str:
    return "--" + field_name.replace("_", "-")


def typed_option(field_name: str, value: Any) -> str:
    """A field's value as its option is typed: ``--critic``, ``--no-critic``, ``--discount 0.99``."""
    flag = option_name(field_name)
    if isinstance(value, bool):
        return flag if value else f"--no-{flag[2:]}"
    return f"{flag} {value:g}" if isinstance(value, float) else f"{flag} {value}"


def add_options(parser: argparse.ArgumentParser, config_class: type, title: str, present: set[str] = frozenset(),
                defaults: dict[str, str] | None = None) -> list[str]:
    """Add one option per dataclass field; unset options stay absent from the namespace.

    Fields named in ``present`` already have an option (another config shares
    the name): they are listed in the result but not added twice. ``defaults``
    says, per field, where the command defaults to another value than the field's
    (``"--task env: norm"``): the help names it beside the field's default.
    """
    from stablebptt.errors import field_kind
    group = parser.add_argument_group(title)
    names = []
    for field in dataclasses.fields(config_class):
        if field.name in present:
            names.append(field.name)
            continue
        kind = _TYPES[field_kind(field)]
        otherwise = f"; {defaults[field.name]}" if defaults and field.name in defaults else ""
        help_text = f"{field.metadata.get('help', '')} (default: {field.default}{otherwise})"
        common = dict(dest=field.name, help=help_text, default=argparse.SUPPRESS)
        if kind is bool:
            group.add_argument(option_name(field.name), action=argparse.BooleanOptionalAction, **common)
        else:
            group.add_argument(option_name(field.name), type=kind, choices=field.metadata.get("choices"),
                               metavar=field.name.upper(), **common)
        names.append(field.name)
    return names


def parse_config(config_class: type, argv: list[str], description: str, title: str):
    """Parse ``argv`` into ``config_class`` for a script whose options are that one dataclass.

    Unknown options, bad types and the dataclass's own validation errors all
    end as one line on stderr with exit code 2.
    """
    return parse_config_given(config_class, argv, description, title)[0]


def parse_config_given(config_class: type, argv: list[str], description: str, title: str) -> tuple[Any, set[str]]:
    """``parse_config``'s config, and the fields ``argv`` set (a default value typed included)."""
    from stablebptt.errors import InputError
    parser = Parser(description=description, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_options(parser, config_class, title)
    given = vars(parser.parse_args(argv))  # unset options stay absent (add_options)
    try:
        return build(config_class, given), set(given)
    except InputError as error:
        fail(str(error))


def build(config_class: type, values: dict[str, Any], source: str = ""):
    """The dataclass from the given values (unknown keys ignored); validation errors propagate.

    A value of the wrong type (read from a file: ``source`` names it) is an InputError.
    """
    from stablebptt.errors import InputError, wrong_kind
    fields = {f.name: f for f in dataclasses.fields(config_class)}
    for name, value in values.items():  # before the config's own checks, which may compare it with a number
        if name in fields and (refusal := wrong_kind(fields[name], value, name)):
            raise InputError(f"{source}: {refusal}" if source else refusal)
    return config_class(**{k: v for k, v in values.items() if k in fields})


@contextlib.contextmanager
def one_line_errors(prefix: str = "") -> Iterator[None]:
    """Within the block, bad input (InputError) ends the command with one line and exit code 2, a
    file that cannot be written (StorageError: a full disk, permissions) with one line and exit code 1."""
    from stablebptt.errors import InputError, StorageError
    try:
        yield
    except InputError as error:
        fail(f"{prefix}{error}")
    except StorageError as error:
        fail(f"{prefix}{error.strerror}", code=1)


def out_of_memory(error: BaseException) -> str | None:
    """The start of the one line for a device allocation failure (XLA's RESOURCE_EXHAUSTED), or None.

    It happens after the memory plan's estimate where other processes hold the device's memory.
    """
    import jax
    if not (isinstance(error, jax.errors.JaxRuntimeError) and "RESOURCE_EXHAUSTED" in str(error)):
        return None
    device = jax.devices()[0]
    return f"out of memory on {device.platform} ({device.device_kind}) while training"


# A signal of the kind that asked to stop, again within this many seconds, is the same request:
# GNU timeout sends SIGTERM to the command and then to its whole process group, Slurm to every
# process of the step. Only a later one (a user's second Ctrl-C) stops at once.
REPEAT_SECONDS = 1.0
STOP_SIGNALS = tuple(getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name))


def stopped_by(signum: int) -> str:
    """The one line of a command that ``signum`` stopped at once."""
    by = "Ctrl-C" if signum == signal.SIGINT else signal.Signals(signum).name
    return (f"stopped by {by}: files are written whole, nothing is half-made; a run folder it claimed "
            "(config.json alone, or a checkpoint) continues with --resume")


def taken_signals() -> tuple[int, ...]:
    """The stop signals a command takes: Ctrl-C always (a shell starts a background job ignoring it, and the
    scripts take it back: a user's kill -INT still stops the run), SIGTERM and SIGHUP unless this process was
    started ignoring them (``nohup`` ignores SIGHUP for the command to outlive its terminal)."""
    return tuple(signum for signum in STOP_SIGNALS
                 if signum == signal.SIGINT or signal.getsignal(signum) is not signal.SIG_IGN)


_ENDING = threading.Lock()  # taken by the first of the handler and the watcher to end the process: one line


_ENDED_WITH_THE_COMMAND: list[Callable[[], None]] = []  # what a stop at once ends first (ended_with_the_command)


@contextlib.contextmanager
def ended_with_the_command(end: Callable[[], None]) -> Iterator[None]:
    """Within the block, a stop at once (a stop signal outside a training loop) calls ``end`` before the process
    exits: a child process in a session of its own, which the terminal's Ctrl-C or a signal to this process does
    not reach, would run on. ``end`` must return at once (a second signal waits for it)."""
    _ENDED_WITH_THE_COMMAND.append(end)
    if _ENDING.locked():  # the stop began before this was added: it may have passed the list
        end()
    try:
        yield
    finally:
        _ENDED_WITH_THE_COMMAND.remove(end)


def _stop_at_once(signum, frame) -> None:
    """A stop signal outside a training loop, in the main thread (Python's handler) or the watcher's. The
    handler ends the process itself: the watcher may look only once a training loop's handler is set, and
    leave the signal to it. A second signal meanwhile returns (a handler run within itself would wait forever)."""
    if not _ENDING.acquire(blocking=False):
        return
    for end in list(_ENDED_WITH_THE_COMMAND):
        with contextlib.suppress(Exception):  # a child that has ended already: nothing to end
            end()
    try:  # stderr may be gone (a closed terminal's SIGHUP, a pipe whose reader ended): the process ends all the same
        os.write(2, f"{stopped_by(signum)}\n".encode())
    finally:
        os._exit(128 + signum)  # the shell's code for a process the signal ended: 130 for Ctrl-C


def stop_at_once_on_signals() -> None:
    """From here on, Ctrl-C, SIGTERM or SIGHUP outside a training loop (``stop_on_signals``) ends the process
    at once with one line on stderr and exit code 128 + the signal's number (130 for Ctrl-C, 143 for
    SIGTERM), in any phase: imports, tracing, compiling, the reward diagnosis; a child process the command
    runs in a session of its own (``ended_with_the_command``) is ended with it. A SIGTERM or SIGHUP the
    process was started ignoring stays ignored (``taken_signals``).

    Python runs a signal's handler only between the main thread's calls, and a compile can hold the
    main thread for minutes: the signal is taken at C level too (``signal.set_wakeup_fd``), and a
    watcher thread or Python's handler, whichever comes first, ends the process. It exits without
    unwinding the interpreter (``os._exit``): unwinding while XLA compiles in another thread can crash
    the process. Every file is written atomically, and run folders resume from any state, so nothing is
    lost. Call it first in a command's process, from the main thread; a library user's process is left
    as it is.
    """
    if threading.current_thread() is not threading.main_thread():
        return
    _COMMAND_PROCESS.set()
    readable, writable = os.pipe()
    os.set_blocking(writable, False)
    taken = taken_signals()
    for signum in taken:
        signal.signal(signum, _stop_at_once)
    signal.set_wakeup_fd(writable, warn_on_full_buffer=False)

    def watch() -> None:
        while True:
            received = os.read(readable, 64)
            # Within a training loop stop_on_signals holds them (stop after this epoch): left to it.
            for signum in taken:
                if signum in received and signal.getsignal(signum) is _stop_at_once:
                    _stop_at_once(signum, None)

    threading.Thread(target=watch, name="stop-signals", daemon=True).start()


@contextlib.contextmanager
def stop_on_signals(announce: Callable[[str], None] = lambda message: None,
                    at_once: Callable[[], str | None] = lambda: None) -> Iterator["StopRequest"]:
    """Within the block, Ctrl-C, SIGTERM (timeout, Slurm, Kubernetes, docker stop) and SIGHUP ask to stop.

    Yields ``should_stop()`` (a ``StopRequest``), which the training loop polls between epochs: it
    saves and stops, and the command exits with ``should_stop.exit_code``. A second signal (another kind, or the same one more than
    ``REPEAT_SECONDS`` later) ends the process at once; the run folder still
    resumes, from its last checkpoint. ``at_once()``: where stopping now loses nothing (no epoch
    begun: the compile, minutes on a large scene, would be waited for to save nothing), the line
    that says so, and the first signal ends the process at once with it (exit code 128 + the signal's
    number); else None. A SIGTERM or SIGHUP the process was started ignoring stays ignored (``taken_signals``).
    Main thread only (as Python's signals).
    """
    requested: list[tuple[int, float]] = []  # (signal, when)

    def handler(signum, frame):
        if not requested and (line := at_once()):
            try:  # stderr may be gone: the process ends all the same
                announce(f"{signal.Signals(signum).name}: {line}")
                sys.stderr.flush()
            finally:
                os._exit(128 + signum)  # as outside training: no unwinding while XLA compiles beside
        now = time.monotonic()
        if requested and requested[0][0] == signum and now - requested[0][1] < REPEAT_SECONDS:
            return  # the same request again: timeout and Slurm signal the process, then its group
        if requested:  # a second request: stop now
            signal.signal(signum, signal.SIG_DFL)
            os.kill(os.getpid(), signum)
        requested.append((signum, now))
        announce(f"{signal.Signals(signum).name}: stopping after this epoch (the checkpoint is saved; "
                 "send it again to stop at once)")

    previous = {signum: signal.signal(signum, handler) for signum in taken_signals()}
    try:
        yield StopRequest(requested)
    finally:
        for signum, old in previous.items():
            if requested and signum == requested[0][0]:  # the same request may still be on its way (timeout
                _ignore_the_repeat(*requested[0], old)  # signals the group after the process): never unguarded
            else:
                signal.signal(signum, old)


class StopRequest:
    """Whether a stop signal asked a training loop to stop (called), and the exit code it asks for: the shell's
    for the signal, as a stop at once gives (130 for Ctrl-C, 143 for SIGTERM); 0 where none asked."""

    def __init__(self, requested: list[tuple[int, float]]):
        self.requested = requested  # (signal, when), the first the request

    def __call__(self) -> bool:
        return bool(self.requested)

    @property
    def exit_code(self) -> int:
        return 128 + self.requested[0][0] if self.requested else 0


def _ignore_the_repeat(signum: int, first: float, previous: Any) -> None:
    """After the block: ``signum`` again within ``REPEAT_SECONDS`` of the request is the same request and
    is ignored; later, ``previous`` (what the block found) handles it."""
    def late(number, frame):
        if time.monotonic() - first < REPEAT_SECONDS:
            return
        signal.signal(number, previous)
        os.kill(os.getpid(), number)

    signal.signal(signum, late)


def in_worker_thread(work: Callable[[], Any]) -> Any:
    """``work()`` in a worker thread, the main thread waiting in short slices; its result or its exception.

    Python runs signal handlers only between the main thread's calls: a main thread
    inside one XLA compile (minutes for a large contact scene) would not see
    SIGTERM until it returned, and a second signal would not stop it at once.
    """
    outcome: dict[str, Any] = {}

    def run() -> None:
        try:
            outcome["value"] = work()
        except BaseException as error:  # handed to the main thread as it is
            outcome["error"] = error

    worker = threading.Thread(target=run, name="stablebptt-work", daemon=True)
    worker.start()
    while worker.is_alive():
        worker.join(0.2)
    if "error" in outcome:
        raise outcome["error"]
    return outcome["value"]


def leave_out_unused_backends() -> None:
    """Import MJX without its Warp backend, and have MuJoCo Playground, where a command loads one of its
    environments, imported without PyTorch: backends of dependencies that no command runs. Called
    first by the commands, before anything else of theirs imports MJX.

    MJX loads its Warp backend at import whenever warp-lang is installed (MuJoCo Playground installs
    it), and Warp has no gradients: a warm train.py's set-up took 0.7-1.8 s less without it
    (the records: ``git show fb065bd:results/startup/cpu-no-warp-after.md``). Playground's torch and RSL-RL wrappers import PyTorch
    wherever it is installed (``playground.UNUSED_BY_COMMANDS``). Afterwards ``import warp`` and
    ``import torch`` work again; only MJX's Warp backend and Playground's torch wrapper stay off in
    this process. MJX is left as it is where it or Warp is already imported.
    """
    from stablebptt.envs import playground
    from stablebptt.imports import imported_without
    playground.leave_out_when_imported(playground.UNUSED_BY_COMMANDS)
    if "mujoco.mjx" in sys.modules or "warp" in sys.modules:
        return
    with imported_without(("warp",)):  # MJX takes the ImportError for "not installed"
        importlib.import_module("stablebptt.physics.mjx_internals")  # imports MJX, keeping its Warp message off stdout


class EpochProgress:
    """A progress bar over epochs with the current test loss, and the time to the first update.

    ``on_compiled`` and ``on_epoch`` are ``runs.epochs.train_epochs``'s callbacks; ``write``
    prints a line without breaking the bar.
    """

    def __init__(self, started: float, total: int, initial: int, updates_per_epoch: int, label: str, disable: bool):
        from tqdm import tqdm
        self.started, self.initial, self.updates = started, initial, updates_per_epoch
        self.bar = tqdm(total=total, initial=initial, unit="epoch", disable=disable, desc=label, dynamic_ncols=True)
        self.compiled: dict[str, float] = {}

    def write(self, line: str, stream=None) -> None:
        self.bar.write(line, file=stream or sys.stderr)

    def on_compiled(self, seconds: float) -> None:
        import time
        self.compiled = {"seconds": seconds, "ready": time.perf_counter() - self.started}

    def on_epoch(self, epoch: int, metrics: dict) -> None:
        import numpy as np
        if epoch == self.initial + 1:  # an epoch is one program: its first update is timed as its share
            first_update = self.compiled["ready"] + metrics["seconds"] / self.updates
            evaluated = metrics.get("eval_seconds", 0.0)  # 0: evaluated inside the epoch, or not at all
            self.write(f"time to the first update: {first_update:.0f} s (compiling {self.compiled['seconds']:.0f} s; "
                       f"the first epoch, {self.updates} update{'s' if self.updates != 1 else ''}"
                       + (f", {metrics['seconds']:.1f} s, its evaluation {evaluated:.2g} s)" if evaluated else
                          f" and the train and test losses, {metrics['seconds']:.1f} s)"), sys.stdout)
        if metrics.get("notice"):  # a non-finite flow gradient left at zero: said, never silent
            self.write(f"epoch {epoch}: {metrics['notice']}")
        self.bar.update(1)
        scored = np.isfinite(metrics["test_loss"])  # an epoch without an evaluation has none, nor a seed stopped apart
        if np.any(scored):
            self.bar.set_postfix(test_loss=f"{float(np.mean(np.asarray(metrics['test_loss'])[scored])):.4g}")

    def close(self) -> None:
        self.bar.close()
