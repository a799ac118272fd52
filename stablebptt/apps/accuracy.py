"""What accuracy costs in time, measured: the trajectory, gradient and training studies.

The command line is scripts/accuracy.py (``stablebptt accuracy``), whose help
describes the studies; ``stablebptt.accuracy_report`` turns their rows into
tables, figures and summary.md.
"""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import Any, Callable, NamedTuple

TASKS = ("cartpole", "repulsion", "quantum")
PRECISIONS = (32, 64)
CARTPOLE_DURATION, REPULSION_DURATION = 1.0, 4.0
QUANTUM_DURATION = 128 * 0.0625  # the paper's 128 steps of 0.0625


@dataclass(frozen=True)
class AccuracyConfig:
    """Options of the accuracy study."""

    tasks: str = field(default="cartpole,repulsion,quantum", metadata={"help": "comma-separated tasks of the trajectory and gradient studies"})
    studies: str = field(default="trajectory,gradients,training", metadata={"help": "comma-separated studies: trajectory, gradients, training, contact"})
    suite: str = field(default="", metadata={"help": "folder of the DeepMind Control Suite's model files (dm_control/suite), for the contact study"})
    contact_models: str = field(default="hopper,walker,cheetah,finger,ball_in_cup", metadata={"help": "comma-separated suite models of the contact study"})
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
    from stablebptt.tasks import cartpole_equations, mjcf
    reference_dt = 1e-4

    def make_task(integrator, dt):
        return mjcf.make(mjcf.Config(poles=poles, integrator=integrator, dt=dt))

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
    from stablebptt.tasks import mjcf, quantum, repulsion

    def upright(states):
        # Angles 0 +- 30 degrees instead of pi +- 30: the poles fall and tumble, a chaotic motion.
        qpos = states.qpos.copy()
        qpos[:, 1:] -= 3.141592653589793
        return states._replace(qpos=qpos)

    quick = config.quick
    setups = {
        "cartpole": GradientSetup(
            "cartpole", f"cart-pole, {config.gradient_poles} poles, MJX Euler",
            lambda: mjcf.make(mjcf.Config(poles=config.gradient_poles)), 0.01,
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




# ----------------------------------------------------------------------------- contact study

CONTACT_STEPS = 50  # steps of each compared trajectory
CONTACT_SETTLE = 0.5  # seconds of MuJoCo simulation under random controls before the comparison starts
FINITE_DIFFERENCE_STEP = 1e-6


def contact_settings(model) -> list[tuple[str, int | None, float]]:
    """(label, fixed Newton iterations or None for the model's own solver, time step) of the contact study."""
    dt = float(model.opt.timestep)
    own = f"own ({int(model.opt.iterations)} it., tol {float(model.opt.tolerance):g})"
    return [(own, None, dt), ("1 iteration", 1, dt), ("2 iterations", 2, dt), ("4 iterations", 4, dt),
            (f"{own}, 2 dt", None, 2 * dt)]


def _c_rollout(model, qpos, qvel, controls) -> "np.ndarray":
    """[steps, nq + nv] states of MuJoCo's C step from (qpos, qvel) under ``controls`` [steps, nu]."""
    import mujoco
    import numpy as np
    data = mujoco.MjData(model)
    data.qpos[:], data.qvel[:] = qpos, qvel
    visited = []
    for control in controls:
        data.ctrl[:] = control
        mujoco.mj_step(model, data)
        visited.append(np.concatenate([data.qpos, data.qvel]))
    return np.array(visited)


def _c_jacobian(model, qpos, qvel, control) -> "np.ndarray":
    """d (qpos, qvel)_next / d (qpos, qvel, ctrl) of one C step, by central differences (qpos in coordinates)."""
    import numpy as np
    point = np.concatenate([qpos, qvel, control])
    nq, nv = model.nq, model.nv

    def next_state(x):
        return _c_rollout(model, x[:nq], x[nq:nq + nv], x[None, nq + nv:])[0]

    columns = []
    for k in range(point.size):
        shift = np.zeros_like(point)
        shift[k] = FINITE_DIFFERENCE_STEP
        columns.append((next_state(point + shift) - next_state(point - shift)) / (2 * FINITE_DIFFERENCE_STEP))
    return np.stack(columns, axis=1)


def contact_study(config: AccuracyConfig, log: Callable, done: list[dict] = (),
                  on_row: Callable[[list[dict]], None] = lambda rows: None) -> list[dict]:
    """Rows per suite model with contacts and solver setting: trajectory error against MuJoCo's C step with the
    model's own settings, step-Jacobian error against central differences of the C step, and the time of a
    batched MJX rollout and of batched forward-mode step Jacobians.

    Rows in ``done`` (an earlier, interrupted call's) are kept and not measured again; ``on_row`` gets
    all rows after each new one, so a long study can be stopped and resumed."""
    import jax
    import jax.numpy as jnp
    import mujoco
    import numpy as np
    from pathlib import Path
    from stablebptt import scene
    from stablebptt.flows import step_jacobians
    from stablebptt.tasks.mjcf import load_model

    rows = list(done)
    measured = {(row["model"], row["setting"]) for row in rows}
    steps = 10 if config.quick else CONTACT_STEPS
    for name in [n for n in config.contact_models.split(",") if n]:
        model = load_model(Path(config.suite) / f"{name}.xml")
        effects = scene.analyze(model)
        rng = np.random.default_rng(config.seed)
        low, high = model.actuator_ctrlrange[:, 0], model.actuator_ctrlrange[:, 1]
        random_controls = lambda count: rng.uniform(low, high, (count, model.nu))
        # A state the model reaches, with its contacts, under random controls (the model's own settings).
        settled = _c_rollout(model, model.qpos0, np.zeros(model.nv), random_controls(round(CONTACT_SETTLE / model.opt.timestep)))
        qpos, qvel = settled[-1, :model.nq], settled[-1, model.nq:]
        data = mujoco.MjData(model)
        data.qpos[:], data.qvel[:] = qpos, qvel
        mujoco.mj_forward(model, data)
        contacts = int(data.ncon)
        held = np.repeat(random_controls(steps), 2, axis=0)  # each control held for two steps: 2 dt sees the same
        truth = _c_rollout(model, qpos, qvel, held)[-1]  # the file's own settings, at the end of every setting's rollout
        truth_jacobians = {}  # time step -> central differences of the C step with the file's solver
        for label, iterations, dt in contact_settings(model):
            if (name, label) in measured:
                continue
            factor = round(dt / float(model.opt.timestep))
            controls = held[::factor][:2 * steps // factor]
            if dt not in truth_jacobians:
                truth_jacobians[dt] = _c_jacobian(scene.with_options(model, timestep=dt), qpos, qvel, controls[0])
            truth_jacobian = truth_jacobians[dt]
            with precision(64):
                lean = scene.lean_model(model, effects, timestep=dt, solver_iterations=iterations)
                step = scene.make_step(lean, effects)
                start = scene.State(jnp.asarray(qpos), jnp.asarray(qvel), jnp.zeros(model.na))
                rollout = jax.jit(lambda s, us: jax.lax.scan(lambda x, u: (step(x, u), None), s, us)[0])
                final = rollout(start, jnp.asarray(controls))
                error = float(np.max(np.abs(np.concatenate([final.qpos, final.qvel]) - truth)))
                jacobian = jax.jit(lambda s, u: step_jacobians(step, s, u))(
                    jax.tree.map(lambda a: a[None], start), jnp.asarray(controls[:1]))
                ours = np.concatenate([jacobian[0][0], jacobian[1][0]], axis=1)[:model.nq + model.nv]
                ours = np.delete(ours, np.arange(model.nq + model.nv, ours.shape[1] - model.nu), axis=1)
                jacobian_error = float(np.linalg.norm(ours - truth_jacobian) / np.linalg.norm(truth_jacobian))
            with precision(32):  # what training runs: float32, a batch of states
                lean32 = scene.lean_model(model, effects, timestep=dt, solver_iterations=iterations)
                step32 = scene.make_step(lean32, effects)
                batch = jax.tree.map(lambda a: jnp.broadcast_to(jnp.asarray(a, jnp.float32), (config.batch,) + np.shape(a)),
                                     scene.State(qpos, qvel, np.zeros(model.na)))
                batch_controls = jnp.asarray(np.broadcast_to(controls[:, None], (len(controls), config.batch, model.nu)), jnp.float32)
            forward, _ = compile_call(jax.jit(lambda s, us: jax.lax.scan(lambda x, u: (jax.vmap(step32)(x, u), None), s, us)[0]),
                                      (batch, batch_controls), 32)
            jacobians, _ = compile_call(jax.jit(lambda s, u: step_jacobians(step32, s, u)), (batch, batch_controls[0]), 32)
            seconds = time_round_robin({"forward": forward, "jacobians": jacobians}, max(2, config.rounds // 4))
            simulated = len(controls) * dt
            rows.append({"model": name, "setting": label, "iterations": iterations or 0, "dt": dt, "steps": len(controls),
                         "contacts": contacts, "trajectory_error": error, "jacobian_error": jacobian_error,
                         "ms_per_simulated_second": 1e3 * seconds["forward"] / simulated,
                         "jacobian_ms_per_step": 1e3 * seconds["jacobians"], "batch": config.batch})
            on_row(rows)
            log(f"  {name:12s} {label:32s} trajectory {error:.2e}  Jacobian {jacobian_error:.2e}  "
                f"{rows[-1]['ms_per_simulated_second']:.1f} ms / sim. s  {rows[-1]['jacobian_ms_per_step']:.1f} ms / Jacobians")
    return rows
