"""A start's timeline (benchmarks/start_timeline.py): JAX's trace, lowering and compile of each program,
recorded with the thread that did the work, and listed in the order they ended."""
from __future__ import annotations

import importlib.util
import threading
import time

import jax
import jax.numpy as jnp

from conftest import ROOT

_spec = importlib.util.spec_from_file_location("start_timeline", ROOT / "benchmarks" / "start_timeline.py")
start_timeline = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(start_timeline)


def test_each_programs_trace_lowering_and_compile_are_recorded_with_its_thread_and_listed_as_they_ended():
    events: list[dict] = []
    listen = start_timeline.recorder(events)
    scale = float(time.time_ns() % 997)  # a program no compile cache holds: its compile runs
    jax.monitoring.register_event_time_span_listener(listen)
    try:
        program = jax.jit(lambda x: jnp.sin(x) * scale).lower(jnp.ones(3))
        worker = threading.Thread(target=program.compile, name="compiling-beside")
        worker.start(), worker.join()
    finally:
        jax.monitoring.unregister_event_time_span_listener(listen)
    ours = [(event["step"], event["program"], event["thread"]) for event in events if "lambda" in event["program"]]
    assert ours == [("trace", "<lambda>", threading.current_thread().name),
                    ("lower", "jit(<lambda>)", threading.current_thread().name),
                    ("compile", "jit(<lambda>)", "compiling-beside")]
    assert all(event["start"] <= event["end"] for event in events)
    began = min(event["start"] for event in events)
    table = start_timeline.timeline(events, began, 0.0)
    ended = [float(line.split("|")[1]) for line in table[2:]]
    assert ended == sorted(ended) and len(ended) == len(events)
    assert "| compiling-beside | compile | `jit(<lambda>)` |" in table[-1]  # its compile ended last
    longest = max(event["end"] - event["start"] for event in events)
    assert len(start_timeline.timeline(events, began, longest + 1.0)) == 2  # nothing that long: the header alone
