#!/usr/bin/env python3
"""Measure update times, in one run, and print them as Markdown tables.

    python scripts/bench.py                          # every task, poles 1 and 3
    python scripts/bench.py --tasks cartpole --poles 1,2,3,4 --out results/bench_cpu.md
    python scripts/bench.py --tasks cartpole --tables steps --simulators generated,floor   # the floor ratio alone
    python scripts/bench.py --startup --suite .cache/dm_control-1.0.50/dm_control/suite --out results/startup/cpu.md
    python scripts/bench.py --startup --models stablebptt/models/cartpole_1.xml --envs CartpoleSwingup --out /tmp/startup.md

Per task, one update (gradient of a batch-8 rollout, then clip and Adam) per mode:
R, M, S and C through the one-pass flows, and "R plain": jax.grad of the plain
rollout with no flow machinery, the baseline the ratios divide by. For the
cart-pole, also its steps: the default one generated body by body (stablebptt/physics/rigid_body.py),
MJX's stages the scene needs (differentiated through inverse dynamics), the same
differentiated by plain autodiff through the mass matrix and its solve, the same
with MJX's dense mass matrix, mjx.step with MuJoCo's default flags, and
closed-form cart-pole equations as the floor; and the parts of the default R update (the rollout alone, and every step's
Jacobian built in one batched call, as the update builds them). Variants of one table are timed round-robin, so drift of
the machine hits all of them alike; tables are timed one after another.

With --startup, the start-up table instead (stablebptt/apps/startup.py): per model (--models) and
environment (--envs), fresh `scripts/train.py --model M` or `--env E` processes timed to their first
update, with an empty compile cache and again with the cache that run filled.
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
import platform
import shlex
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from stablebptt.apps.bench import TABLES, BenchConfig
from stablebptt.cli import ended_with_the_command, fail, option_name, parse_config_given
from stablebptt.errors import InputError
from stablebptt.timing import machine, usable_cores


def main(argv: list[str]) -> int:
    config, given = parse_config_given(BenchConfig, argv, __doc__, "benchmark")
    refuse_options_of_the_other_table(config, given)
    if config.startup:
        return startup(config, argv)
    from stablebptt import tasks
    names = config.task_list  # "cartpole": the MJCF task's cart-poles (--poles)
    unknown = [t for t in names if tasks.canonical(t) not in tasks.entries()]
    if unknown:
        fail(f"unknown task {unknown[0]!r}: choose from {', '.join(sorted(tasks.entries()))}")
    for name in ("rounds", "batch"):
        if getattr(config, name) <= 0:
            fail(f"--{name} must be positive, got {getattr(config, name)}")
    tables = config.table_list
    if not tables or any(name not in TABLES for name in tables):
        fail(f"--tables takes a comma-separated subset of {', '.join(TABLES)}, got {','.join(tables) or 'nothing'}")
    from stablebptt.apps.bench import bench_cases, mode_table
    try:  # every task's cases before anything is timed: a bad option is refused at once
        cases = {name: bench_cases(name, config) for name in names}
    except InputError as error:
        fail(str(error))
    import jax
    header = [f"Measured by `python scripts/bench.py {' '.join(argv)}`".rstrip()
              + f" on {platform.machine()} ({jax.devices()[0].platform}, {jax.device_count()} device, "
              f"{usable_cores()} of {os.cpu_count()} cores), "
              f"jax {jax.__version__}, batch {config.batch}, median of {config.rounds} rounds.", ""]
    print("\n".join(header), flush=True)
    report = list(header)
    for name in names:
        module = tasks.load(name)
        section = []
        for case in cases[name]:
            if "modes" in tables:
                section += mode_table(case.title, module.make(case.task_config), config.batch, config.rounds)
            if "steps" in tables and case.steps is not None:
                section += case.steps()
        if not section:
            continue
        print("\n".join(section), flush=True)
        report += section
        if config.out:  # after every task, so a long benchmark keeps what it measured
            from stablebptt.storage import atomic_write
            Path(config.out).parent.mkdir(parents=True, exist_ok=True)
            atomic_write(Path(config.out), ("\n".join(report) + "\n").encode())
    return 0


# Runs scripts/train.py as its own process would, recording the progress callbacks' times (the numbers
# train.py prints, unrounded) against this process's start: one line "startup-record {json}".
_PROBE = """
import json, os, runpy, sys, time
started = time.perf_counter()
sys.argv = sys.argv[1:]
sys.path[0] = os.path.dirname(sys.argv[0])  # as `python scripts/train.py` would have it
from stablebptt import cli

class Recorded(cli.EpochProgress):
    def on_epoch(self, epoch, metrics):
        if epoch == self.initial + 1:
            ready = self.started + self.compiled["ready"] - started
            epoch_s = metrics["seconds"] / self.updates
            import jax
            print("startup-record " + json.dumps({"setup_s": ready - self.compiled["seconds"],
                  "compile_s": self.compiled["seconds"], "epoch_s": epoch_s, "first_update_s": ready + epoch_s,
                  "reported_first_update_s": self.compiled["ready"] + epoch_s,
                  "device": jax.devices()[0].device_kind}), flush=True)
        super().on_epoch(epoch, metrics)

cli.EpochProgress = Recorded
runpy.run_path(sys.argv[0], run_name="__main__")
"""


def refuse_options_of_the_other_table(config: BenchConfig, given: set[str]) -> None:
    """One line, exit 2, for an option given that changes nothing in what the command makes (its default value
    typed included): the start-up table's options (their help begins "for --startup:") without --startup, the
    update tables' with it."""
    for option in dataclasses.fields(BenchConfig):
        if option.name in ("startup", "out") or option.name not in given:
            continue
        flag, for_startup = option_name(option.name), option.metadata["help"].startswith("for --startup:")
        if for_startup != config.startup:
            fail(f"{flag} is an option of the start-up table: give --startup, or leave {flag} out" if for_startup else
                 f"{flag} is an option of the update tables, which --startup does not make: leave {flag} out")


