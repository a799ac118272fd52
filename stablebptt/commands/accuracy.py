#!/usr/bin/env python3
"""What accuracy costs in time: simulator, gradient and training error against wall-clock time.

    python scripts/accuracy.py                           # the three studies, every task -> results/accuracy/
    python scripts/accuracy.py --quick --out /tmp/acc    # a small smoke version
    python scripts/accuracy.py --tasks repulsion --studies trajectory,gradients

trajectory: per task, the error of the final simulated state against a float64
  high-accuracy reference, against the wall time per simulated second of a
  batched forward rollout, for every integrator (cart-pole: MJX Euler,
  implicitfast and RK4; repulsion: explicit Euler and RK4; quantum:
  Crank-Nicolson), several time steps, float32 and float64. The controls are
  fixed (one constant control per trajectory), so every scheme integrates the
  same equations. At the paper's time step, the cost of an R gradient too.
gradients: the R and M gradients w.r.t. the policy parameters in float32
  against float64 as the horizon grows, and the growth of their norm with the
  simulated time (a fitted exponent per simulated second).
training: a short training per mode (R, M, S, C) and precision on one task:
  test loss against cumulative wall-clock seconds.

Writes tidy CSVs, PNG figures and summary.md (every table and the command) to
--out, each file atomically. Variants of one table are timed round-robin, so
load from other processes on the machine hits all of them alike; compare
times within one run only.
"""
from __future__ import annotations

import dataclasses
import platform
import sys
import time
from pathlib import Path

from stablebptt.apps.accuracy import AccuracyConfig, check_tasks
from stablebptt.cli import fail, parse_config
from stablebptt.errors import InputError
from stablebptt.reports import accuracy_report
from stablebptt.reports.accuracy_report import STUDIES


def parse(argv: list[str]) -> AccuracyConfig:
    config = parse_config(AccuracyConfig, argv, __doc__, "accuracy study")
    for name in config.study_list:
        if name not in STUDIES:
            fail(f"unknown study {name!r} in --studies: choose from {', '.join(STUDIES)}")
    try:
        check_tasks(config)
    except InputError as error:
        fail(str(error))
    if "contact" in config.study_list and not Path(config.suite, "hopper.xml").is_file():
        fail("the contact study needs --suite: the folder of dm_control's suite/*.xml (pip download dm_control, unzip)")
    if not (1 <= config.poles <= 4 and 1 <= config.gradient_poles <= 4):
        fail("--poles and --gradient-poles must be 1, 2, 3 or 4")
    for name in ("batch", "rounds", "epochs", "train_size"):
        if getattr(config, name) <= 0:
            fail(f"--{name.replace('_', '-')} must be a positive integer, got {getattr(config, name)}")
    if config.train_size % 8:
        fail(f"--train-size must be a multiple of the batch of 8, got {config.train_size}")
    return config


def main(argv: list[str]) -> int:
    config = parse(argv)
    out = Path(config.out)
    if config.replot:
        if not (out / accuracy_report.META_FILE).is_file():
            fail(f"{out} has no {accuracy_report.META_FILE}: run the study first (without --replot)")
        print("\n".join(accuracy_report.report(out)))
        return 0
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        fail(f"cannot create {out}: {error.strerror}")
    if config.quick:
        config = dataclasses.replace(config, batch=min(config.batch, 2), rounds=min(config.rounds, 2),
                                     epochs=min(config.epochs, 3), train_size=16)

    import os

    import jax

    from stablebptt.apps.contact_study import contact_study
    from stablebptt.apps.gradient_study import gradient_setups, gradient_study
    from stablebptt.apps.training_study import training_study
    from stablebptt.apps.trajectory_study import trajectory_setups, trajectory_study
    from stablebptt.storage import write_json

    started = time.perf_counter()
    log = lambda message: print(message, file=sys.stderr, flush=True)
    write_json(out / accuracy_report.META_FILE, {
        "command": "python scripts/accuracy.py" + "".join(f" {a}" for a in argv),
        "machine": f"{platform.machine()} ({jax.devices()[0].platform}, {jax.device_count()} device, {os.cpu_count()} CPU cores)",
        "jax": jax.__version__, **dataclasses.asdict(config)})
    tables = []
    for name, study in (("trajectory", lambda: [row for setup in trajectory_setups(config) for row in trajectory_study(setup, config, log)]),
                        ("gradients", lambda: [row for setup in gradient_setups(config) for row in gradient_study(setup, config, log)]),
                        ("training", lambda: training_study(config, log)),
                        ("contact", lambda: contact_study(
                            config, log, done=accuracy_report.read_csv(out / "contact.csv") if (out / "contact.csv").is_file() else [],
                            on_row=lambda rows: accuracy_report.write_csv(out / "contact.csv", rows)))):
        if name in config.study_list:
            rows = study()
            accuracy_report.write_csv(out / f"{name}.csv", rows)
            if name == "gradients":
                accuracy_report.write_csv(out / "gradient_growth.csv", accuracy_report.growth_rows(rows))
            tables = accuracy_report.report(out, draw=(name,))  # after every study, so a long run keeps what it measured
    print("\n".join(tables))
    log(f"done in {time.perf_counter() - started:.0f} s -> {out}")
    return 0


if __name__ == "__main__":
    from stablebptt.cli import stop_at_once_on_signals
    stop_at_once_on_signals()
    sys.exit(main(sys.argv[1:]))
