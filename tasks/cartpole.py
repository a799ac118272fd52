"""Cart-pole with 1-4 poles through MuJoCo MJX, and any MJCF in its place.

The task is read from the MJCF itself (models/README.md documents the
convention): initial states from keyframe ``init`` plus a spread, the target
from keyframe ``target`` (else the reference pose), per-joint loss weights,
final or averaged loss and the horizon from ``<custom>`` fields. The cart-poles
use the same convention, so nothing here knows about carts, slides or poles:
joints and actuators are found by type.
"""
from __future__ import annotations

import hashlib
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from stablebptt import models, mujoco_log, scene
from stablebptt.errors import InputError
from stablebptt.flows import Dynamics
from stablebptt.networks import mlp_apply, mlp_init
from stablebptt.scene import State
from stablebptt.training import Task

MODELS = models.DIRECTORY  # package data: found wherever the package is installed
DEFAULT_EPOCHS = 1000
DEFAULT_HORIZON = 100
DEFAULT_SPREAD = 0.1  # per-dof half-width of the initial-state noise when the MJCF declares none
MAX_HORIZON = 100_000  # steps; beyond it the rollout's stored states alone outgrow any machine
FORWARD_MODE_MAX_STATE = 64  # numbers in (qpos, qvel, act) up to which step Jacobians are built forward
# Joint types as plain ints: MuJoCo's enums do not compare equal to NumPy integers.
FREE, BALL, SLIDE, HINGE = (int(t) for t in (mujoco.mjtJoint.mjJNT_FREE, mujoco.mjtJoint.mjJNT_BALL,
                                            mujoco.mjtJoint.mjJNT_SLIDE, mujoco.mjtJoint.mjJNT_HINGE))


@dataclass(frozen=True)
class Config:
    """Options of the cart-pole / MJCF task."""

    poles: int = field(default=1, metadata={"help": "number of poles, 1-4 (models/cartpole_N.xml)"})
    model: str = field(default="", metadata={"help": "any MJCF file to control instead of a cart-pole (see models/README.md)"})
    spread: float = field(default=1.0, metadata={"help": "scales the initial-state spread the MJCF declares"})
    integrator: str = field(default="", metadata={"help": "override the MJCF's integrator: euler, rk4 or implicitfast", "choices": ("", "euler", "rk4", "implicitfast")})
    dt: float = field(default=0.0, metadata={"help": "override the MJCF's time step; the simulated time stays the same unless --steps is given"})
    steps: int = field(default=0, metadata={"help": "override the horizon in steps (0: the MJCF's bptt_horizon, else 100)"})
    pipeline: str = field(default="lean", metadata={"help": "lean: only the MJX stages the scene needs; mjx: mjx.step with MuJoCo's default flags", "choices": ("lean", "mjx")})
    solver_iterations: int = field(default=0, metadata={"help": "constraint solver of scenes with contacts or limits: N runs exactly N Newton iterations (loop-free); 0 keeps the model's own solver where gradients are forward mode and, in reverse mode, takes the fewest iterations within 1e-3 of it (relative acceleration at sampled states)"})
    step_derivative: str = field(default="auto", metadata={"help": "how gradients pass through a step: forward (every step's Jacobian by forward mode, all steps in one batch after the rollout), reverse, or auto (forward for states of at most 64 numbers)", "choices": ("auto", "forward", "reverse")})

    def __post_init__(self):
        if not self.model and not 1 <= self.poles <= 4:
            raise InputError(f"--poles must be 1, 2, 3 or 4, got {self.poles}; for other systems pass --model FILE.xml")
        if not (math.isfinite(self.spread) and self.spread >= 0):
            raise InputError(f"--spread must be a finite number, zero or positive, got {self.spread}")
        if not (math.isfinite(self.dt) and self.dt >= 0):
            raise InputError(f"--dt must be a finite positive time step (or 0 for the MJCF's own), got {self.dt}")
        if not 0 <= self.solver_iterations <= 10_000:
            raise InputError(f"--solver-iterations must be between 1 and 10000 (or 0 to choose), got {self.solver_iterations}")
        if not 0 <= self.steps <= MAX_HORIZON:
            raise InputError(f"--steps must be between 1 and {MAX_HORIZON} (or 0 for the MJCF's own), got {self.steps}")

    @property
    def model_path(self) -> Path:
        return Path(self.model) if self.model else models.cartpole(self.poles)


