"""Traced programs kept between runs: a second identical run skips tracing as well as compiling.

JAX's persistent cache (``runtime.use_compile_cache``) keeps what XLA compiled, but it is keyed by the
lowered program, so every run still traces and differentiates the step first: for a scene with
contacts, most of a warm start. Here the traced and lowered epoch is kept too, serialized with
``jax.export``, under a key of everything that decides it:

    epoch, seconds = compile_epoch(trainer.epoch, arguments, key_parts, cache_dir, trainer.compiler_options)

``key_parts`` must name all of it beyond the library's source, the package versions, the device and
the argument shapes, which are added here: the task and its options, the training config, and what
the task reads from outside the library (a model file's compiled contents); ``run_key`` builds them
for a registered task. Where a task cannot
say (``None``: an environment imported from the user's own package), the epoch is traced as usual.
The run that traces and every later one compile the kept program, so a run and its repetition
compute the same numbers.
"""
from __future__ import annotations

import functools
import hashlib
import importlib
import json
import os
import pickle
import re
import threading
import time
from pathlib import Path
from typing import Any, Callable

from stablebptt.storage import atomic_write

FOLDER = "traced"  # inside the compile cache's directory
SUFFIX = ".jaxexport"
PACKAGES = ("jax", "jaxlib", "mujoco", "mujoco-mjx", "playground", "brax", "optax", "numpy")


def run_key(task_module, task_name: str, task_config, train_config) -> dict | None:
    """The key parts of a run of a registered task: everything beyond the library that decides its
    programs (the task and its options, the training config, the module's ``program_inputs``), or
    None where the task cannot say (no ``program_inputs``, or it answers None)."""
    import dataclasses

    from stablebptt.engine.config import STOPPING_OPTIONS
    inputs = getattr(task_module, "program_inputs", lambda config: None)(task_config)
    if inputs is None:
        return None
    # How long a run trains and how often it saves decide when it stops, not what it compiles: a resume
    # with more --epochs than the first start had traced and compiled every program again (80 s on a GPU).
    train = {name: value for name, value in dataclasses.asdict(train_config).items() if name not in STOPPING_OPTIONS}
    return {"task": task_name, "task_config": dataclasses.asdict(task_config), "train": train, "inputs": inputs}


# JAX's own measure of each persistent-cache hit: the entry's recorded compile time less its loading.
_COMPILE_SAVED_EVENT = "/jax/compilation_cache/compile_time_saved_sec"
_compile_saved = {"seconds": 0.0, "listening": False}
_compile_saved_lock = threading.Lock()  # hits come from the threads that compile beside a check


def compile_seconds_saved() -> float:
    """The seconds of compile that JAX's persistent cache has saved this process since its first call
    here: a start that reads it as it begins and as it trains tells a fresh machine's start from one
    whose programs were compiled before (``runs.epochs.record_start``)."""
    if not _compile_saved["listening"]:
        import jax.monitoring

        def listen(event: str, seconds: float, **_) -> None:
            if event == _COMPILE_SAVED_EVENT:
                with _compile_saved_lock:
                    _compile_saved["seconds"] += max(float(seconds), 0.0)
        with _compile_saved_lock:
            if not _compile_saved["listening"]:
                jax.monitoring.register_event_duration_secs_listener(listen)
                _compile_saved["listening"] = True
    return _compile_saved["seconds"]


def cache_dir() -> Path | None:
    """JAX's persistent compile cache directory, where the kept programs live beside XLA's; None: off."""
    import jax
    directory = jax.config.jax_compilation_cache_dir
    return Path(directory) if directory else None


def program_key(key_parts: dict, arguments: tuple) -> str:
    """SHA-256 of ``key_parts``, the library's source, package versions, device, flags, the JAX
    settings that change a traced program (float64, matmul precision) and the arguments' tree,
    shapes and types."""
    import jax

    shapes = jax.tree.map(lambda a: f"{getattr(a, 'shape', ())}:{getattr(a, 'dtype', type(a).__name__)}", arguments)
    everything = {
        "parts": key_parts, "code": code_digest(), "packages": _versions(),
        "device": str(jax.devices()[0].device_kind), "backend": jax.default_backend(),
        "x64": bool(jax.config.jax_enable_x64), "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "matmul_precision": str(jax.config.jax_default_matmul_precision),
        "arguments": _tree_digest(jax.tree.structure(arguments)), "shapes": jax.tree.leaves(shapes),
    }
    return hashlib.sha256(json.dumps(everything, sort_keys=True, default=str).encode()).hexdigest()


@functools.cache  # installed versions do not change under a running process
def _versions() -> dict[str, str]:
    from importlib.metadata import PackageNotFoundError, version

    def installed(name: str) -> str:
        try:
            return version(name)
        except PackageNotFoundError:
            return ""
    return {name: installed(name) for name in PACKAGES}


