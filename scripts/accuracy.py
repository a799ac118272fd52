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

import sys
from pathlib import Path


import csv
import dataclasses
import io
import platform
import time
from dataclasses import dataclass, field
from typing import Any, Callable, NamedTuple

from stablebptt.cli import fail, parse_config

STUDIES = ("trajectory", "gradients", "training")
TASKS = ("cartpole", "repulsion", "quantum")
PRECISIONS = (32, 64)
CARTPOLE_DURATION, REPULSION_DURATION = 1.0, 4.0
QUANTUM_DURATION = 128 * 0.0625  # the paper's 128 steps of 0.0625


@dataclass(frozen=True)
class AccuracyConfig:
    """Options of the accuracy study."""

    tasks: str = field(default="cartpole,repulsion,quantum", metadata={"help": "comma-separated tasks of the trajectory and gradient studies"})
    studies: str = field(default="trajectory,gradients,training", metadata={"help": "comma-separated studies: trajectory, gradients, training"})
    poles: int = field(default=1, metadata={"help": "poles of the cart-pole in the trajectory study (1-4)"})
    gradient_poles: int = field(default=4, metadata={"help": "poles of the cart-pole in the gradient study (1-4)"})
    batch: int = field(default=8, metadata={"help": "trajectories per rollout and gradient"})
    rounds: int = field(default=20, metadata={"help": "timed rounds per variant (median reported)"})
    train_task: str = field(default="repulsion", metadata={"help": "task of the training study", "choices": TASKS})
    epochs: int = field(default=150, metadata={"help": "epochs per mode in the training study"})
    train_size: int = field(default=64, metadata={"help": "training initial states in the training study"})
    seed: int = field(default=0, metadata={"help": "seed of the initial states, controls and parameters"})
    quick: bool = field(default=False, metadata={"help": "a small smoke version: few time steps, short horizons, 3 epochs"})
    replot: bool = field(default=False, metadata={"help": "only redraw the figures and summary.md from the CSVs in --out"})
    out: str = field(default="results/accuracy", metadata={"help": "directory for the CSVs, figures and summary.md"})

    @property
    def task_list(self) -> list[str]:
        return [name for name in self.tasks.split(",") if name]

    @property
    def study_list(self) -> list[str]:
        return [name for name in self.studies.split(",") if name]


# ----------------------------------------------------------------------------- shared helpers

def precision(bits: int):
    """Context in which arrays, models and traces are float32 (32) or float64 (64)."""
    import jax
    return jax.enable_x64(bits == 64)


def cast(tree: Any, bits: int) -> Any:
    """A NumPy/JAX pytree as JAX arrays of the given float width; call inside ``precision(bits)``."""
    import jax
    import jax.numpy as jnp
    import numpy as np
    dtype = jnp.float64 if bits == 64 else jnp.float32
    return jax.tree.map(lambda a: jnp.asarray(np.asarray(a), dtype), tree)


def to_numpy(tree: Any) -> Any:
    import jax
    import numpy as np
    return jax.tree.map(lambda a: np.asarray(a, np.float64), tree)


def flat_states(tree: Any) -> "np.ndarray":
    """A batch of states (any pytree, leading axis = batch) as float64 rows [batch, numbers]."""
    import jax
    import numpy as np
    leaves = [np.asarray(leaf, np.float64) for leaf in jax.tree.leaves(tree)]
    return np.concatenate([leaf.reshape(len(leaf), -1) for leaf in leaves], axis=1)


class Call(NamedTuple):
    """A compiled executable, its arguments and the precision it runs in."""

    function: Callable
    arguments: tuple
    bits: int


_traced_in = {"bits": None}


def compile_call(function: Callable, arguments: tuple, bits: int) -> tuple[Call, float]:
    """Compile ``function`` (jitted) for ``arguments`` ahead of time; returns the call and the compile seconds.

    JAX's trace caches do not tell float32 from float64 everywhere: an inner
    jitted helper traced in one precision (``jnp.tril`` inside MJX's RK4) is
    reused in the other and fails to lower. The caches are therefore cleared
    whenever the precision changes; compiled executables do not depend on them.
    """
    import jax
    if _traced_in["bits"] not in (None, bits):
        jax.clear_caches()
    _traced_in["bits"] = bits
    from stablebptt import timing
    with precision(bits):
        compiled, seconds = timing.compile_ahead(function, *arguments)
        return Call(compiled, arguments, bits), seconds


def run_once(call: Call) -> tuple[Any, float]:
    """Run a compiled call; returns the result and the seconds it took."""
    from stablebptt import timing
    with precision(call.bits):
        return timing.timed(lambda: call.function(*call.arguments))


def time_round_robin(calls: dict, rounds: int) -> dict:
    """Median seconds per call of already compiled ``calls``, one call of each per round."""
    from stablebptt import timing
    return timing.round_robin({key: (lambda call=call: run_once(call)[0]) for key, call in calls.items()}, rounds, warmup=0)


def policy_params(task, seed: int) -> Any:
    """Float32 Glorot parameters, output layer included (a zero output layer would make R equal M)."""
    import jax
    with precision(32):
        return to_numpy(task.init_params(jax.random.PRNGKey(seed), False))


def write_csv(path: Path, rows: list[dict]) -> None:
    """A tidy CSV, one row per measurement; floats in full precision."""
    from stablebptt.runs import atomic_write
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=list(rows[0]), lineterminator="\n")
    writer.writeheader()
    writer.writerows([{k: repr(v) if isinstance(v, float) else v for k, v in row.items()} for row in rows])
    atomic_write(path, text.getvalue().encode())