def load_model(path: Path) -> mujoco.MjModel:
    """Load an MJCF (or a compiled ``.mjb``, as runs keep); any failure becomes one clear InputError line."""
    if not path.is_file():
        raise InputError(f"model file {path} does not exist")
    try:
        with mujoco_log.collected() as warnings:
            if path.suffix == ".mjb":
                model = mujoco.MjModel.from_binary_path(str(path))
            else:
                model = mujoco.MjModel.from_xml_path(str(path))
    except ValueError as error:
        detail = " ".join(str(error).split())
        raise InputError(f"cannot load {path}: {detail}") from None
    for line in warnings:
        # MuJoCo's parser warns of every NaN in the file; NaN and infinity are refused below and in read_spec.
        if line.strip() and "NaN" not in line:
            print(f"{path.name}: {line.strip()}", file=sys.stderr)
    timestep = float(model.opt.timestep)
    if not (math.isfinite(timestep) and timestep > 0):
        raise InputError(f"{path.name}: <option timestep> must be a finite positive number, got {timestep:g}")
    return model


def _numeric(model: mujoco.MjModel, name: str, size: int | None, default):
    index = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_NUMERIC, name)
    if index < 0:
        return default
    start, length = model.numeric_adr[index], model.numeric_size[index]
    values = np.array(model.numeric_data[start:start + length], dtype=float)
    if size is not None and len(values) != size:
        raise InputError(f"<numeric name=\"{name}\"> has {len(values)} values, the model needs {size}")
    if not np.all(np.isfinite(values)):
        raise InputError(f"<numeric name=\"{name}\"> must hold finite numbers, got {' '.join(f'{v:g}' for v in values)}")
    return values


def _text(model: mujoco.MjModel, name: str, default: str) -> str:
    index = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_TEXT, name)
    if index < 0:
        return default
    start, length = model.text_adr[index], model.text_size[index]
    raw = bytes(model.text_data[start:start + length]).rstrip(b"\x00")
    try:
        return raw.decode("utf-8").strip()
    except UnicodeDecodeError:
        raise InputError(f"<text name=\"{name}\"> is not UTF-8 text: {raw!r}") from None


def _keyframe(model: mujoco.MjModel, name: str):
    index = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_KEY, name)
    return None if index < 0 else model.key(index)


@dataclass(frozen=True)
class Spec:
    """The task an MJCF declares, after defaults."""

    horizon: int
    loss: str  # "final" or "mean"
    joint_weight: np.ndarray  # [njnt]
    init: State
    qpos_spread: np.ndarray  # [nv], tangent space
    qvel_spread: np.ndarray  # [nv]
    target_qpos: np.ndarray  # [nq]


def read_spec(model: mujoco.MjModel, spread_scale: float = 1.0) -> Spec:
    """Read the task convention of models/README.md from ``model``."""
    if model.nu == 0:
        raise InputError("no actuators: add an <actuator> so the controller can act")
    horizon = _numeric(model, "bptt_horizon", 1, np.array([DEFAULT_HORIZON]))
    if not (horizon[0] == round(horizon[0]) and 1 <= horizon[0] <= MAX_HORIZON):
        raise InputError(f"<numeric name=\"bptt_horizon\"> must be a whole number of steps from 1 to {MAX_HORIZON}, "
                         f"got {horizon[0]:g}")
    loss = _text(model, "bptt_loss", "final")
    if loss not in ("final", "mean"):
        raise InputError(f'<text name="bptt_loss"> must be "final" or "mean", got "{loss}"')
    weights = _numeric(model, "bptt_joint_weight", model.njnt, np.ones(model.njnt))
    if not np.any(weights > 0) or np.any(weights < 0):
        raise InputError("bptt_joint_weight needs non-negative weights, at least one positive")
    init_key, target_key = _keyframe(model, "init"), _keyframe(model, "target")
    for key, label in ((init_key, "init"), (target_key, "target")):
        if key is not None and not all(np.all(np.isfinite(getattr(key, f))) for f in ("qpos", "qvel", "act")):
            raise InputError(f'<key name="{label}"> must hold finite numbers')
    init = State(
        jnp.asarray(init_key.qpos if init_key is not None else model.qpos0),
        jnp.asarray(init_key.qvel if init_key is not None else np.zeros(model.nv)),
        jnp.asarray(init_key.act if init_key is not None else np.zeros(model.na)),
    )
    return Spec(
        horizon=int(horizon[0]),
        loss=loss,
        joint_weight=weights,
        init=init,
        qpos_spread=spread_scale * _numeric(model, "bptt_qpos_spread", model.nv, np.full(model.nv, DEFAULT_SPREAD)),
        qvel_spread=spread_scale * _numeric(model, "bptt_qvel_spread", model.nv, np.full(model.nv, DEFAULT_SPREAD)),
        target_qpos=np.array(target_key.qpos if target_key is not None else model.qpos0),
    )


