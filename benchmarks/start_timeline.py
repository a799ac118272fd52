"""When a start traced, lowered and compiled each of its programs, and in which thread: one train
command run in this process, from an empty compile cache of its own, with JAX's compile events
recorded (``jax.monitoring``), printed as a timeline beside the run's start-up phases (its
``startup.json``).

    python benchmarks/start_timeline.py -- --env HumanoidStand --recipe locomotion --seeds 5 --epochs 1
    python benchmarks/start_timeline.py --accelerator-order -- --env HumanoidStand --recipe locomotion \\
        --batch 16 --train-size 2 --test-size 2 --seeds 1 --epochs 1

A start overlaps its work: XLA compiles in threads of its own while Python traces the next program,
but two traces, in whatever threads, take turns holding Python's lock, and each takes longer. The
timeline shows which program waited for which. ``--accelerator-order``: on a CPU alone, the start
takes the order it takes beside an accelerator (the reward check run as on the accelerator host's
CPU, begun once the start asks for its answer where the reward turns no comparison into a number;
the programs beside the epoch traced before the check); it shows that order, not an accelerator's
times: on a CPU every compile shares its cores.

--min-seconds (default 0.5) leaves out shorter events; --out OUT writes OUT.md too.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from stablebptt.storage import atomic_write  # noqa: E402

# JAX's names for the three steps of making a program (jax._src.dispatch), as this timeline names them.
EVENTS = {"/jax/core/compile/jaxpr_trace_duration": "trace",
          "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
          "/jax/core/compile/backend_compile_duration": "compile"}


def take_accelerator_order() -> None:
    """The start's order beside an accelerator, taken on a CPU alone: the check runs on "the host's CPU"
    (this one), and the start counts its host as apart from the device it trains on."""
    import jax

    from stablebptt.engine import starting
    from stablebptt.envs import adapter, diagnosis
    for module in (adapter, diagnosis):
        module.check_device = lambda: jax.devices("cpu")[0]
    starting._host_apart = lambda: True


def recorder(events: list[dict]):
    """A listener of JAX's time spans (``jax.monitoring.register_event_time_span_listener``) that appends
    each trace, lowering and compile to ``events``: its step, program, start, end and thread."""
    def listen(event: str, start: float, end: float, **details) -> None:
        if event in EVENTS:  # called in the thread that did the work
            events.append({"step": EVENTS[event], "program": details.get("fun_name", ""), "start": start,
                           "end": end, "thread": threading.current_thread().name})
    return listen


def timeline(events: list[dict], began: float, shortest: float) -> list[str]:
    """The events of ``shortest`` seconds or more as a table, in the order they ended."""
    lines = ["| ended, s | began, s | seconds | thread | step | program |", "|---:|---:|---:|---|---|---|"]
    for event in sorted(events, key=lambda event: event["end"]):
        if event["end"] - event["start"] >= shortest:
            lines.append(f"| {event['end'] - began:.1f} | {event['start'] - began:.1f} | "
                         f"{event['end'] - event['start']:.1f} | {event['thread']} | {event['step']} | "
                         f"`{event['program']}` |")
    return lines


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    ours, train_arguments = (argv[:argv.index("--")], argv[argv.index("--") + 1:]) if "--" in argv else (argv, [])
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--accelerator-order", action="store_true",
                        help="on a CPU alone, take the order a start takes beside an accelerator")
    parser.add_argument("--min-seconds", type=float, default=0.5, help="leave out shorter events")
    parser.add_argument("--out", type=Path, help="OUT.md is written too")
    options = parser.parse_args(ours)
    if not train_arguments:
        parser.error("give the train command's arguments after --")
    with tempfile.TemporaryDirectory() as scratch:
        os.environ["STABLEBPTT_COMPILE_CACHE"] = str(Path(scratch) / "cache")  # a cold start
        run = Path(scratch) / "run"
        if "--out" in train_arguments:
            run = Path(train_arguments[train_arguments.index("--out") + 1])
        else:
            train_arguments = [*train_arguments, "--out", str(run)]
        import jax.monitoring
        events: list[dict] = []
        jax.monitoring.register_event_time_span_listener(recorder(events))
        if options.accelerator_order:
            take_accelerator_order()
        from stablebptt.commands import train
        began = time.time()
        status = train.main(train_arguments)
        if status != 0 or not (run / "startup.json").is_file():
            raise SystemExit(f"the train command exited {status} without a startup.json")
        start = json.loads((run / "startup.json").read_text())[-1]
    lines = [f"# `stablebptt train {' '.join(train_arguments)}`"
             + (", in the order beside an accelerator" if options.accelerator_order else ""), "",
             (f"{start['seconds_to_training']:.1f} s to training on {start['device']} ({start.get('host', '')}); "
              f"events of {options.min_seconds:g} s or more, seconds from the command's start:"), "",
             *timeline(events, began, options.min_seconds), "", "The start's phases (`startup.json`):", "",
             *[f"- {name}: {seconds:.1f} s" for name, seconds in start["phases"].items()]]
    if options.out:
        options.out.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(options.out.with_suffix(".md"), ("\n".join(lines) + "\n").encode())
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