def markdown_table(header: list[str], rows: list[list[str]]) -> list[str]:
    """Markdown lines; columns whose first cell starts with a digit are right-aligned."""
    align = ["---:" if rows and rows[0][i][:1].isdigit() else "---" for i in range(len(header))]
    return ["| " + " | ".join(header) + " |", "| " + " | ".join(align) + " |"] + ["| " + " | ".join(r) + " |" for r in rows]


def sci(value: float, digits: int = 2) -> str:
    import math
    return "n/a" if not math.isfinite(value) else f"{value:.{digits - 1}e}"


def fixed(value: float, decimals: int) -> str:
    """A number with ``decimals`` decimals; empty where it was not measured (NaN)."""
    import math
    return "" if math.isnan(value) else f"{value:.{decimals}f}"


# ----------------------------------------------------------------------------- trajectory study

@dataclass(frozen=True)
class TrajectorySetup:
    """One task's side of the trajectory study.

    Attributes:
      task: registry name.
      label: the set-up in words (for tables and plots).
      duration: simulated time of every rollout.
      integrators: the schemes compared.
      dts: the time steps, each dividing ``duration`` into whole steps.
      paper: the paper's (integrator, dt), the baseline of the cost ratios.
      make_task: ``make_task(integrator, dt) -> Task``; call inside the precision wanted (MJX bakes it into the model).
      controls: ``controls(rng, batch)``: one fixed control per trajectory, held for the whole rollout.
      reference: ``reference(initial_states, controls) -> (final states [batch, numbers], description)`` in float64.
    """

    task: str
    label: str
    duration: float
    integrators: tuple[str, ...]
    dts: tuple[float, ...]
    paper: tuple[str, float]
    make_task: Callable
    controls: Callable
    reference: Callable


def rollout_program(step: Callable, steps: int) -> Callable:
    """Jitted ``(initial states [B], controls [B]) -> final states [B]`` holding each control for ``steps`` steps."""
    import jax
    batch_step = jax.vmap(step)

    def rollout(initial_states, controls):
        return jax.lax.scan(lambda state, _: (batch_step(state, controls), None), initial_states, None, length=steps)[0]

    return jax.jit(rollout)


def cartpole_setup(poles: int, quick: bool) -> TrajectorySetup:
    from stablebptt.tasks import cartpole, cartpole_equations
    reference_dt = 1e-4

    def make_task(integrator, dt):
        return cartpole.make(cartpole.Config(poles=poles, integrator=integrator, dt=dt))

    def controls(rng, batch):
        return rng.uniform(-2.0, 2.0, (batch, 1))  # a constant force on the cart, in newtons

    def reference(initial_states, forces):
        import jax.numpy as jnp
        from stablebptt.integrators import rk4
        from stablebptt.scene import State
        steps = round(CARTPOLE_DURATION / reference_dt)
        with precision(64):
            arguments = (cast(initial_states, 64), cast(forces, 64))
            mjx_step = make_task("rk4", reference_dt).dynamics.step
        mjx_final = run_once(compile_call(rollout_program(mjx_step, steps), arguments, 64)[0])[0]
        # Independent check: RK4 of the closed-form rigid-body equations at the same step.
        derivative = lambda s, f: State(s.qvel, cartpole_equations.exact_accelerations(s, f[0]), jnp.zeros_like(s.act))
        closed_final = run_once(compile_call(rollout_program(rk4(derivative, reference_dt), steps), arguments, 64)[0])[0]
        mjx_final, closed_final = flat_states(mjx_final), flat_states(closed_final)
        agreement = float(abs(mjx_final - closed_final).max())
        return mjx_final, (f"float64 MJX RK4 at dt {reference_dt:g} ({steps} steps); RK4 of the closed-form "
                           f"equations at the same dt agrees to {agreement:.1e}")

    dts = (0.02, 0.01, 0.005) if quick else (0.02, 0.01, 0.005, 0.0025, 0.001)
    label = f"Cart-pole (MJX), {poles} pole{'s' if poles > 1 else ''}"
    return TrajectorySetup("cartpole", label, CARTPOLE_DURATION, ("euler", "implicitfast", "rk4"), dts, ("euler", 0.01),
                           make_task, controls, reference)


def repulsion_setup(quick: bool) -> TrajectorySetup:
    from stablebptt.tasks import repulsion

    def make_task(integrator, dt):
        return repulsion.make(repulsion.Config(integrator=integrator, steps=round(REPULSION_DURATION / dt)))

    def controls(rng, batch):
        return rng.uniform(-1.0, 1.0, (batch, 4))  # (c0, c1) per driver; c0 < 0 pulls a driver through the evaders

    def reference(initial_states, coefficients):
        finals = []
        with precision(64):
            arguments = (cast(initial_states, 64), cast(coefficients, 64))
        for steps in (7680, 15360):
            step = make_task("rk4", REPULSION_DURATION / steps).dynamics.step
            finals.append(flat_states(run_once(compile_call(rollout_program(step, steps), arguments, 64)[0])[0]))
        agreement = float(abs(finals[0] - finals[1]).max())
        return finals[1], (f"float64 RK4 with 15360 steps (dt {REPULSION_DURATION / 15360:.2g}); "
                           f"half as many steps agree to {agreement:.1e}")

    steps = (30, 60, 120) if quick else (30, 60, 120, 240, 480, 960)
    return TrajectorySetup("repulsion", "Repulsion", REPULSION_DURATION, ("euler", "rk4"),
                           tuple(REPULSION_DURATION / s for s in steps), ("euler", REPULSION_DURATION / 60),
                           make_task, controls, reference)