def _quat_multiply(a, b):
    w1, v1, w2, v2 = a[0], a[1:], b[0], b[1:]
    return jnp.concatenate([jnp.array([w1 * w2 - v1 @ v2]), w1 * v2 + w2 * v1 + jnp.cross(v1, v2)])


def _quat_exp(rotation):
    """Unit quaternion of a rotation vector; smooth at zero."""
    angle_sq = rotation @ rotation
    angle = jnp.sqrt(jnp.where(angle_sq > 0, angle_sq, 1.0))
    half_sinc = jnp.where(angle_sq > 0, jnp.sin(angle / 2) / angle, 0.5)
    return jnp.concatenate([jnp.array([jnp.cos(jnp.where(angle_sq > 0, angle, 0.0) / 2)]), half_sinc * rotation])


def perturb_qpos(model: mujoco.MjModel, qpos: jax.Array, dq: jax.Array) -> jax.Array:
    """Move ``qpos`` by the tangent vector ``dq`` (rotations compose as quaternions)."""
    parts = []
    for joint in range(model.njnt):
        kind, q, v = int(model.jnt_type[joint]), model.jnt_qposadr[joint], model.jnt_dofadr[joint]
        if kind in (HINGE, SLIDE):
            parts.append(qpos[q:q + 1] + dq[v:v + 1])
        elif kind == BALL:
            parts.append(_quat_multiply(qpos[q:q + 4], _quat_exp(dq[v:v + 3])))
        else:  # free joint: position, then orientation
            parts += [qpos[q:q + 3] + dq[v:v + 3], _quat_multiply(qpos[q + 3:q + 7], _quat_exp(dq[v + 3:v + 6]))]
    return jnp.concatenate(parts) if parts else qpos


def joint_errors(model: mujoco.MjModel, qpos: jax.Array, target: np.ndarray) -> jax.Array:
    """Per-joint distance to the target: 1 - cos of the angle for hinges and rotations, squares for positions."""
    errors = []
    for joint in range(model.njnt):
        kind, q = int(model.jnt_type[joint]), model.jnt_qposadr[joint]
        if kind == HINGE:
            errors.append(1.0 - jnp.cos(qpos[q] - target[q]))
        elif kind == SLIDE:
            errors.append((qpos[q] - target[q]) ** 2)
        else:
            rot = q + (3 if kind == FREE else 0)
            # 1 - cos(rotation angle) = 2 (1 - <q, q*>^2): sign-free, as quaternions double-cover.
            error = 2.0 * (1.0 - (qpos[rot:rot + 4] @ target[rot:rot + 4]) ** 2)
            if kind == FREE:
                error += jnp.sum((qpos[q:q + 3] - target[q:q + 3]) ** 2)
            errors.append(error)
    return jnp.stack(errors)


def make(config: Config) -> Task:
    path = config.model_path
    model = load_model(path)
    try:
        if model.njnt == 0:
            raise InputError("no joints: nothing to control")
        spec = read_spec(model, config.spread)
        effects = scene.analyze(model)
        return _make(config, path, model, spec, effects)
    except InputError as error:  # every message names the model it is about
        raise InputError(f"{path.name}: {error}") from None


