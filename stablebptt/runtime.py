"""Process-level settings a program may ask for: the library itself changes none on import."""
from __future__ import annotations

import gc
import os
import sys
import warnings
from pathlib import Path
from typing import Any, Callable

# Objects allocated between two collections of Python's youngest generation (Python's own: 700).
SPACED_COLLECTIONS = 20_000


def one_cpu_thread() -> None:
    """Give XLA:CPU's intra-op pool one thread (``PJRT_NPROC=1``), unless ``PJRT_NPROC`` is set already.

    jaxlib's batched LAPACK kernels (MJX's Newton solver: Cholesky and triangular solves over every
    step's Jacobian) split a large batch into chunks queued on the intra-op pool and block the pool
    thread that runs them until the chunks are done: when as many such calls run at once as the pool
    has threads, every thread waits and the program hangs. With one thread the kernels run the batch
    in place. JAX reads the variable when it creates its CPU client, so call this before the first
    computation; the ``stablebptt`` commands call it as they start.

    Example::

      import stablebptt as sb
      sb.one_cpu_thread()  # before anything runs on JAX's CPU backend

    Called after JAX's first computation it changes nothing in this process, and warns.
    """
    if "PJRT_NPROC" in os.environ:
        return
    os.environ["PJRT_NPROC"] = "1"
    bridge = sys.modules.get("jax._src.xla_bridge")  # JAX's backends, where JAX is loaded at all
    if bridge is not None and getattr(bridge, "backends_are_initialized", lambda: False)():
        warnings.warn("one_cpu_thread came after JAX's first computation: its CPU client keeps the threads it was "
                      "made with (with more than one, MJX's solver can deadlock); call it before anything runs",
                      RuntimeWarning, stacklevel=2)


def rarer_garbage_collections() -> None:
    """Collect Python's cyclic garbage after every ``SPACED_COLLECTIONS`` new objects (Python's own
    threshold is 700) where it would collect more often; a threshold of 0 (collections off) stays.

    Tracing a program makes millions of small objects, and each collection of the older generations
    walks all of them: a start's traces run a tenth to a fifth sooner, its peak memory about the same
    (docs/performance.md, "Python's garbage collected less often", gives the commands and figures). The
    garbage is still collected, later. The ``stablebptt`` commands call it as they start.

    Example::

      import stablebptt as sb
      sb.rarer_garbage_collections()  # before a start's traces
    """
    youngest, *older = gc.get_threshold()
    if 0 < youngest < SPACED_COLLECTIONS:
        gc.set_threshold(SPACED_COLLECTIONS, *older)


COMPILE_CACHE_ENV = "STABLEBPTT_COMPILE_CACHE"  # a directory, or "off"


def compile_cache_dir() -> Path | None:
    """Where compiled programs are kept between runs: $STABLEBPTT_COMPILE_CACHE, else the user's
    cache directory ($XDG_CACHE_HOME or ~/.cache, then stablebptt/jax); None when it is "off"."""
    value = os.environ.get(COMPILE_CACHE_ENV, "")
    if value == "off":
        return None
    if value:
        return Path(value)
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "stablebptt" / "jax"


def use_compile_cache(enabled: bool = True,
                      note: Callable[[str], None] = lambda line: print(line, file=sys.stderr)) -> Path | None:
    """Turn on JAX's persistent compilation cache (before the first compile): a second identical run
    loads its programs instead of compiling them. Returns the directory, or None when off.

    A directory that cannot be written is left off with one line to ``note`` (JAX would warn at every
    program); a damaged entry (a process killed while JAX wrote it) is compiled again and replaced,
    and an entry that cannot be written (a full disk) skipped, with one line to ``note`` for the first
    of each (JAX would warn at every program, and recompile a damaged entry in every run).
    """
    directory = compile_cache_dir() if enabled else None
    if directory is None:
        return None
    import tempfile
    try:
        directory.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=directory):
            pass
    except OSError as error:
        note(f"note: compiled programs are not kept between runs: cannot write to the compile cache {directory} "
             f"({error.strerror or error}); set {COMPILE_CACHE_ENV} to a writable directory, or to off")
        return None
    import jax
    jax.config.update("jax_compilation_cache_dir", str(directory))
    # Every program, the set-up's tiny ones too: loading them is quicker than compiling them anew in
    # every warm run (hopper 4.3 -> 3.4 s to its first update: ``git show fb065bd:results/startup/cpu-cache-tiny-after.md``).
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    _handle_cache_faults(directory, note)
    return directory


_cache_state: dict[str, Any] = {}  # the directory and note of the latest use_compile_cache, and what it told


def _handle_cache_faults(directory: Path, note: Callable[[str], None]) -> None:
    """A cache entry that cannot be read becomes a miss, compiled and written anew; an entry that
    cannot be written (a full disk) is skipped. Each kind of fault is told once, in one line.

    JAX warns of every such entry, and never writes over a key that exists (it writes entries
    in place, so a killed process leaves half of one): every later run would warn and compile again.
    """
    import jax
    from jax._src import compilation_cache
    _cache_state.update(directory=directory, note=note, told=set())
    if getattr(compilation_cache.get_executable_and_time, "handled_by_stablebptt", False):
        return
    from jax._src import lru_cache
    suffix = getattr(lru_cache, "_CACHE_SUFFIX", "-cache")  # how JAX names an entry's file after its key
    read, write = compilation_cache.get_executable_and_time, compilation_cache.put_executable_and_time

    def tell(kind: str, error: Exception, what: str) -> None:
        if kind not in _cache_state["told"]:
            _cache_state["told"].add(kind)
            detail = (str(error).splitlines() or [""])[0][:80]
            _cache_state["note"](f"note: {what} the compile cache {_cache_state['directory']} "
                                 f"({type(error).__name__}: {detail})")

    def get_executable_and_time(cache_key, *args, **kwargs):
        try:
            return read(cache_key, *args, **kwargs)
        except Exception as error:  # noqa: BLE001 - any unreadable entry: JAX's own answer is to compile
            if jax.config.jax_raise_persistent_cache_errors or isinstance(error, compilation_cache.CacheVerificationError):
                raise
            try:
                (Path(_cache_state["directory"]) / f"{cache_key}{suffix}").unlink(missing_ok=True)
            except OSError:
                pass
            tell("read", error, "a damaged entry is compiled again and replaced in")
            return None, None

    def put_executable_and_time(*args, **kwargs):
        try:
            return write(*args, **kwargs)
        except Exception as error:  # noqa: BLE001 - the program is compiled and runs; only keeping it failed
            if jax.config.jax_raise_persistent_cache_errors:
                raise
            tell("write", error, "compiled programs are not all kept: cannot write to")

    for wrapper in (get_executable_and_time, put_executable_and_time):
        wrapper.handled_by_stablebptt = True
    compilation_cache.get_executable_and_time = get_executable_and_time
    compilation_cache.put_executable_and_time = put_executable_and_time
