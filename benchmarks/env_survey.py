#!/usr/bin/env python3
"""Survey MuJoCo Playground environments: does each load, pass the reward check, compile and train?

    taskset -c 1 python benchmarks/env_survey.py                       # the 25 DeepMind Control Suite envs
    python benchmarks/env_survey.py --envs PendulumSwingup,CartpoleSwingup --out /tmp/survey

For every environment, in its own subprocess (a crash or hang stops only that
environment; ``--timeout`` seconds each, and ``--max-rss-gb`` of memory), it
records:

- the model: MuJoCo's solver and its iterations, contact slots and joint-limit
  constraint rows (MJX's constraint layout of ``env.mj_model``);
- the outcome: refused (``load_env`` or ``env_task`` raised an ``InputError``;
  its one-line message), trained, diverged, error (one line and the traceback's
  last lines), timeout or killed;
- times: importing, loading, ``env_task`` (the reward diagnosis), the trainer's
  set-up, compiling one epoch ahead (``lower().compile()``), the first epoch,
  seconds per later epoch, and the time to the first update as
  ``scripts/train.py`` reports it (everything up to the compiled epoch, plus
  the first epoch's share of one update), the epoch-0 evaluation excluded;
- the episode return (minus the loss) of the policy at initialisation (epoch 0,
  evaluated before any update with the trainer's own ``evaluate`` on the same
  train and test states) and after every epoch; the final and the best epoch,
  and whether the test return rose above epoch 0's.

The JSON (``OUT.json``) is rewritten atomically after each environment and an
environment already in it is skipped, so a stopped survey resumes; the
Markdown table (``OUT.md``) is rendered from it each time.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import shlex
import signal
import subprocess
import sys
import tempfile
import time
import traceback
from datetime import datetime, timezone
from pathlib import Path

from stablebptt.engine import per_update
from stablebptt.engine.config import TrainConfig, seed_array

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_OUT = ROOT / "results" / "envs" / "suite_cpu"
SETTING_KEYS = ("steps", "episode_length", "epochs", "train_size", "test_size", "batch", "mode", "clip", "lr", "seed",
                "timeout", "max_rss_gb")
TRACEBACK_LINES = 12


# --------------------------------------------------------------------------- shared


def _write_atomic(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(handle, "w") as stream:
            stream.write(text)
            stream.flush()
            os.fsync(stream.fileno())
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise


def _write_json(path: Path, payload) -> None:
    _write_atomic(path, json.dumps(payload, indent=2, allow_nan=True) + "\n")


def _one_line(error: BaseException) -> str:
    text = str(error).strip()
    first = text.splitlines()[0] if text else ""
    return f"{type(error).__name__}: {first}" if first else type(error).__name__


def _settings(args) -> dict:
    return {key: getattr(args, key) for key in SETTING_KEYS}


# --------------------------------------------------------------------------- worker (one env, one process)


def _peak_rss_mb() -> float:
    import resource
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def compile_ahead(function, *arguments):
    """``function`` (jitted, or the trainer's per-update epoch) compiled for ``arguments``, and the seconds it took."""
    started = time.perf_counter()
    compiled = function.lower(*arguments).compile()
    return compiled, time.perf_counter() - started


def _cpu_seconds() -> float:
    """User and system CPU seconds of this process (its share of a shared core, against its wall time)."""
    import resource
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def _model_info(env) -> dict:
    """Solver, iterations, contacts and limits of the env's MuJoCo model."""
    import mujoco
    model = env.mj_model
    info = {
        "solver": mujoco.mjtSolver(model.opt.solver).name.removeprefix("mjSOL_"),
        "iterations": int(model.opt.iterations),
        "ls_iterations": int(model.opt.ls_iterations),
        "cone": mujoco.mjtCone(model.opt.cone).name.removeprefix("mjCONE_"),
        "timestep": float(model.opt.timestep),
        "substeps": int(getattr(env, "n_substeps", 0) or 0),
        "nq": int(model.nq), "nv": int(model.nv), "nu": int(model.nu), "ngeom": int(model.ngeom),
        "limited_joints": int(sum(model.jnt_limited)),
        "contact_disabled": bool(model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONTACT),
    }
    try:  # MJX's own constraint layout: what its solver sees every step
        from mujoco.mjx._src import collision_driver, constraint
        info["contact_slots"] = int(len(collision_driver.make_condim(model)))
        ne, nf, nl, nc = constraint.counts(constraint.make_efc_type(model))
        info.update(equality_rows=int(ne), friction_rows=int(nf), limit_rows=int(nl), contact_rows=int(nc),
                    constraint_rows=int(ne + nf + nl + nc))
    except Exception as error:  # noqa: BLE001 - a private API; the survey goes on without it
        info["constraint_layout_error"] = _one_line(error)
    return info


def worker(args) -> int:
    """Survey one environment, writing the record to ``args.worker_out`` after every phase."""
    started = time.perf_counter()
    out = Path(args.worker_out)
    record: dict = {"env": args.worker, "phase": "importing", "times": {}, "pid": os.getpid()}

    def save(phase: str | None = None) -> None:
        now = time.perf_counter() - started
        if phase is not None:
            record["phase"], record["phase_started_s"] = phase, now
        record["elapsed_s"] = now
        record["cpu_s"] = _cpu_seconds()
        record["peak_rss_mb"] = _peak_rss_mb()
        _write_json(out, record)

    def timed(name: str, call):
        begin = time.perf_counter()
        try:
            return call()
        finally:  # a refusal's time too
            record["times"][name] = time.perf_counter() - begin

    save()
    try:
        def import_all():
            import stablebptt
            stablebptt.one_cpu_thread()  # before JAX's CPU client exists
            from stablebptt.envs import playground
            playground.registry()

        timed("import_s", import_all)
        import jax
        record["device"] = jax.devices()[0].device_kind  # "cpu", or the GPU's name
        import numpy as np

        from stablebptt.engine import training
        from stablebptt.engine.training import nonfinite_names
        from stablebptt.envs.adapter import env_task
        from stablebptt.envs.protocol import load_env
        from stablebptt.errors import InputError

        save("loading")
        try:
            env = timed("load_s", lambda: load_env(args.worker))
        except InputError as error:
            record.update(outcome="refused", stage="load_env", reason=str(error).strip().splitlines()[0])
            save("done")
            return 0
        record["model"] = _model_info(env)

        save("env_task (reward diagnosis)")
        try:
            task = timed("task_s", lambda: env_task(env, horizon=args.steps, episode_length=args.episode_length,
                                                     name=args.worker))
        except InputError as error:
            record.update(outcome="refused", stage="env_task", reason=str(error).strip().splitlines()[0])
            save("done")
            return 0
        record["summary"] = task.summary
        record["resolved"] = task.resolved

        config = TrainConfig(mode=args.mode, clip=args.clip, lr=args.lr, epochs=args.epochs, seed=args.seed,
                                      train_size=args.train_size, test_size=args.test_size, batch=args.batch)
        save("make_trainer")
        trainer = timed("setup_s", lambda: training.make_trainer(task, config))
        record["epoch_program"] = "per-update" if isinstance(trainer.epoch, per_update.PerUpdateEpoch) else "whole"
        record["flows"] = list(trainer.flows)
        seeds = seed_array(config)
        state = timed("init_s", lambda: jax.block_until_ready(trainer.init(seeds)))
        arguments = (trainer.batches, trainer.train_states, trainer.test_states)
        updates = config.train_size // config.batch

        save("compiling the epoch")
        epoch_fn, record["times"]["compile_s"] = compile_ahead(trainer.epoch, state, *arguments)
        before_first = sum(record["times"][k] for k in ("import_s", "load_s", "task_s", "setup_s", "init_s",
                                                         "compile_s"))
        # Epoch 0: the policy at initialisation, before any update, on the states every epoch reports.
        save("compiling the evaluation (epoch 0)")
        evaluate, record["times"]["eval_compile_s"] = compile_ahead(trainer.evaluate, state.params, trainer.test_states)
        if config.train_size != config.test_size:
            evaluate_train, seconds = compile_ahead(trainer.evaluate, state.params, trainer.train_states)
            record["times"]["eval_compile_s"] += seconds
        else:
            evaluate_train = evaluate
        save("evaluating epoch 0")
        begin = time.perf_counter()
        train_loss = float(np.mean(jax.device_get(evaluate_train(state.params, trainer.train_states))))
        test_loss = float(np.mean(jax.device_get(evaluate(state.params, trainer.test_states))))
        record["times"]["eval_s"] = time.perf_counter() - begin
        record["epochs"] = [{"epoch": 0, "train_return": -train_loss, "test_return": -test_loss}]

        record["outcome"] = "training"
        for epoch in range(1, config.epochs + 1):
            save(f"epoch {epoch} of {config.epochs}")
            begin = time.perf_counter()
            new_state, metrics = epoch_fn(state, *arguments)
            metrics = jax.device_get(metrics)
            seconds = time.perf_counter() - begin
            if not np.all(metrics["finite"]):
                what = nonfinite_names(trainer.flows, int(np.bitwise_or.reduce(np.atleast_1d(metrics["nonfinite"]))))
                record.update(outcome="diverged", reason=f"non-finite {', '.join(what)} at epoch {epoch}")
                break
            state = new_state
            record["epochs"].append({
                "epoch": epoch, "seconds": seconds,
                "train_return": -float(np.mean(metrics["train_loss"])),
                "test_return": -float(np.mean(metrics["test_loss"])),
                "batch_return": -float(np.mean(metrics["batch_loss"])),  # minus the horizon's training loss
                "update_norm": float(np.mean(metrics["update_norm"])),
                "cosine": float(np.mean(metrics["cosine"])),
            })
            if epoch == 1:
                record["times"]["first_epoch_s"] = seconds
                record["times"]["first_update_s"] = before_first + seconds / updates
        else:
            record["outcome"] = "trained"
        save("done")
        return 0
    except BaseException as error:  # noqa: BLE001 - the survey records any failure in one line
        record.update(outcome="error", reason=_one_line(error),
                      traceback=traceback.format_exc().rstrip().splitlines()[-TRACEBACK_LINES:])
        save()
        print(traceback.format_exc(), file=sys.stderr)
        return 1


# --------------------------------------------------------------------------- parent (the survey)


def _cpu_model() -> str:
    try:
        for line in subprocess.run(["lscpu"], capture_output=True, text=True, check=True).stdout.splitlines():
            if line.startswith("Model name:"):
                return line.split(":", 1)[1].strip()
    except (OSError, subprocess.CalledProcessError):
        pass
    return platform.processor() or "unknown"


def _library_version() -> str:
    """The checkout's commit, and whether stablebptt/ differs from it (it may change while the survey runs)."""
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "stablebptt"], cwd=ROOT, capture_output=True,
                               text=True).stdout.strip()
    except OSError:
        return "unknown"
    return commit + (" + uncommitted changes in stablebptt/" if dirty else "")