def _make(config: Config, path: Path, model: mujoco.MjModel, spec: Spec, effects: scene.SceneEffects) -> Task:
    state_size = 2 * model.nv + model.na + (model.nq - model.nv)
    derivative = config.step_derivative
    if derivative == "auto":
        # Forward mode costs one batched pass per state number; reverse mode one
        # pass through every tiny MJX operation: small states favour forward.
        derivative = "forward" if state_size <= FORWARD_MODE_MAX_STATE else "reverse"
    timestep = config.dt or float(model.opt.timestep)
    simulated_time = spec.horizon * float(model.opt.timestep)
    horizon = config.steps or round(simulated_time / timestep)
    if horizon < 1:
        raise InputError(f"--dt {config.dt:g} leaves less than one step of the task's {simulated_time:g} s: "
                         f"choose a smaller --dt, or give --steps")
    if horizon > MAX_HORIZON:
        raise InputError(f"--dt {config.dt:g} makes the task's {simulated_time:g} s {horizon:.3g} steps, more than "
                         f"{MAX_HORIZON}: choose a larger --dt, or give --steps")
    if config.pipeline == "mjx":  # the baseline: MuJoCo's default flags, only integrator and dt overridden
        lean = scene.with_options(model, config.integrator or None, config.dt or None)
        for bit in scene.diagnostics_bits(lean):  # diagnostics change no dynamics, and MJX has none
            lean.opt.enableflags &= ~bit
    else:
        # Forward mode differentiates the model's own constraint solver (its
        # while loop) exactly; reverse mode needs a loop-free one, as close to it as asked.
        iterations = config.solver_iterations or None
        if iterations is None and derivative == "reverse" and effects.constraints:
            # Measured where this task's rollouts go: from its initial state, over its horizon.
            physics = scene.with_options(model, config.integrator or None, config.dt or None)
            iterations = scene.loop_free_iterations(physics, scene.sampled_states(
                physics, np.asarray(spec.init.qpos), np.asarray(spec.init.qvel), steps=horizon))
        lean = scene.lean_model(model, effects, config.integrator or None, config.dt or None, iterations)
    step = scene.make_step(lean, effects, config.pipeline)
    weights = jnp.asarray(spec.joint_weight / spec.joint_weight.sum())
    target = spec.target_qpos
    sizes = (model.nq + model.nv + model.na, 100, 100, model.nu)

    def policy(params, state: State):
        return mlp_apply(params, jnp.concatenate([state.qpos, state.qvel, state.act]))

    def loss(states: State, controls):
        per_step = jax.vmap(lambda qpos: weights @ joint_errors(model, qpos, target))(states.qpos)
        return per_step[-1] if spec.loss == "final" else per_step.mean()

    def sample_initial_states(key, count):
        k_pos, k_vel = jax.random.split(key)
        dq = jax.random.uniform(k_pos, (count, model.nv), minval=-1.0, maxval=1.0) * spec.qpos_spread
        dv = jax.random.uniform(k_vel, (count, model.nv), minval=-1.0, maxval=1.0) * spec.qvel_spread
        qpos = jax.vmap(lambda d: perturb_qpos(model, spec.init.qpos, d))(dq)
        return State(qpos, spec.init.qvel + dv, jnp.broadcast_to(spec.init.act, (count, model.na)))

    summary = scene.describe(effects, lean, model) + (f"; pipeline: {config.pipeline}" if config.pipeline != "lean" else "")
    summary += f"; step gradients: {derivative} mode"
    if config.pipeline == "lean" and scene.implicit_derivative_applies(lean, effects):
        summary += " through inverse dynamics"
    known_columns, symmetric_joints = scene.symmetries(lean, effects)
    if derivative == "forward" and symmetric_joints:
        summary += f" (symmetries: no tangent for {', '.join(symmetric_joints)})"
    name = "cartpole" if not config.model else path.stem
    as_list = lambda a: np.asarray(a, dtype=float).tolist()
    resolved = {
        "model_file": str(path.resolve()),
        "model_sha256": hashlib.sha256(path.read_bytes()).hexdigest(),
        "timestep": float(lean.opt.timestep),
        "horizon_steps": horizon,
        "loss": spec.loss,
        "joint_weight": dict(zip(joint_names(model), as_list(spec.joint_weight))),
        "init": {"qpos": as_list(spec.init.qpos), "qvel": as_list(spec.init.qvel), "act": as_list(spec.init.act)},
        "qpos_spread": as_list(spec.qpos_spread),
        "qvel_spread": as_list(spec.qvel_spread),
        "target_qpos": as_list(spec.target_qpos),
        "step_derivative": derivative,
        "solver": {"iterations": int(lean.opt.iterations), "tolerance": float(lean.opt.tolerance),
                   "solver": mujoco.mjtSolver(lean.opt.solver).name} if effects.constraints else None,
    }
    return Task(
        name=name,
        dynamics=Dynamics(step=step, policy=policy, loss=loss, horizon=horizon, step_derivative=derivative,
                          known_columns=known_columns),
        init_params=lambda key, zero_output: mlp_init(key, sizes, zero_output),
        sample_initial_states=sample_initial_states,
        summary=f"{path.name}: {summary}; horizon {horizon} steps, {spec.loss}-state loss",
        resolved=resolved,
    )


def joint_names(model: mujoco.MjModel) -> list[str]:
    return [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j) or f"joint {j}" for j in range(model.njnt)]
