"""The timing harness of the benchmarks: compile ahead, then time calls round-robin.

Round-robin (one call of each variant per round, the median over rounds) exposes
every variant to the same drift of the machine (frequency scaling, other
processes), so ratios measured in one run compare like with like.
"""
from __future__ import annotations

import os
import platform
import time
from pathlib import Path
from typing import Any, Callable


def usable_cores() -> int:
    """The CPU cores this process may run on (its affinity where the OS has one, as Linux does; else
    the machine's count)."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def machine() -> str:
    """The machine in words: architecture, processor, cores this process may use."""
    model = ""
    try:
        lines = Path("/proc/cpuinfo").read_text(errors="replace").splitlines()
        model = next((line.split(":", 1)[1].strip() for line in lines if line.startswith("model name")), "")
    except OSError:
        pass
    return (f"{platform.machine()}{f' ({model})' if model else ''}, {usable_cores()} of "
            f"{os.cpu_count()} cores, {platform.system()} {platform.release()}")


def compile_ahead(function: Callable, *arguments) -> tuple[Callable, float]:
    """``function`` (jitted) compiled for ``arguments``, and the seconds that took."""
    started = time.perf_counter()
    compiled = function.lower(*arguments).compile()
    return compiled, time.perf_counter() - started


def timed(call: Callable[[], Any]) -> tuple[Any, float]:
    """``call()``'s result, waited for (JAX dispatches asynchronously), and the seconds it took."""
    import jax
    started = time.perf_counter()
    result = jax.block_until_ready(call())
    return result, time.perf_counter() - started


def round_robin(calls: dict[str, Callable[[], Any]], rounds: int, warmup: int = 1) -> dict[str, float]:
    """Median seconds per call of each zero-argument ``calls[name]``, after ``warmup`` untimed rounds
    (the first calls after compiling run cold)."""
    import numpy as np
    for _ in range(warmup):
        for call in calls.values():
            timed(call)
    samples: dict[str, list[float]] = {name: [] for name in calls}
    for _ in range(rounds):
        for name, call in calls.items():
            samples[name].append(timed(call)[1])
    return {name: float(np.median(values)) for name, values in samples.items()}
