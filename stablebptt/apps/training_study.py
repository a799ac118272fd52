"""The training study: a short training per mode and precision, test loss against wall-clock seconds.
"""
from __future__ import annotations

import time
from typing import TYPE_CHECKING, Callable

from stablebptt.apps.measuring import PRECISIONS, compile_call, precision

if TYPE_CHECKING:
    from stablebptt.apps.accuracy import AccuracyConfig


def training_task_config(name: str):
    """The training study's configuration of the task ``name``: its studies module's ``training_config``, else
    the defaults."""
    from stablebptt import tasks
    from stablebptt.apps.study_hooks import hook
    module = tasks.load(name)
    configure = hook(name, "training_config")
    return configure(module) if configure is not None else module.Config()


def training_task(name: str):
    """The training study's task (``training_task_config``)."""
    from stablebptt import tasks
    return tasks.load(name).make(training_task_config(name))


def training_study(config: AccuracyConfig, log: Callable) -> list[dict]:
    """Rows (one per mode, precision and epoch): test loss against cumulative wall-clock seconds.

    Float64 starts from the float32 run's data and initial state, upcast, so the
    precisions differ in rounding only (sampling under x64 would draw other numbers).
    """
    import jax
    import jax.numpy as jnp
    import numpy as np

    from stablebptt.engine.config import TrainConfig, seed_array
    from stablebptt.engine.training import make_trainer
    from stablebptt.flows.modes import MODES

    def upcast(tree):  # inside precision(64)
        return jax.tree.map(lambda a: jnp.asarray(a, jnp.float64) if jnp.issubdtype(a.dtype, jnp.floating) else a, tree)

    from stablebptt import tasks
    epochs, size = config.epochs, config.train_size
    setup = tasks.entry(config.train_task).label(training_task_config(config.train_task))  # e.g. "repulsion, rc=0.01"
    runs, rows = {}, []
    for mode in MODES:
        # --no-cosine: each mode computes only the flows it needs, so the times are the modes' own.
        train_config = TrainConfig(mode=mode, epochs=epochs, train_size=size, test_size=size, batch=8,
                                   cosine=False, seed=config.seed + 42)
        for bits in PRECISIONS:
            with precision(bits):
                trainer = make_trainer(training_task(config.train_task), train_config)
                if bits == 32:
                    state32 = trainer.init(seed_array(train_config))
                    data32 = (trainer.batches, trainer.train_states, trainer.test_states)
                state, data = (state32, data32) if bits == 32 else (upcast(state32), upcast(data32))
            epoch, compile_seconds = compile_call(trainer.epoch, (state,) + data, bits)
            with precision(bits):
                untrained = float(trainer.evaluate(state.params, data[2])[0])
            runs[mode, bits] = {"epoch": epoch.function, "state": state, "data": data, "seconds": 0.0, "compile_s": compile_seconds}
            rows.append({"task": config.train_task, "setup": setup, "mode": mode, "precision": f"float{bits}", "epoch": 0, "seconds": 0.0,
                         "test_loss": untrained, "train_loss": float("nan"), "finite": True, "compile_s": compile_seconds})
            log(f"  training {mode} float{bits}: compiled in {compile_seconds:.1f} s")
    for number in range(1, epochs + 1):
        for (mode, bits), run in runs.items():  # round-robin: drift of the machine hits every mode alike
            with precision(bits):
                started = time.perf_counter()
                state, metrics = run["epoch"](run["state"], *run["data"])
                metrics = jax.device_get(metrics)
                run["seconds"] += time.perf_counter() - started
            run["state"] = state
            rows.append({"task": config.train_task, "setup": setup, "mode": mode, "precision": f"float{bits}", "epoch": number,
                         "seconds": run["seconds"], "test_loss": float(np.asarray(metrics["test_loss"])[0]),
                         "train_loss": float(np.asarray(metrics["train_loss"])[0]),
                         "finite": bool(np.asarray(metrics["finite"])[0]), "compile_s": run["compile_s"]})
        if number % 25 == 0 or number == epochs:
            log(f"  training epoch {number}/{epochs}")
    return rows