def _tree_digest(tree) -> str:
    """The arguments' tree, the same in every run: its text shows some static leaves by address (MJX's
    contact data), so it is pickled, node data and all; where that fails, its text without addresses.
    Pickled as it pickles once unpickled: a tree read back from a kept program (an environment's
    states) holds its own copy of each shared object (a NumPy dtype), which pickles otherwise."""
    try:
        return hashlib.sha256(pickle.dumps(pickle.loads(pickle.dumps(tree)))).hexdigest()
    except Exception:  # noqa: BLE001 - a node whose data does not pickle
        return re.sub(r" at 0x[0-9a-fA-F]+", "", str(tree))


def kept_answer(key_parts: dict | None, name: str, compute: Callable[[], Any]) -> Any:
    """``compute()``'s answer (JSON), kept beside the traced programs under ``key_parts`` and ``name``
    while JAX's compile cache is on: a set-up measurement or check that traces the step (the memory
    plan's bytes, the task check, the step's size) is not repeated by an identical later run.
    ``key_parts`` None: computed."""
    return kept_answer_later(key_parts, name, lambda: compute)()


def kept_answer_later(key_parts: dict | None, name: str, start: Callable[[], Callable[[], Any]]) -> Callable[[], Any]:
    """``kept_answer`` for an answer computed beside the caller: ``start()`` begins computing it and
    returns a function that waits for it (an environment's reward diagnosis, compiling while the
    trainer is built). Returns a function that waits for the answer, keeps it and gives it; a kept
    answer is given at once, and nothing is started."""
    path = _answer_path(key_parts, name)
    if path is not None:
        try:
            kept = json.loads(path.read_text())["answer"]
            return lambda: kept
        except (OSError, ValueError, KeyError, TypeError):
            pass  # none kept yet, or unreadable: computed and kept anew
    wait = start()

    @functools.cache  # waited for once, kept once
    def answer():
        value = wait()
        if path is not None:
            try:
                path.parent.mkdir(parents=True, exist_ok=True)
                atomic_write(path, json.dumps({"name": name, "answer": value}).encode())
            except OSError:
                pass
        return value

    return answer


def _answer_path(key_parts: dict | None, name: str) -> Path | None:
    cache = cache_dir()
    if key_parts is None or cache is None:
        return None
    return cache / FOLDER / f"{program_key({**key_parts, 'answer': name}, ())}.json"


def compile_epoch(epoch: Callable, arguments: tuple, key_parts: dict | None, cache_dir: Path | None,
                  compiler_options: dict | None = None) -> tuple[Callable, float]:
    """A trainer's ``epoch`` compiled for ``arguments``, and the seconds that took (tracing included):
    ``lower_epoch(...).compile()``."""
    started = time.perf_counter()
    compiled = lower_epoch(epoch, arguments, key_parts, cache_dir, compiler_options).compile()
    return compiled, time.perf_counter() - started


def lower_epoch(epoch: Callable, arguments: tuple, key_parts: dict | None, cache_dir: Path | None,
                compiler_options: dict | None = None, update_now: bool = False):
    """A trainer's ``epoch`` traced and lowered for ``arguments`` (arrays, or their shapes); its
    ``compile()`` gives the program.

    With ``key_parts`` and ``cache_dir``, each of its programs (one, or a ``PerUpdateEpoch``'s three)
    comes from the traced program kept in ``cache_dir`` under the key, or is traced and kept first;
    ``compiler_options`` are the trainer's. Otherwise, or for a program that cannot be exported (a
    host callback), it is lowered as usual. A ``PerUpdateEpoch`` lowers its pieces as it compiles
    (the metrics' program takes its shapes from the update's compiled program), its update here
    where ``update_now`` (``PerUpdateEpoch.lower``).
    """
    def lower_one(program: Callable, program_arguments: tuple, name: str):
        return lower_kept(program, program_arguments, key_parts, name, compiler_options, cache_dir)

    if hasattr(epoch, "compile_pieces"):
        return epoch.lower(*arguments, lower_one=lower_one, update_now=update_now)
    return lower_one(epoch, arguments, "epoch")


def lower_kept(program: Callable, arguments: tuple, key_parts: dict | None, name: str,
               compiler_options: dict | None, folder: Path | None):
    """``program`` (jitted) lowered for ``arguments`` (arrays, or their shapes) from its traced program
    kept under ``key_parts`` and ``name`` in ``folder`` (JAX's compile cache, ``cache_dir()``), traced
    and kept first where none is; without a key or a folder, lowered as usual. A run and its resume lower it alike,
    so the second finds what the first compiled in XLA's cache: a checkpoint's arrays, which carry no
    weak types where the first start's may, change no traced program. ``compiler_options``: the jit's
    own, which the kept program is compiled with."""
    if key_parts is None or folder is None:
        return program.lower(*arguments)
    return _lower_kept(program, arguments, {**key_parts, "program": name}, Path(folder) / FOLDER, compiler_options)


def _lower_kept(program: Callable, arguments: tuple, key_parts: dict, folder: Path, compiler_options: dict | None):
    """``program`` lowered for ``arguments`` from its kept traced program, which is traced and kept
    first where none is; a program that cannot be exported is lowered as usual."""
    import jax

    call = _kept_call(program, arguments, key_parts, folder)
    if call is None:  # not exportable: the plain program serves
        return program.lower(*arguments)
    # The kept program is compiled the same way in the run that traced it and in every later one.
    return jax.jit(call, compiler_options=compiler_options).lower(*arguments)