def _versions() -> dict:
    from importlib import metadata
    versions = {"python": platform.python_version()}
    for package in ("jax", "jaxlib", "mujoco", "mujoco-mjx", "playground", "optax"):
        try:
            versions[package] = metadata.version(package)
        except metadata.PackageNotFoundError:
            pass
    versions["stablebptt"] = _library_version()
    return versions


def _command(argv: list[str]) -> str:
    """The command line as run, with the CPU pinning and niceness this process has."""
    cpus = sorted(os.sched_getaffinity(0))
    prefix = []
    if len(cpus) < (os.cpu_count() or len(cpus)):
        prefix += ["taskset", "-c", ",".join(map(str, cpus))]
    niceness = os.nice(0)
    if niceness:
        prefix += ["nice", "-n", str(niceness)]
    python = os.path.relpath(sys.executable, Path.cwd()) if sys.executable.startswith(str(Path.cwd())) else sys.executable
    script = os.path.relpath(os.path.abspath(sys.argv[0]), Path.cwd())
    return shlex.join(prefix + [python, script] + argv)


def _process_group_usage(group: int) -> tuple[float, float]:
    """Resident memory (MB) and CPU seconds of every process in process group ``group`` (Linux /proc)."""
    rss, ticks = 0, 0
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            if int(fields[2]) != group:  # pgrp, the 5th field of stat
                continue
            ticks += int(fields[11]) + int(fields[12])  # utime, stime
            for line in (entry / "status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    rss += int(line.split()[1])
        except (OSError, IndexError, ValueError):
            continue
    return rss / 1024, ticks / os.sysconf("SC_CLK_TCK")


def _stop_group(process: subprocess.Popen) -> None:
    """End the worker we started and its children (its own session), politely first."""
    for sig, wait in ((signal.SIGTERM, 10), (signal.SIGKILL, 30)):
        try:
            os.killpg(process.pid, sig)
        except ProcessLookupError:
            return
        try:
            process.wait(timeout=wait)
            return
        except subprocess.TimeoutExpired:
            continue


def survey_one(name: str, args, log_dir: Path) -> dict:
    """Run the worker for ``name`` in a subprocess, under the time and memory limits; its record."""
    worker_out = log_dir / f"{name}.json"
    log = log_dir / f"{name}.log"
    worker_out.unlink(missing_ok=True)
    command = [sys.executable, os.path.abspath(__file__), "--worker", name, "--worker-out", str(worker_out)]
    command += [f"--{key.replace('_', '-')}={value}" for key, value in _settings(args).items()]
    library = _library_version()
    started = time.perf_counter()
    stop, peak_mb, cpu_s = None, 0.0, 0.0
    with open(log, "w") as stream:
        process = subprocess.Popen(command, stdout=stream, stderr=subprocess.STDOUT, cwd=ROOT, start_new_session=True)
        while process.poll() is None:
            elapsed = time.perf_counter() - started
            rss_mb, seconds = _process_group_usage(process.pid)
            peak_mb, cpu_s = max(peak_mb, rss_mb), max(cpu_s, seconds)
            if elapsed > args.timeout:
                stop = ("timeout", f"timeout after {elapsed:.0f} s")
            elif peak_mb > args.max_rss_gb * 1024:
                stop = ("killed", f"killed: memory above {args.max_rss_gb:g} GB after {elapsed:.0f} s")
            if stop:
                _stop_group(process)
                break
            time.sleep(1.0)
    wall = time.perf_counter() - started
    try:
        record = json.loads(worker_out.read_text())
    except (OSError, ValueError):
        record = {"env": name, "phase": "starting", "times": {}}
    record.update(wall_s=wall, returncode=process.returncode, parent_peak_rss_mb=peak_mb, library=library,
                  parent_cpu_s=cpu_s,
                  finished=datetime.now(timezone.utc).isoformat(timespec="seconds"))
    if stop:
        trained = max(0, len(record.get("epochs", [])) - 1)
        record.update(outcome=stop[0], reason=f"{stop[1]}, during {record.get('phase', '?')}"
                      + (f" ({trained} of {args.epochs} epochs done)" if trained else ""))
    elif record.get("outcome") in (None, "training"):  # the worker died without saying why
        tail = log.read_text(errors="replace").rstrip().splitlines()[-TRACEBACK_LINES:] if log.exists() else []
        code = process.returncode
        why = f"signal {signal.Signals(-code).name}" if code is not None and code < 0 else f"exit code {code}"
        record.update(outcome="error", reason=f"worker ended ({why}) during {record.get('phase', '?')}"
                      + (f": {tail[-1]}" if tail else ""), traceback=tail)
    record.pop("pid", None)
    return record


# --------------------------------------------------------------------------- rendering


def _number(value, digits: int = 1) -> str:
    if value is None:
        return "-"
    if isinstance(value, float) and value != value:
        return "nan"
    return f"{value:.{digits}f}"


def _returns(record: dict) -> dict:
    epochs = record.get("epochs") or []
    if not epochs:
        return {}
    start = epochs[0]["test_return"]
    trained = epochs[1:]
    result = {"start": start}
    if trained:
        best = max(trained, key=lambda e: e["test_return"] if e["test_return"] == e["test_return"] else -float("inf"))
        final = trained[-1]["test_return"]
        result.update(final=final, final_epoch=trained[-1]["epoch"], best=best["test_return"], best_epoch=best["epoch"],
                      rose=bool(final > start), best_rose=bool(best["test_return"] > start))
    return result


def summary_numbers(record: dict) -> dict:
    """The numbers a row shows, also stored in the JSON."""
    times = record.get("times", {})
    later = [e["seconds"] for e in (record.get("epochs") or [])[2:]]
    per_epoch = sorted(later)[len(later) // 2] if later else times.get("first_epoch_s")
    return {**_returns(record), "seconds_per_epoch": per_epoch}


def _contacts(model: dict | None) -> str:
    if not model:
        return "-"
    if model.get("contact_disabled"):
        contacts = "off"
    elif "contact_slots" in model:
        contacts = f"{model['contact_slots']}" if model["contact_slots"] else "none"
    else:
        contacts = "?"
    limits = model.get("limit_rows", model.get("limited_joints"))
    return f"{contacts} / {limits if limits else 'none'}"


def _outcome(record: dict) -> str:
    outcome = record.get("outcome", "?")
    reason = (record.get("reason") or "").replace("|", "\\|")
    if outcome == "refused":
        stage = record.get("stage")
        seconds = record.get("times", {}).get("task_s" if stage == "env_task" else "load_s")
        return f"refused by {stage} after {_number(seconds, 0)} s: {reason}"
    if outcome == "trained":
        return f"trained ({record.get('epoch_program')} program)"
    return f"{outcome}: {reason}" if reason else outcome


def render(payload: dict, names: list[str]) -> str:
    settings, machine = payload["settings"], payload["machine"]
    records = payload["envs"]
    order = [n for n in names if n in records] + [n for n in records if n not in names]
    gpus = sorted({r["device"] for r in records.values() if r.get("device", "cpu") != "cpu"})
    device = machine.get("device") or ", ".join(gpus)  # the GPU the environments trained on, if any
    if device:
        where = (f"- Machine: one {device} (JAX's device), {machine['cpu']} with {machine['cores']} cores "
                 f"(CPUs {machine['cpus']}); times are wall times.")
    else:
        where = (f"- CPU: {machine['cpu']}; the survey ran on ONE core (CPU {machine['cpus']}, nice {machine['nice']}) "
                 "beside other work: other work ran on the machine at the same time (not pinned, so at "
                 "times on this core too). Times are wall times of a loaded machine; 'process CPU' against 'process wall' "
                 "in the last table shows the share of the core each environment got.")
    lines = [
        f"# MuJoCo Playground's DeepMind Control Suite through stablebptt on {'one ' + device if device else 'a CPU'}",
        "",
        "Produced by (from the repository root; "
        + ("one invocation" if len(payload["invocations"]) == 1 else
           f"{len(payload['invocations'])} invocations, resumed") + "):",
        "",
    ]
    for invocation in payload["invocations"]:
        lines += ["```", invocation["command"], "```", f"started {invocation['started']}", ""]
    total = sum(records[n].get("wall_s", 0.0) for n in order)
    lines += [
        where,
        f"- Versions: {', '.join(f'{k} {v}' for k, v in payload['versions'].items() if k != 'stablebptt')}.",
        _library_line(records, order),
        f"- Settings: horizon {settings['steps']} steps (BPTT rollout), evaluation episodes of "
        f"{settings['episode_length']} steps, {settings['epochs']} epochs of {settings['train_size']} training "
        f"states in batches of {settings['batch']} ({settings['train_size'] // settings['batch']} updates per epoch), "
        f"{settings['test_size']} test states, mode {settings['mode']}, clip {settings['clip']}, Adam lr "
        f"{settings['lr']:g}, seed {settings['seed']}, zero-output policy start (the library's default), one "
        f"seed; every environment in its own process, at most {settings['timeout']:g} s and "
        f"{settings['max_rss_gb']:g} GB each; cold compiles (no persistent compilation cache).",
        f"- Wall time of the environments' processes together: {total / 60:.1f} min.",
    ] + ([f"- Note: {payload['removed_note']}."] if payload.get("removed_note") else []) + [
        f"- Note: {note}" for note in payload.get("notes", [])] + [

        "",
        "| env | solver iterations | contacts / limits | outcome / why | load s | first update s | compile s "
        "| s/epoch | return at start | return at end (best @ epoch) | rose? |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name in order:
        record = records[name]
        model, times, numbers = record.get("model"), record.get("times", {}), record.get("summary_numbers", {})
        iterations = f"{model['iterations']} ({model['solver']}, ls {model['ls_iterations']})" if model else "-"
        if "final" in numbers:
            end = f"{numbers['final']:.2f} ({numbers['best']:.2f} @ {numbers['best_epoch']})"
            rose = "yes" if numbers["rose"] else ("best only" if numbers["best_rose"] else "no")
        else:
            end, rose = "-", "-"
        start = f"{numbers['start']:.2f}" if "start" in numbers else "-"
        first_update, compile_s = _number(times.get("first_update_s"), 0), _number(times.get("compile_s"), 0)
        if record.get("outcome") in ("timeout", "killed") and "first_update_s" not in times:
            first_update = f"> {record.get('wall_s', 0):.0f}"
            if record.get("phase") == "compiling the epoch":
                compile_s = f"> {record.get('wall_s', 0) - record.get('phase_started_s', 0):.0f}"
        lines.append(f"| {name} | {iterations} | {_contacts(model)} | {_outcome(record)} | "
                     f"{_number(times.get('load_s'))} | {first_update} | "
                     f"{compile_s} | {_number(numbers.get('seconds_per_epoch'))} | "
                     f"{start} | {end} | {rose} |")
    lines += [
        "",
        "Columns:",
        "",
        "- solver iterations: `mj_model.opt.iterations` (solver, line-search iterations).",
        "- contacts / limits: contact slots MJX allocates each step (`make_condim`; 'none': no geom pair can "
        "collide) / joint- and tendon-limit constraint rows.",
        "- load s: `load_env(name)` alone (importing JAX, stablebptt and MuJoCo Playground before it took "
        + _import_range(records) + " more).",
        "- first update s: as `scripts/train.py` reports it: import + load + `env_task` (its reward diagnosis "
        "compiles) + `make_trainer` + init + compiling the epoch + the first epoch's share of one update. "
        "The epoch-0 evaluation (its own compile) is left out.",
        "- compile s: `trainer.epoch.lower(...).compile()` alone (the whole epoch, or for a per-update epoch its "
        "update, evaluation and summary programs).",
        "- s/epoch: median of epochs 2 on (the first epoch where only it ran), each epoch "
        f"{settings['train_size'] // settings['batch']} updates plus the train and test episodes' evaluation.",
        "- return: mean test-set episode return (minus the test loss), `episode_length` steps from fresh resets, "
        "deterministic policy; at start = epoch 0, the policy at initialisation before any update; at end = the "
        "last epoch (best epoch in brackets); rose? = final above start ('best only': some epoch was, the last not).",
        "",
    ]
    details = [n for n in order if records[n].get("outcome") not in ("trained",)]
    if details:
        lines += ["## Refusals, errors and timeouts in full", ""]
        for name in details:
            record = records[name]
            lines.append(f"- **{name}** ({record.get('outcome')}): {record.get('reason', '')}")
            if record.get("traceback"):
                lines += ["", "  ```"] + [f"  {line}" for line in record["traceback"]] + ["  ```", ""]
        lines.append("")
    trained = [n for n in order if "epochs" in records[n] and len(records[n]["epochs"]) > 1]
    if trained:
        lines += ["## Test return per epoch", "",
                  "| env | " + " | ".join(str(e) for e in range(settings["epochs"] + 1)) + " |",
                  "|---|" + "---|" * (settings["epochs"] + 1)]
        for name in trained:
            row = [f"{e['test_return']:.2f}" for e in records[name]["epochs"]]
            row += ["-"] * (settings["epochs"] + 1 - len(row))
            lines.append(f"| {name} | " + " | ".join(row) + " |")
        lines.append("")
    lines += ["## Other times (s)", "",
              "| env | import | load | env_task | make_trainer | compile | eval compile | first epoch | process wall |"
              " process CPU | peak RSS GB | program | reached |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for name in order:
        record = records[name]
        times = record.get("times", {})
        peak = max(record.get("peak_rss_mb", 0.0), record.get("parent_peak_rss_mb", 0.0)) / 1024
        lines.append(f"| {name} | " + " | ".join(_number(times.get(k)) for k in (
            "import_s", "load_s", "task_s", "setup_s", "compile_s", "eval_compile_s", "first_epoch_s"))
            + f" | {_number(record.get('wall_s'))} | {_number(_cpu(record))} | {peak:.1f} | "
            f"{record.get('epoch_program', '-')} | {record.get('phase', '-')} |")
    lines.append("")
    return "\n".join(lines)


def _cpu(record: dict) -> float | None:
    """The worker's CPU seconds: its own count at its end, else what the survey saw of it (before it was stopped)."""
    if record.get("phase") == "done" or record.get("outcome") == "error":
        return max(record.get("cpu_s", 0.0), record.get("parent_cpu_s", 0.0))
    return record.get("parent_cpu_s")  # a stopped worker's own count is that of its last phase's start


def _library_line(records: dict, order: list[str]) -> str:
    """Which state of the library each environment ran on (it may change under a long survey)."""
    groups: dict[str, list[str]] = {}
    for name in order:
        groups.setdefault(records[name].get("library", "unknown"), []).append(name)
    if len(groups) == 1:
        return f"- stablebptt: {next(iter(groups))}."
    return "- stablebptt changed while the survey ran: " + "; ".join(
        f"{version} for {', '.join(names)}" for version, names in groups.items()) + "."


def _import_range(records: dict) -> str:
    values = [r["times"]["import_s"] for r in records.values() if "import_s" in r.get("times", {})]
    return f"{min(values):.0f}-{max(values):.0f} s" if values else "some seconds"


def survey(args, argv: list[str]) -> int:
    out = Path(args.out)
    if out.suffix in (".md", ".json"):
        out = out.with_suffix("")
    json_path, md_path = out.with_suffix(".json"), out.with_suffix(".md")
    if args.envs:
        names = [n for n in args.envs.split(",") if n]
    else:
        from mujoco_playground import dm_control_suite
        names = list(dm_control_suite.ALL_ENVS)
    settings = _settings(args)
    invocation = {"command": _command(argv), "started": datetime.now(timezone.utc).isoformat(timespec="seconds")}
    if args.render_only:
        payload = json.loads(json_path.read_text())
        _write_atomic(md_path, render(payload, names))
        print(f"wrote {md_path}")
        return 0
    if json_path.exists():
        payload = json.loads(json_path.read_text())
        if payload["settings"] != settings:
            changed = sorted(k for k in settings if payload["settings"].get(k) != settings[k])
            print(f"error: {json_path} was made with other settings ({', '.join(changed)}); give another --out",
                  file=sys.stderr)
            return 2
        payload["invocations"].append(invocation)
    else:
        payload = {"settings": settings, "invocations": [invocation], "envs": {},
                   "machine": {"cpu": _cpu_model(), "cpus": ",".join(map(str, sorted(os.sched_getaffinity(0)))),
                               "nice": os.nice(0), "cores": os.cpu_count(), "platform": platform.platform()},
                   "versions": _versions()}
    log_dir = Path(args.log_dir)
    log_dir.mkdir(parents=True, exist_ok=True)
    todo = [n for n in names if n not in payload["envs"]]
    print(f"{len(names) - len(todo)} of {len(names)} environments already in {json_path}; surveying {len(todo)}",
          flush=True)
    for index, name in enumerate(todo, 1):
        print(f"[{index}/{len(todo)}] {name} ...", flush=True)
        record = survey_one(name, args, log_dir)
        record["summary_numbers"] = summary_numbers(record)
        payload["envs"][name] = record
        _write_json(json_path, payload)
        _write_atomic(md_path, render(payload, names))
        numbers = record["summary_numbers"]
        print(f"    {_outcome(record)}; {record['wall_s']:.0f} s; return {numbers.get('start', float('nan')):.3g}"
              f" -> {numbers.get('final', float('nan')):.3g}", flush=True)
    _write_atomic(md_path, render(payload, names))
    print(f"wrote {json_path} and {md_path}")
    return 0


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", default="", help="comma-separated Playground names (default: every env of "
                        "mujoco_playground.dm_control_suite.ALL_ENVS)")
    parser.add_argument("--steps", type=int, default=50, help="BPTT horizon in steps")
    parser.add_argument("--episode-length", type=int, default=200, help="steps of the evaluation episodes")
    parser.add_argument("--epochs", type=int, default=8)
    parser.add_argument("--train-size", type=int, default=16)
    parser.add_argument("--test-size", type=int, default=16)
    parser.add_argument("--batch", type=int, default=8)
    # The modes and clips are checked after parsing, from the library's tables: a worker must not import
    # stablebptt before it times that import.
    parser.add_argument("--mode", default="C", help="gradient flow, as train.py --mode")
    parser.add_argument("--clip", default="norm", help="gradient clipping, as train.py --clip")
    parser.add_argument("--lr", type=float, default=1e-3)
    parser.add_argument("--seed", type=int, default=42, help="network seed")
    parser.add_argument("--timeout", type=float, default=480, help="seconds per environment")
    parser.add_argument("--max-rss-gb", type=float, default=12, help="memory per environment before it is killed")
    parser.add_argument("--out", default=str(DEFAULT_OUT.relative_to(ROOT)) if Path.cwd() == ROOT else str(DEFAULT_OUT),
                        help="path of the results without suffix: OUT.json and OUT.md")
    parser.add_argument("--log-dir", default=os.path.join(tempfile.gettempdir(), "env_survey_logs"),
                        help="each worker's output and last record")
    parser.add_argument("--render-only", action="store_true", help="only render OUT.md from OUT.json")
    parser.add_argument("--worker", default="", help=argparse.SUPPRESS)
    parser.add_argument("--worker-out", default="", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker:
        return worker(args)
    from stablebptt.engine.config import CLIP_MODES
    from stablebptt.flows.modes import MODES
    for option, value, choices in (("--mode", args.mode, MODES), ("--clip", args.clip, CLIP_MODES)):
        if value not in choices:
            parser.error(f"{option} {value!r}: choose one of {', '.join(choices)}")
    if args.train_size % args.batch:
        parser.error("--batch must divide --train-size")
    return survey(args, argv)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