def quantum_setup(quick: bool) -> TrajectorySetup:
    from stablebptt.tasks import quantum
    physics = quantum.Physics()

    def make_task(integrator, dt):
        del integrator  # Crank-Nicolson is the task's only scheme
        return quantum.make(quantum.Config(dt=dt, steps=round(QUANTUM_DURATION / dt)))

    def controls(rng, batch):
        return rng.uniform(-5.0, 5.0, batch)  # tilts comparable to the level spacing

    def reference(initial_states, tilts):
        import numpy as np
        # A constant control makes H constant: psi(T) = V exp(-i Lambda T) V^T psi(0), exactly (float64 LAPACK).
        n, dx = physics.nx, physics.dx
        laplacian = (np.diag(np.full(n, -2.0)) + np.diag(np.ones(n - 1), 1) + np.diag(np.ones(n - 1), -1)) / dx**2
        psi0 = initial_states[..., 0] + 1j * initial_states[..., 1]
        finals = []
        for psi, u in zip(psi0, tilts):
            energies, vectors = np.linalg.eigh(-laplacian + u * np.diag(physics.grid))
            psi_t = vectors @ (np.exp(-1j * energies * QUANTUM_DURATION) * (vectors.T @ psi))
            finals.append(np.stack([psi_t.real, psi_t.imag], axis=-1).reshape(-1))
        return np.array(finals), "exact solution of the semi-discrete equation (eigenvectors of H, float64)"

    steps = (32, 128, 512) if quick else (32, 64, 128, 256, 512, 1024, 2048)
    return TrajectorySetup("quantum", "Quantum", QUANTUM_DURATION, ("crank-nicolson",),
                           tuple(QUANTUM_DURATION / s for s in steps), ("crank-nicolson", 0.0625),
                           make_task, controls, reference)


def trajectory_setups(config: AccuracyConfig) -> list[TrajectorySetup]:
    makers = {"cartpole": lambda: cartpole_setup(config.poles, config.quick),
              "repulsion": lambda: repulsion_setup(config.quick),
              "quantum": lambda: quantum_setup(config.quick)}
    return [makers[name]() for name in config.task_list]