def _time_run(command: list[str], cache: Path, timeout: float) -> dict:
    """One fresh training process with ``cache`` as its compile cache: its times, or why there are none."""
    environment = dict(os.environ, STABLEBPTT_COMPILE_CACHE=str(cache))
    started = time.perf_counter()
    # A session of its own, so that a timeout stops the process and every thread and child it started.
    process = subprocess.Popen([sys.executable, "-c", _PROBE] + command, stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True, env=environment, start_new_session=True)
    end = lambda: os.killpg(process.pid, signal.SIGKILL)  # noqa: E731 - the run and all it started
    try:
        with ended_with_the_command(end):  # a stop signal to this command
            stdout, stderr = process.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        end()
        process.communicate()
        return {"status": f"timeout after {timeout:.0f} s", "wall_s": time.perf_counter() - started}
    except BaseException:  # anything else that ends this command ends the run in its session too
        end()
        raise
    record = {"wall_s": time.perf_counter() - started}
    found = [line.split(" ", 1)[1] for line in stdout.splitlines() if line.startswith("startup-record ")]
    if process.returncode != 0 or not found:
        last = (stderr.strip().splitlines() or ["no output"])[-1]
        return dict(record, status=f"failed (exit {process.returncode})", error=last)
    return dict(record, status="ok", **json.loads(found[0]))


def startup(config, argv: list[str]) -> int:
    """The start-up table (``--startup``): cold and warm fresh processes per model and environment, a row at a time."""
    from stablebptt.apps.startup import resolve_envs, resolve_models, table
    if not (math.isfinite(config.timeout) and config.timeout > 0):
        fail(f"--timeout must be a positive number of seconds, got {config.timeout}")
    from stablebptt.errors import InputError
    from stablebptt.storage import atomic_write
    try:  # the default models only where neither models nor environments are named
        models = resolve_models(config.model_list, config.suite) if config.model_list or not config.env_list else []
        envs = resolve_envs(config.env_list)
    except InputError as error:
        fail(str(error))
    options = {"--model": shlex.split(config.train_args), "--env": shlex.split(config.env_args)}
    for flag, name in (("--model", "--train-args"), ("--env", "--env-args")):
        if any(argument in (flag, "--out", "--resume") or argument.startswith((f"{flag}=", "--out=", "--resume="))
               for argument in options[flag]):
            fail(f"{name} must not hold {flag}, --out or --resume: the benchmark sets them")
    # (name, train.py's options) per row: the models, then the environments
    entries = [(name, ["--model", str(path), *options["--model"]]) for name, path in models]
    entries += [(name.rpartition(":")[2], ["--env", name, *options["--env"]]) for name in envs]
    import jax
    description = machine()
    commands = " and ".join(command for command, present in (
        (f"`python scripts/train.py --model M {config.train_args}`", models),
        (f"`python scripts/train.py --env E {config.env_args}`", envs)) if present)
    out = Path(config.out) if config.out else None
    record = {"command": f"python scripts/bench.py {shlex.join(argv)}", "machine": description,
              "jax": jax.__version__, "python": platform.python_version(), "timeout_s": config.timeout, "rows": []}

    def header() -> list[str]:
        devices = ", ".join(sorted({row[kind]["device"] for row in record["rows"] for kind in ("cold", "warm")
                                    if "device" in row[kind]}))  # as the training processes saw it
        return [f"Measured by `python scripts/bench.py {shlex.join(argv)}` on {description}"
                f"{f', JAX device {devices}' if devices else ''}, jax {jax.__version__}: "
                f"per row, {commands} in a fresh process, "
                f"cold (an empty compile cache) then warm (the same command again, with the cache the cold run filled). "
                f"Seconds from the process's start: set-up (imports, model, scene analysis, tracing) to the start of "
                f"compiling, compiling, the first epoch's share of one update; the load average (1 min) beside them "
                f"says how busy the machine was.", ""]

    print("\n".join(header()), flush=True)
    train = str(Path(__file__).resolve().parent / "train.py")
    with tempfile.TemporaryDirectory(prefix="startup-") as scratch:
        for name, arguments in entries:
            cache, runs_dir = Path(scratch) / name / "cache", Path(scratch) / name / "runs"
            row = {"model": name, ("env" if arguments[0] == "--env" else "file"): arguments[1],
                   "load": {"start": os.getloadavg()}}
            for kind in ("cold", "warm"):
                command = [train, *arguments, "--no-progress", "--out", str(runs_dir / kind)]
                row[f"{kind}_command"] = (f"STABLEBPTT_COMPILE_CACHE={cache} python scripts/train.py "
                                          + shlex.join(command[1:]))
                if kind == "warm" and row["cold"]["status"] != "ok":
                    row[kind] = {"status": "not run"}  # nothing in the cache to start warm from
                    continue
                row[kind] = _time_run(command, cache, config.timeout)
            row["load"]["end"] = os.getloadavg()
            record["rows"].append(row)
            lines = table(record["rows"])
            print(lines[-1] if len(record["rows"]) > 1 else "\n".join(lines), flush=True)
            if out:  # after every row, so a long table keeps what it measured
                out.parent.mkdir(parents=True, exist_ok=True)
                atomic_write(out, ("\n".join(header() + lines) + "\n").encode())
                atomic_write(out.with_suffix(".json"), (json.dumps(record, indent=1) + "\n").encode())
    return 0


if __name__ == "__main__":
    from stablebptt.cli import stop_at_once_on_signals
    stop_at_once_on_signals()
    sys.exit(main(sys.argv[1:]))