def keep_also(key_parts: dict | None, other: dict | None, name: str, arguments: tuple) -> None:
    """The traced program kept under ``key_parts`` and ``name`` for ``arguments`` (``lower_kept``) kept under
    ``other`` too, where one is kept and none is there: a program that two keys decide alike, traced under
    the first, is then found under either (a start that settles its task's key once its programs are traced)."""
    folder = cache_dir()
    if key_parts is None or other is None or folder is None:
        return
    source, target = (folder / FOLDER / f"{program_key({**parts, 'program': name}, arguments)}{SUFFIX}"
                      for parts in (key_parts, other))
    try:
        if source.is_file() and not target.is_file():
            atomic_write(target, source.read_bytes())
    except OSError:  # not kept: the next run traces it again
        pass


def kept_function(function: Callable, arguments: tuple, key_parts: dict | None, name: str) -> Callable:
    """``function`` (jitted) for arguments shaped as ``arguments``, read from its traced program kept
    under ``key_parts`` and ``name`` while JAX's compile cache is on (traced and kept first where none
    is): an identical later run calls it, eagerly or inside another program, without tracing it.
    ``key_parts`` None, the cache off, or a function that cannot be exported: ``function`` itself."""
    import jax

    folder = cache_dir()
    if key_parts is None or folder is None:
        return function
    # Shapes only: the arguments may be another program's tracers.
    shapes = jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype, weak_type=getattr(a, "weak_type", False)), arguments)
    call = _kept_call(function, shapes, {**key_parts, "program": name}, folder / FOLDER)
    return function if call is None else jax.jit(call)


def _kept_call(program: Callable, arguments: tuple, key_parts: dict, folder: Path) -> Callable | None:
    """A traceable call of ``program``'s kept traced program for ``arguments``' shapes, traced and kept
    first where none is; None where it cannot be exported."""
    import jax

    path = folder / f"{program_key(key_parts, arguments)}{SUFFIX}"
    kept = _read(path) if path.is_file() else None
    if kept is None:
        kept = _traced(program, arguments)
        if kept is None:
            return None
        try:
            folder.mkdir(parents=True, exist_ok=True)
            atomic_write(path, _serialized(*kept))
        except Exception:  # noqa: BLE001 - not kept (a full disk, a tree that does not pickle): the next run traces again
            pass
    exported, out_tree = kept

    def call(*given):
        return jax.tree.unflatten(out_tree, exported.call(*jax.tree.leaves(given)))

    return call


def _traced(program: Callable, arguments: tuple):
    """(``jax.export.Exported`` of ``program`` over the arguments' leaves, the result's tree), or None.

    The program is exported over flat lists of arrays: ``jax.export`` serializes only the trees of
    its own types, and the states here are the user's, optax's and MJX's classes.
    """
    import jax
    from jax import export

    leaves, in_tree = jax.tree.flatten(arguments)
    out_tree = []
    function = getattr(program, "__wrapped__", program)  # a jit with compiler options may not be nested

    def flat(*given):
        result, tree = jax.tree.flatten(function(*jax.tree.unflatten(in_tree, given)))
        out_tree.append(tree)
        return result

    try:
        return export.export(jax.jit(flat))(*leaves), out_tree[0]
    except Exception:  # noqa: BLE001 - a host callback, an effect: export refuses, tracing stays
        return None


def _serialized(exported, out_tree) -> bytes:
    # The result's tree is pickled: its node classes are importable, as they were when it was traced.
    tree = pickle.dumps(out_tree)
    return len(tree).to_bytes(8, "little") + tree + bytes(exported.serialize())


def _read(path: Path):
    """(exported, result tree) from a kept file, or None when it cannot be read (damaged, another
    version's): the program is then traced anew and the file replaced. The file is unpickled: the
    cache directory is the user's own, as trusted as the executables JAX keeps there."""
    from jax import export
    try:
        data = path.read_bytes()
        size = int.from_bytes(data[:8], "little")
        return export.deserialize(bytearray(data[8 + size:])), pickle.loads(data[8:8 + size])
    except Exception:  # noqa: BLE001 - any unreadable entry
        return None


# The package whose source (the tasks' included) decides what a program or a grid computes: pieces of
# different code never merge.
CODE_PACKAGES = ("stablebptt",)


@functools.cache  # the source does not change under a running process; keys read it per program
def code_digest() -> str:
    """SHA-256 (16 hex digits) of the library's and the tasks' Python source, file names included."""
    digest = hashlib.sha256()
    for package in CODE_PACKAGES:
        folder = Path(importlib.import_module(package).__file__).parent
        for path in sorted(folder.rglob("*.py")):
            digest.update(f"{package}/{path.relative_to(folder).as_posix()}\n".encode())
            digest.update(path.read_bytes())
    return digest.hexdigest()[:16]