def trajectory_study(setup: TrajectorySetup, config: AccuracyConfig, log: Callable) -> list[dict]:
    """Rows (one per integrator, dt and precision): final-state error and time per simulated second."""
    import jax
    import numpy as np
    from stablebptt.flows import flow_gradients

    rng = np.random.default_rng(config.seed)
    with precision(64):  # float64 initial states; float32 runs start from their rounding
        paper_task = setup.make_task(*setup.paper)
        initial_states = to_numpy(paper_task.sample_initial_states(jax.random.PRNGKey(config.seed), config.batch))
    controls = setup.controls(rng, config.batch)
    reference, description = setup.reference(initial_states, controls)
    log(f"{setup.task}: reference = {description}")

    forward, gradient, meta = {}, {}, {}
    params = policy_params(paper_task, config.seed)
    for integrator in setup.integrators:
        for dt in setup.dts:
            steps = round(setup.duration / dt)
            for bits in PRECISIONS:
                key = (integrator, dt, bits)
                with precision(bits):
                    task = setup.make_task(integrator, dt)
                    arguments = (cast(initial_states, bits), cast(controls, bits))
                    gradient_arguments = (cast(params, bits), cast(initial_states, bits))
                call, compile_seconds = compile_call(rollout_program(task.dynamics.step, steps), arguments, bits)
                if dt == setup.paper[1]:
                    # What a training update costs: the task's own loss, horizon and policy.
                    grad = jax.jit(lambda p, x, d=task.dynamics: flow_gradients(d, ("R",), p, x))
                    gradient[key] = compile_call(grad, gradient_arguments, bits)[0]
                final = run_once(call)[0]
                error = float(np.max(np.abs(flat_states(final) - reference)))
                forward[key] = call
                meta[key] = dict(steps=steps, error=error, compile_s=compile_seconds)
                log(f"  {integrator:14s} dt {dt:<8.4g} float{bits}: error {error:.2e}  (compiled in {compile_seconds:.1f} s)")
    forward_seconds = time_round_robin(forward, config.rounds)
    gradient_seconds = time_round_robin(gradient, max(3, config.rounds // 3))

    baseline = forward_seconds[setup.paper + (32,)]
    rows = []
    for key, seconds in forward_seconds.items():
        integrator, dt, bits = key
        rows.append({
            "task": setup.task, "setup": setup.label, "integrator": integrator, "precision": f"float{bits}", "dt": dt,
            "steps": meta[key]["steps"], "paper_dt": setup.paper[1], "simulated_time": setup.duration, "batch": config.batch,
            "error": meta[key]["error"],
            "ms_per_simulated_second": 1e3 * seconds / setup.duration,
            "ms_per_step": 1e3 * seconds / meta[key]["steps"],
            "cost_vs_paper": seconds / baseline,
            "gradient_ms_per_simulated_second": 1e3 * gradient_seconds[key] / setup.duration if key in gradient else float("nan"),
            "compile_s": meta[key]["compile_s"],
            "reference": description,
        })
    return rows


# ----------------------------------------------------------------------------- gradient study

@dataclass(frozen=True)
class GradientSetup:
    """One task's side of the gradient study.

    Attributes:
      task: registry name.
      label: the set-up in words (for tables and plots).
      make_task: ``make_task() -> Task`` at the paper's time step; call inside the precision wanted.
      dt: its time step.
      horizons: rollout lengths in steps, each compiled in float32 and float64.
      regimes: name -> transform of the float64 initial states (a NumPy pytree).
    """

    task: str
    label: str
    make_task: Callable
    dt: float
    horizons: tuple[int, ...]
    regimes: dict


def gradient_setups(config: AccuracyConfig) -> list[GradientSetup]:
    from stablebptt.tasks import cartpole, quantum, repulsion

    def upright(states):
        # Angles 0 +- 30 degrees instead of pi +- 30: the poles fall and tumble, a chaotic motion.
        qpos = states.qpos.copy()
        qpos[:, 1:] -= 3.141592653589793
        return states._replace(qpos=qpos)

    quick = config.quick
    setups = {
        "cartpole": GradientSetup(
            "cartpole", f"cart-pole, {config.gradient_poles} poles, MJX Euler",
            lambda: cartpole.make(cartpole.Config(poles=config.gradient_poles)), 0.01,
            (20, 60) if quick else (100, 200, 300, 500, 1000, 2000, 3000),
            {"hanging (paper)": lambda s: s, "upright": upright}),
        "repulsion": GradientSetup(
            "repulsion", "repulsion, explicit Euler", lambda: repulsion.make(repulsion.Config()), REPULSION_DURATION / 60,
            (20, 60) if quick else (100, 300, 1000), {"paper": lambda s: s}),
        "quantum": GradientSetup(
            "quantum", "quantum, Crank-Nicolson", lambda: quantum.make(quantum.Config()), 0.0625,
            (20, 60) if quick else (100, 300, 1000), {"paper": lambda s: s}),
    }
    return [setups[name] for name in config.task_list]


def tree_norm(tree) -> float:
    import jax
    import numpy as np
    return float(np.sqrt(sum(np.sum(np.asarray(leaf, np.float64) ** 2) for leaf in jax.tree.leaves(tree))))


def gradient_study(setup: GradientSetup, config: AccuracyConfig, log: Callable) -> list[dict]:
    """Rows (one per regime, horizon, flow and precision): gradient norm, and float32's error against float64."""
    import jax
    import numpy as np
    from stablebptt.flows import flow_gradients

    flows = ("R", "M")
    with precision(64):
        base = setup.make_task()
        sampled = to_numpy(base.sample_initial_states(jax.random.PRNGKey(config.seed + 1), config.batch))
    params = policy_params(base, config.seed)
    regimes = {name: transform(sampled) for name, transform in setup.regimes.items()}
    results, rows = {}, []
    for horizon in setup.horizons:
        for bits in PRECISIONS:
            with precision(bits):
                task = setup.make_task()
                dynamics = dataclasses.replace(task.dynamics, horizon=horizon)
                program = jax.jit(lambda p, x, d=dynamics: flow_gradients(d, flows, p, x))
                arguments = {regime: (cast(params, bits), cast(states, bits)) for regime, states in regimes.items()}
            compiled = None
            for regime, regime_arguments in arguments.items():
                if compiled is None:  # one executable serves every regime: same shapes
                    compiled, compile_seconds = compile_call(program, regime_arguments, bits)
                call = compiled._replace(arguments=regime_arguments)
                loss, grads = run_once(call)[0]
                seconds = min(run_once(call)[1] for _ in range(3))
                grads = to_numpy(grads)
                results[regime, horizon, bits] = grads
                for index, flow in enumerate(flows):
                    grad = jax.tree.map(lambda a: a[index], grads)
                    finite = all(np.all(np.isfinite(leaf)) for leaf in jax.tree.leaves(grad))
                    rows.append({
                        "task": setup.task, "setup": setup.label, "regime": regime, "horizon": horizon,
                        "simulated_time": horizon * setup.dt, "flow": flow, "precision": f"float{bits}",
                        "loss": float(loss), "norm": tree_norm(grad), "finite": finite,
                        "relative_error_vs_float64": float("nan"), "ms_per_gradient": 1e3 * seconds,
                    })
            log(f"  {setup.task} horizon {horizon:5d} float{bits}: compiled in {compile_seconds:.1f} s, "
                f"{1e3 * seconds:.0f} ms per R+M gradient (batch {config.batch})")
    for row in rows:
        if row["precision"] == "float32":
            index = flows.index(row["flow"])
            g32, g64 = (jax.tree.map(lambda a: a[index], results[row["regime"], row["horizon"], bits]) for bits in PRECISIONS)
            row["relative_error_vs_float64"] = tree_norm(jax.tree.map(np.subtract, g32, g64)) / tree_norm(g64)
    return rows


def growth_rows(rows: list[dict]) -> list[dict]:
    """Fit log ||g|| = a + lambda t over the horizons of each (task, regime, flow, precision)."""
    import numpy as np
    groups = {}
    for row in rows:
        groups.setdefault((row["task"], row["setup"], row["regime"], row["flow"], row["precision"]), []).append(row)
    fits = []
    for (task, label, regime, flow, bits), members in groups.items():
        members = [m for m in members if m["finite"] and m["norm"] > 0]
        if len(members) < 2:
            continue
        t = np.array([m["simulated_time"] for m in members])
        log_norm = np.log([m["norm"] for m in members])
        slope, intercept = np.polyfit(t, log_norm, 1)
        residual = log_norm - (intercept + slope * t)
        fits.append({"task": task, "setup": label, "regime": regime, "flow": flow, "precision": bits,
                     "exponent_per_simulated_second": float(slope), "intercept": float(intercept),
                     "rms_residual": float(np.sqrt(np.mean(residual**2))),
                     "t_min": float(t.min()), "t_max": float(t.max()), "points": len(members),
                     "norm_min": float(np.exp(log_norm.min())), "norm_max": float(np.exp(log_norm.max()))})
    return fits


# ----------------------------------------------------------------------------- training study

def training_task(name: str):
    """The training study's task: repulsion at rc 0.01 (where the paper's modes differ most), else the defaults."""
    from stablebptt import tasks
    module = tasks.load(name)
    return module.make(module.Config(rc=0.01) if name == "repulsion" else module.Config())


def training_study(config: AccuracyConfig, log: Callable) -> list[dict]:
    """Rows (one per mode, precision and epoch): test loss against cumulative wall-clock seconds.

    Float64 starts from the float32 run's data and initial state, upcast, so the
    precisions differ in rounding only (sampling under x64 would draw other numbers).
    """
    import jax
    import jax.numpy as jnp
    import numpy as np
    from stablebptt.flows import MODES
    from stablebptt.training import TrainConfig, make_trainer, seed_array

    def upcast(tree):  # inside precision(64)
        return jax.tree.map(lambda a: jnp.asarray(a, jnp.float64) if jnp.issubdtype(a.dtype, jnp.floating) else a, tree)

    epochs, size = config.epochs, config.train_size
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
            rows.append({"task": config.train_task, "mode": mode, "precision": f"float{bits}", "epoch": 0, "seconds": 0.0,
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
            rows.append({"task": config.train_task, "mode": mode, "precision": f"float{bits}", "epoch": number,
                         "seconds": run["seconds"], "test_loss": float(np.asarray(metrics["test_loss"])[0]),
                         "train_loss": float(np.asarray(metrics["train_loss"])[0]),
                         "finite": bool(np.asarray(metrics["finite"])[0]), "compile_s": run["compile_s"]})
        if number % 25 == 0 or number == epochs:
            log(f"  training epoch {number}/{epochs}")
    return rows


# ----------------------------------------------------------------------------- figures

# Okabe-Ito colours: distinguishable with colour blindness.
INTEGRATOR_COLORS = {"euler": "#0072B2", "implicitfast": "#009E73", "rk4": "#D55E00", "crank-nicolson": "#CC79A7"}
INTEGRATOR_NAMES = {"euler": "Euler", "implicitfast": "implicitfast", "rk4": "RK4", "crank-nicolson": "Crank-Nicolson"}
PRECISION_STYLES = {"float32": ("--", "s", False), "float64": ("-", "o", True)}  # line, marker, filled
SERIES_COLORS = ("#0072B2", "#D55E00", "#009E73", "#CC79A7", "#E69F00", "#56B4E9")
FLOW_STYLES = {"R": ("-", "o", True), "M": (":", "^", False)}


def _figure(width: float, height: float):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    figure = Figure(figsize=(width, height), layout="constrained")
    FigureCanvasAgg(figure)  # headless: never touches pyplot or a display
    return figure


def _log_axes(ax, x: bool = True) -> None:
    from matplotlib.ticker import NullFormatter
    if x:
        ax.set_xscale("log")
    ax.set_yscale("log")
    ax.yaxis.set_minor_formatter(NullFormatter())  # no 4x10^-1 clutter on short axes
    ax.grid(True, which="major", alpha=0.35)
    ax.grid(True, which="minor", alpha=0.1)


def _plain_log_ticks(axis, values) -> None:
    """Ticks at ``values`` written as plain numbers (100, 0.5) on a log axis."""
    from matplotlib.ticker import FixedLocator, FuncFormatter, NullFormatter, NullLocator
    axis.set_major_locator(FixedLocator(list(values)))
    axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    axis.set_minor_locator(NullLocator())
    axis.set_minor_formatter(NullFormatter())


def _marker_style(colour: str, filled: bool) -> dict:
    return dict(marker=None, color=colour, markerfacecolor=colour if filled else "white", markeredgecolor=colour,
                markeredgewidth=1.4, markersize=7)


def _pareto(points: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """The points no other point beats in both time and error, sorted by time."""
    front, best = [], float("inf")
    for seconds, error in sorted(points):
        if error < best:
            front.append((seconds, error))
            best = error
    return front


def trajectory_figure(rows: list[dict]):
    """Error at the final time against ms per simulated second, one log-log panel per task, dt labelled."""
    import math
    from matplotlib.lines import Line2D

    setups = list(dict.fromkeys(row["setup"] for row in rows))
    figure = _figure(5.4 * len(setups), 5.2)
    axes = figure.subplots(1, len(setups), squeeze=False)[0]
    for ax, setup in zip(axes, setups):
        task_rows = [r for r in rows if r["setup"] == setup and math.isfinite(r["error"]) and r["error"] > 0]
        front = _pareto([(r["ms_per_simulated_second"], r["error"]) for r in task_rows])
        if front:
            xs, ys = zip(*front)
            ax.step(xs, ys, where="post", color="0.6", linewidth=6, alpha=0.22, zorder=0, solid_capstyle="round")
        labelled = []  # (log x, log y, text) of the dt labels drawn: Euler and implicitfast coincide on the cart-pole
        for integrator, bits in dict.fromkeys((r["integrator"], r["precision"]) for r in task_rows):
            series = sorted((r for r in task_rows if (r["integrator"], r["precision"]) == (integrator, bits)), key=lambda r: -r["dt"])
            linestyle, marker, filled = PRECISION_STYLES[bits]
            colour = INTEGRATOR_COLORS[integrator]
            ax.plot([r["ms_per_simulated_second"] for r in series], [r["error"] for r in series], linestyle=linestyle,
                    linewidth=1.4, **{**_marker_style(colour, filled), "marker": marker})
            for r in series if bits == "float64" else ():  # float32 shares the time steps
                x, y, text = math.log10(r["ms_per_simulated_second"]), math.log10(r["error"]), f"{r['dt']:.3g}"
                # Skip a label that would overlap one drawn, or repeat its dt at about the same error.
                if not any(abs(y - y0) < 0.25 and (abs(x - x0) < 0.25 or text == text0) for x0, y0, text0 in labelled):
                    labelled.append((x, y, text))
                    ax.annotate(text, (r["ms_per_simulated_second"], r["error"]), textcoords="offset points",
                                xytext=(6, 4), fontsize=7.5, color=colour)
        ax.set_title(f"{setup}, batch {task_rows[0]['batch']}, T = {task_rows[0]['simulated_time']:g}", fontsize=11)
        ax.set_xlabel("wall time per simulated second [ms] (forward rollout)")
        ax.set_ylabel("max |state - reference| at T")
        reference = task_rows[0]["reference"].split(";")[0]
        ax.annotate(f"reference: {reference}", xy=(0.5, 0), xycoords="axes fraction", xytext=(0, -34),
                    textcoords="offset points", ha="center", va="top", fontsize=8, color="0.35")
        _log_axes(ax)
    integrators = list(dict.fromkeys(r["integrator"] for r in rows))
    handles = [Line2D([], [], color=INTEGRATOR_COLORS[i], linewidth=2.2, label=INTEGRATOR_NAMES[i]) for i in integrators]
    for bits, (linestyle, marker, filled) in PRECISION_STYLES.items():
        handles.append(Line2D([], [], linestyle=linestyle, label=bits, **{**_marker_style("0.3", filled), "marker": marker}))
    handles.append(Line2D([], [], color="0.6", linewidth=6, alpha=0.3, label="Pareto front"))
    figure.legend(handles=handles, loc="outside lower center", ncol=len(handles), frameon=False)
    figure.suptitle("Trajectory error against cost (one constant control per trajectory); labels: time step dt", fontsize=12)
    return figure


def gradient_figure(rows: list[dict], fits: list[dict]):
    """(a) float32 error of the R and M gradients against the horizon; (b) ||g|| against simulated time."""
    from matplotlib.lines import Line2D

    figure = _figure(13, 5.6)
    left, right = figure.subplots(1, 2)
    series = list(dict.fromkeys((r["setup"], r["regime"]) for r in rows))
    exponent = {(f["setup"], f["regime"], f["flow"]): f["exponent_per_simulated_second"] for f in fits if f["precision"] == "float64"}
    handles = []
    for colour, (label, regime) in zip(SERIES_COLORS, series):
        for flow, (linestyle, marker, filled) in FLOW_STYLES.items():
            members = sorted((r for r in rows if (r["setup"], r["regime"], r["flow"]) == (label, regime, flow)), key=lambda r: r["horizon"])
            style = {**_marker_style(colour, filled), "marker": marker, "linestyle": linestyle, "linewidth": 1.5}
            f32 = [r for r in members if r["precision"] == "float32"]
            left.plot([r["horizon"] for r in f32], [max(r["relative_error_vs_float64"], 1e-17) for r in f32], **style)
            f64 = [r for r in members if r["precision"] == "float64"]
            right.plot([r["simulated_time"] for r in f64], [r["norm"] for r in f64], **style)
        rates = ", ".join(f"{flow} {exponent[label, regime, flow]:+.2f}" for flow in FLOW_STYLES if (label, regime, flow) in exponent)
        handles.append(Line2D([], [], color=colour, linewidth=2.2, label=f"{label}, {regime} (fitted growth per s: {rates})"))
    for flow, (linestyle, marker, filled) in FLOW_STYLES.items():
        handles.append(Line2D([], [], linestyle=linestyle, label=f"{flow} gradient", **{**_marker_style("0.3", filled), "marker": marker}))
    left.axhline(1.0, color="0.5", linewidth=0.8, zorder=0)
    left.set_xlabel("horizon [steps]")
    left.set_ylabel(r"$\|g_{32} - g_{64}\| \,/\, \|g_{64}\|$")
    left.set_title("(a) Float32 gradient error against float64")
    right.set_xlabel("simulated time of the horizon [s]")
    right.set_ylabel(r"$\|g\|$ (float64), mean over the batch")
    right.set_title(r"(b) Gradient norm: growth $\propto e^{\lambda t}$, $\lambda$ fitted")
    _log_axes(left)
    _plain_log_ticks(left.xaxis, sorted({r["horizon"] for r in rows}))
    _log_axes(right, x=False)
    figure.legend(handles=handles, loc="outside lower center", ncol=2, frameon=False, fontsize=9)
    figure.suptitle("Gradients w.r.t. the policy parameters (Glorot-initialised policy)", fontsize=12)
    return figure


def training_figure(rows: list[dict]):
    """Test loss against cumulative wall-clock seconds per mode (colour) and precision (line style)."""
    import numpy as np
    from stablebptt.plots import MODE_COLORS, MODE_ORDER

    figure = _figure(7.8, 5.2)
    ax = figure.subplots()
    for mode in MODE_ORDER:
        for bits in PRECISION_STYLES:
            members = sorted((r for r in rows if r["mode"] == mode and r["precision"] == bits), key=lambda r: r["epoch"])
            if members:
                flat = " (loss never moves)" if len({r["test_loss"] for r in members}) == 1 else ""
                ax.plot([r["seconds"] for r in members], [r["test_loss"] for r in members], color=MODE_COLORS[mode],
                        linestyle=PRECISION_STYLES[bits][0], linewidth=1.6, label=f"{mode}, {bits}{flat}")
    ax.set_yscale("log")
    losses = [r["test_loss"] for r in rows if r["test_loss"] > 0]
    subs = range(1, 10) if max(losses) < 10 * min(losses) else (1, 2, 5)  # about five labels either way
    ticks = [v for v in np.outer(10.0 ** np.arange(-6, 7), subs).ravel() if min(losses) / 1.2 <= v <= max(losses) * 1.2]
    _plain_log_ticks(ax.yaxis, ticks)
    ax.grid(True, which="major", alpha=0.3)
    ax.set_xlabel("wall-clock seconds of training (compilation excluded)")
    ax.set_ylabel("test loss")
    epochs = max(r["epoch"] for r in rows)
    ax.set_title(f"{rows[0]['task']}: test loss against training time, {epochs} epochs per curve", fontsize=11)
    ax.legend(ncol=2, frameon=False, fontsize=9)
    return figure


# ----------------------------------------------------------------------------- tables

def trajectory_tables(rows: list[dict]) -> tuple[list[str], list[str]]:
    """(key table: the paper's time step plus each scheme's best, full table)."""
    import math
    key, full = [], []
    for row in rows:
        full.append([row["task"], INTEGRATOR_NAMES[row["integrator"]], row["precision"], f"{row['dt']:.4g}", str(row["steps"]),
                     sci(row["error"]), fixed(row["ms_per_simulated_second"], 2), fixed(row["cost_vs_paper"], 2),
                     fixed(row["gradient_ms_per_simulated_second"], 1)])
    groups = dict.fromkeys((r["task"], r["integrator"], r["precision"]) for r in rows)
    for task, integrator, bits in groups:
        members = [r for r in rows if (r["task"], r["integrator"], r["precision"]) == (task, integrator, bits)]
        at_paper = next((r for r in members if r["dt"] == r["paper_dt"]), None)
        finite = [r for r in members if math.isfinite(r["error"])]
        best = min(finite, key=lambda r: r["error"]) if finite else None
        if at_paper is None or best is None:
            continue
        key.append([task, INTEGRATOR_NAMES[integrator], bits, f"{at_paper['dt']:.4g}", sci(at_paper["error"]),
                    fixed(at_paper["cost_vs_paper"], 2), fixed(at_paper["gradient_ms_per_simulated_second"], 1),
                    f"{sci(best['error'])} at dt {best['dt']:.3g}", fixed(best["cost_vs_paper"], 1)])
    key_table = markdown_table(["task", "integrator", "precision", "dt", "error at T", "cost x", "R gradient ms / sim. s",
                                "smallest error", "its cost x"], key)
    full_table = markdown_table(["task", "integrator", "precision", "dt", "steps", "error at T", "ms / simulated s",
                                 "cost x", "R gradient ms / sim. s"], full)
    return key_table, full_table


def gradient_tables(rows: list[dict], fits: list[dict]) -> tuple[list[str], list[str]]:
    """(float32 error and norms per horizon, growth exponents)."""
    lines = []
    index = {(r["task"], r["regime"], r["horizon"], r["flow"], r["precision"]): r for r in rows}
    for task, label, regime, horizon in dict.fromkeys((r["task"], r["setup"], r["regime"], r["horizon"]) for r in rows):
        get = lambda flow, bits: index[task, regime, horizon, flow, bits]
        r64, m64 = get("R", "float64"), get("M", "float64")
        lines.append([label, regime, str(horizon), f"{r64['simulated_time']:.3g}", sci(r64["norm"]), sci(m64["norm"]),
                      sci(get("R", "float32")["relative_error_vs_float64"]), sci(get("M", "float32")["relative_error_vs_float64"]),
                      "yes" if all(get(f, b)["finite"] for f in "RM" for b in ("float32", "float64")) else "NO",
                      f"{get('R', 'float32')['ms_per_gradient']:.0f} / {r64['ms_per_gradient']:.0f}"])
    error_table = markdown_table(["set-up", "initial states", "steps", "simulated s", "norm R (f64)", "norm M (f64)",
                                  "rel. error R f32", "rel. error M f32", "all finite", "ms R+M f32 / f64"], lines)
    growth = [[f["setup"], f["regime"], f["flow"], f["precision"], f"{f['exponent_per_simulated_second']:+.3f}",
               f"{f['t_min']:.3g}-{f['t_max']:.3g}", f"{f['rms_residual']:.2f}", f"{sci(f['norm_min'])} - {sci(f['norm_max'])}"]
              for f in fits]
    growth_table = markdown_table(["set-up", "initial states", "flow", "precision", "exponent per simulated s",
                                   "fitted over s", "rms residual of log", "norm range"], growth)
    return error_table, growth_table


def training_table(rows: list[dict]) -> list[str]:
    """Per mode and precision: compile and epoch time, test loss at the start, the end and best."""
    lines = []
    for mode, bits in dict.fromkeys((r["mode"], r["precision"]) for r in rows):
        members = sorted((r for r in rows if r["mode"] == mode and r["precision"] == bits), key=lambda r: r["epoch"])
        last = members[-1]
        lines.append([mode, bits, f"{members[0]['compile_s']:.1f}", f"{last['seconds'] / max(last['epoch'], 1):.3f}",
                      f"{last['seconds']:.1f}", f"{members[0]['test_loss']:.4g}", f"{last['test_loss']:.4g}",
                      f"{min(r['test_loss'] for r in members):.4g}"])
    return markdown_table(["mode", "precision", "compile s", "s / epoch", "total s", "test loss at start",
                           "test loss at end", "best test loss"], lines)


# ----------------------------------------------------------------------------- main

def parse(argv: list[str]) -> AccuracyConfig:
    config = parse_config(AccuracyConfig, argv, __doc__, "accuracy study")
    for name in config.task_list:
        if name not in TASKS:
            fail(f"unknown task {name!r} in --tasks: choose from {', '.join(TASKS)}")
    for name in config.study_list:
        if name not in STUDIES:
            fail(f"unknown study {name!r} in --studies: choose from {', '.join(STUDIES)}")
    if not (1 <= config.poles <= 4 and 1 <= config.gradient_poles <= 4):
        fail("--poles and --gradient-poles must be 1, 2, 3 or 4")
    for name in ("batch", "rounds", "epochs", "train_size"):
        if getattr(config, name) <= 0:
            fail(f"--{name.replace('_', '-')} must be a positive integer, got {getattr(config, name)}")
    if config.train_size % 8:
        fail(f"--train-size must be a multiple of the batch of 8, got {config.train_size}")
    return config


def read_csv(path: Path) -> list[dict]:
    """Rows written by ``write_csv``, numbers and booleans parsed back."""
    def parse_value(text: str):
        if text in ("True", "False"):
            return text == "True"
        for kind in (int, float):
            try:
                return kind(text)
            except ValueError:
                pass
        return text

    with open(path, newline="") as handle:
        return [{key: parse_value(value) for key, value in row.items()} for row in csv.DictReader(handle)]


def report(out: Path, draw: tuple[str, ...] = STUDIES) -> list[str]:
    """Summary.md, and the figures of the studies in ``draw``, from the CSVs and meta.json in ``out``.

    Never measures. Returns the key tables (Markdown lines).
    """
    from stablebptt.plots import render
    from stablebptt.runs import atomic_write, read_json

    meta = read_json(out / META_FILE)
    summary = ["# What accuracy costs in time", "",
               f"Made by `{meta['command']}` on {meta['machine']}, jax {meta['jax']}. Times are medians of "
               f"{meta['rounds']} round-robin rounds (gradients: best of 3), comparable only within one table.", ""]
    printed, measured = [], lambda name: name in meta["studies"].split(",") and (out / f"{name}.csv").exists()
    if measured("trajectory"):
        rows = read_csv(out / "trajectory.csv")
        if "trajectory" in draw:
            render(trajectory_figure(rows), out / "trajectory.png")
        key_table, full_table = trajectory_tables(rows)
        references = {r["task"]: r["reference"] for r in rows}
        durations = ", ".join(f"{task} {next(r['simulated_time'] for r in rows if r['task'] == task):g}" for task in references)
        summary += ["## Trajectory error against time", "",
                    "Error: the largest |difference| over the state (positions and velocities) and over a batch of "
                    f"{rows[0]['batch']} trajectories at the final time ({durations}; cart-pole with {meta['poles']} "
                    f"pole{'s' if meta['poles'] > 1 else ''}), one constant control per trajectory. 'cost x': wall time of "
                    "the batched forward rollout per simulated second, relative to the paper's setting (its integrator "
                    "and dt, float32). 'R gradient': one R gradient of the task's loss through its policy at the "
                    "paper's dt (forward + backward), ms per simulated second.", ""]
        summary += [f"- reference, {task}: {text}" for task, text in references.items()] + [""]
        summary += key_table + ["", "![trajectory](trajectory.png)", "", "Every time step:", ""] + full_table + [""]
        printed += key_table + [""]
    if measured("gradients"):
        rows, fits = read_csv(out / "gradients.csv"), read_csv(out / "gradient_growth.csv")
        if "gradients" in draw:
            render(gradient_figure(rows, fits), out / "gradients.png")
        error_table, growth_table = gradient_tables(rows, fits)
        summary += ["## Gradients: float32 against float64, and growth with the horizon", "",
                    f"R and M gradients of the mean loss of {meta['batch']} trajectories w.r.t. the policy parameters "
                    "(Glorot output layer, so that R differs from M), one compiled program per horizon and precision; "
                    "float32 starts from the same parameters and (rounded) initial states. 'upright': the cart-pole "
                    "started with its poles at 0 +- 30 degrees instead of pi +- 30 (the poles fall and tumble).", ""]
        summary += error_table + ["", "Growth: least-squares fit of log ||g|| against the simulated time over every "
                                  "horizon (float64).", ""] + growth_table + ["", "![gradients](gradients.png)", ""]
        printed += error_table + [""] + growth_table + [""]
    if measured("training"):
        rows = read_csv(out / "training.csv")
        if "training" in draw:
            render(training_figure(rows), out / "training.png")
        table = training_table(rows)
        epochs = max(r["epoch"] for r in rows)
        task = rows[0]["task"]
        summary += ["## Training: test loss against wall-clock time", "",
                    f"{task}{' (rc 0.01)' if task == 'repulsion' else ''}: {epochs} epochs of {meta['train_size']} "
                    "training states (batch 8), tested on as many, one seed; float64 starts from the float32 run's "
                    "data and parameters. Each mode computes only the flows it needs (--no-cosine); epochs are "
                    "timed round-robin, compilation excluded.", ""]
        summary += table + ["", "![training](training.png)", ""]
        printed += table + [""]
    atomic_write(out / "summary.md", ("\n".join(summary) + "\n").encode())
    return printed


META_FILE = "meta.json"


def main(argv: list[str]) -> int:
    config = parse(argv)
    out = Path(config.out)
    if config.replot:
        if not (out / META_FILE).is_file():
            fail(f"{out} has no {META_FILE}: run the study first (without --replot)")
        print("\n".join(report(out)))
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
    from stablebptt.runs import write_json

    started = time.perf_counter()
    log = lambda message: print(message, file=sys.stderr, flush=True)
    write_json(out / META_FILE, {
        "command": "python scripts/accuracy.py" + "".join(f" {a}" for a in argv),
        "machine": f"{platform.machine()} ({jax.devices()[0].platform}, {jax.device_count()} device, {os.cpu_count()} CPU cores)",
        "jax": jax.__version__, **dataclasses.asdict(config)})
    tables = []
    for name, study in (("trajectory", lambda: [row for setup in trajectory_setups(config) for row in trajectory_study(setup, config, log)]),
                        ("gradients", lambda: [row for setup in gradient_setups(config) for row in gradient_study(setup, config, log)]),
                        ("training", lambda: training_study(config, log))):
        if name in config.study_list:
            rows = study()
            write_csv(out / f"{name}.csv", rows)
            if name == "gradients":
                write_csv(out / "gradient_growth.csv", growth_rows(rows))
            tables = report(out, draw=(name,))  # after every study, so a long run keeps what it measured
    print("\n".join(tables))
    log(f"done in {time.perf_counter() - started:.0f} s -> {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
