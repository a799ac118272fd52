"""Any MJCF file as a task, simulated through MuJoCo MJX; the cart-poles are its models plus ``--poles``.

The task is read from the MJCF itself (stablebptt/models/README.md documents the
convention): initial states from keyframe ``init`` plus a spread, the target
from keyframe ``target`` (else the reference pose), per-joint loss weights,
final or averaged loss and the horizon from ``<custom>`` fields. A task file
next to the model (``MODEL.task.json``) or the task options override them, so a
third-party file trains toward a chosen target untouched. The cart-poles use the
same convention, so nothing here knows about carts, slides or poles: joints and
actuators are found by type. Reading the file and what it declares is
``tasks.mjcf_spec`` (``load_model``, ``read_spec``); here are the options, the
joint-space maths of the loss and the initial states, and the task put together.
"""
from __future__ import annotations

import hashlib
import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from stablebptt import models
from stablebptt.engine.episodes import Episodes
from stablebptt.engine.task import Task
from stablebptt.errors import InputError, config_field, keywords_named
from stablebptt.flows.dynamics import Dynamics, Plan
from stablebptt.networks import mlp_apply, mlp_init
from stablebptt.physics import simulator
from stablebptt.physics.lean_step import State
from stablebptt.physics.mjx_internals import mjx
from stablebptt.physics.simulator import SimulatorConfig
from stablebptt.storage import file_sha256
from stablebptt.tasks import mjcf_spec
from stablebptt.tasks.mjcf_spec import BALL, FREE, HINGE, MAX_HORIZON, SLIDE, Spec, joint_names, load_model

# The MJCF reading of tasks.mjcf_spec is part of this task's interface too.
MODELS = models.DIRECTORY  # package data: found wherever the package is installed
DEFAULT_EPOCHS = 1000

# What a task file may set: the task, not the simulation.
MAX_EPISODE = 1_000_000  # steps of an episode (episode_seconds)
TASK_FILE_OPTIONS = ("init_pose", "target_pose", "reach", "loss_joints", "loss", "horizon_seconds", "spread")


@keywords_named
@dataclass(frozen=True)
class Config(SimulatorConfig):
    """Options of the MJCF task: the model, the task over what it declares, and (inherited) how it is simulated."""

    poles: int = field(default=1, metadata={"help": "number of poles, 1-4 (stablebptt/models/cartpole_N.xml)"})
    model: str = field(default="", metadata={"help": "any MJCF file to control instead of a cart-pole (see stablebptt/models/README.md)"})
    spread: float = field(default=1.0, metadata={"help": "scales the initial-state spread the MJCF declares"})
    steps: int = field(default=0, metadata={"help": "override the horizon in steps (0: the MJCF's bptt_horizon, else 100)"})
    # The task, over what the MJCF declares (stablebptt/models/README.md); a task file may set these too.
    task_file: str = field(default="", metadata={"help": "JSON file of task options (keys as these options' names, e.g. {\"init_pose\": \"hinge=3.1416\"}); default: MODEL.task.json next to the model when it exists; none: no file"})
    init_pose: str = field(default="", metadata={"help": "centre of the initial states: a keyframe's name, or JOINT=VALUE,... on the MJCF's own (hinges in radians)"})
    target_pose: str = field(default="", metadata={"help": "target of the pose loss: a keyframe's name, or JOINT=VALUE,... on the MJCF's own"})
    reach: str = field(default="", metadata={"help": "SITE=X,Y,Z (or BODY=X,Y,Z): the loss includes that site's (body's) squared distance to the point, in metres; the pose loss then only covers --loss-joints"})
    loss_joints: str = field(default="", metadata={"help": "joints the pose loss compares, comma-separated (leave passive bodies out); none: no pose loss"})
    loss: str = field(default="", metadata={"help": "when the loss is taken: final (last state) or mean (over all steps); default: the MJCF's bptt_loss, else final", "choices": ("", "final", "mean")})
    horizon_seconds: float = field(default=0.0, metadata={"help": "horizon in simulated seconds (0: the MJCF's bptt_horizon, else 100 steps); --steps overrides it"})
    episode_seconds: float = field(default=0.0, metadata={"help": "give the task episodes of this many simulated seconds, so that it trains on carried ones (--episodes): windows of the horizon along them, each step's reward the negative state loss, an episode that ends (or whose state is no longer finite) reset from the initial states' spread; 0: no episodes, the paper's protocol"})

    def __post_init__(self):
        super().__post_init__()
        if not self.model and not 1 <= self.poles <= 4:
            raise InputError(f"{config_field(self, 'poles')} must be 1, 2, 3 or 4, got {self.poles}; for other systems give {config_field(self, 'model')} (an MJCF file)")
        if not (math.isfinite(self.spread) and self.spread >= 0):
            raise InputError(f"{config_field(self, 'spread')} must be a finite number, zero or positive, got {self.spread}")
        if not 0 <= self.steps <= MAX_HORIZON:
            raise InputError(f"{config_field(self, 'steps')} must be between 1 and {MAX_HORIZON} (or 0 for the MJCF's own), got {self.steps}")
        if self.loss not in ("", "final", "mean"):
            raise InputError(f"{config_field(self, 'loss')} must be final or mean (or empty for the MJCF's own), got {self.loss!r}")
        if not (math.isfinite(self.episode_seconds) and self.episode_seconds >= 0):
            raise InputError(f"{config_field(self, 'episode_seconds')} must be a finite time, zero or positive, got {self.episode_seconds}")
        if not (math.isfinite(self.horizon_seconds) and self.horizon_seconds >= 0):
            raise InputError(f"{config_field(self, 'horizon_seconds')} must be a finite positive time (or 0 for the MJCF's own), got {self.horizon_seconds}")
        self._merge_task_file()

    def conflicts(self) -> list[str]:
        """Options set together where one makes the other meaningless (``checks.check_options``)."""
        field = lambda name: config_field(self, name)  # noqa: E731
        problems = super().conflicts()
        if self.model and self.poles != 1:
            problems.append(f"{field('poles')} {self.poles} picks a cart-pole model, and {field('model')} gives "
                            f"another: drop one")
        if self.steps and self.horizon_seconds:
            problems.append(f"{field('steps')} {self.steps} overrides {field('horizon_seconds')} "
                            f"{self.horizon_seconds:g}: give one")
        if self.target_pose and (self.loss_joints == "none" or (self.reach and not self.loss_joints)):
            problems.append(f"{field('target_pose')} sets the target of the pose loss, which compares no joint "
                            f"({field('loss_joints')} none, or {field('reach')} alone): drop it, or name the joints "
                            f"with {field('loss_joints')}")
        return problems

    def _merge_task_file(self) -> None:
        """Fill the task options still at their defaults from the task file, and record which file that was."""
        if self.task_file == "none" or not (self.task_file or self.model):
            return
        given = bool(self.task_file)
        path = Path(self.task_file) if given else Path(self.model).with_suffix(".task.json")
        if not path.is_file():
            if given:
                raise InputError(f"task file {path} does not exist")
            return
        try:
            values = json.loads(path.read_text(encoding="utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError) as error:
            raise InputError(f"task file {path} is not JSON text: {error}") from None
        if not isinstance(values, dict):
            raise InputError(f"task file {path} must hold one JSON object of task options")
        unknown = sorted(set(values) - set(TASK_FILE_OPTIONS))
        if unknown:
            raise InputError(f"task file {path}: unknown option {unknown[0]!r} (it may set {', '.join(TASK_FILE_OPTIONS)})")
        from stablebptt.cli import build  # the same type checks as a run's config.json
        from_file = build(Config, {**values, "task_file": "none"}, source=str(path))
        defaults = Config(task_file="none")
        for name in values:
            if getattr(self, name) == getattr(defaults, name):  # the command line wins
                object.__setattr__(self, name, getattr(from_file, name))
        object.__setattr__(self, "task_file", str(path.resolve()))

    @property
    def model_path(self) -> Path:
        return Path(self.model) if self.model else models.cartpole(self.poles)


def read_spec(model: mujoco.MjModel, config: Config | None = None) -> Spec:
    """The task of stablebptt/models/README.md's convention in ``model``, with ``config``'s task options (default: none) over it."""
    return mjcf_spec.read_spec(model, config or Config(task_file="none"))


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
        spec = read_spec(model, config)
        if spec.unused_keyframes:
            print(f"{path.name}: keyframe{'s' if len(spec.unused_keyframes) > 1 else ''} "
                  f"{', '.join(spec.unused_keyframes)} not used by the task (choose one with --init-pose NAME "
                  "or --target-pose NAME)", file=sys.stderr)
        return _make(config, path, model, spec)
    except InputError as error:  # every message names the model it is about
        raise InputError(f"{path.name}: {error}") from None


def _make(config: Config, path: Path, model: mujoco.MjModel, spec: Spec) -> Task:
    timestep = config.dt or float(model.opt.timestep)
    simulated_time = config.horizon_seconds or spec.horizon * float(model.opt.timestep)
    horizon = config.steps or round(simulated_time / timestep)
    if horizon < 1:
        raise InputError(f"a time step of {timestep:g} s leaves less than one step of the task's {simulated_time:g} s: "
                         f"choose a smaller {config_field(Config, 'dt')}, a longer "
                         f"{config_field(Config, 'horizon_seconds')}, or give {config_field(Config, 'steps')}")
    if horizon > MAX_HORIZON:
        raise InputError(f"a time step of {timestep:g} s makes the task's {simulated_time:g} s {horizon:.3g} steps, "
                         f"more than {MAX_HORIZON}: choose a larger {config_field(Config, 'dt')}, or give "
                         f"{config_field(Config, 'steps')}")
    sim = simulator.build(model, config)
    lean = sim.lean
    weights = jnp.asarray(spec.joint_weight / max(spec.joint_weight.sum(), 1e-300))
    target = spec.target_qpos
    sizes = (model.nq + model.nv + model.na, 100, 100, model.nu)

    # A limited actuator's control is squashed smoothly into its range (a zero output is its centre,
    # slope 1 there): a clamp gives a saturated controller a zero gradient, and it never leaves saturation.
    limited = np.asarray(model.actuator_ctrllimited, bool)
    centre = np.where(limited, model.actuator_ctrlrange.mean(axis=1), 0.0)
    half_width = np.where(limited, np.maximum(np.diff(model.actuator_ctrlrange, axis=1)[:, 0] / 2, 1e-12), 1.0)

    def policy(params, state: State):
        raw = mlp_apply(params, jnp.concatenate([state.qpos, state.qvel, state.act]))
        return jnp.where(limited, centre + half_width * jnp.tanh(raw / half_width), raw)

    reach = spec.reach
    if reach is not None:
        kinematics_model = sim.mjx_model
        empty = mjx.make_data(kinematics_model)

    def state_loss(qpos):
        pose = weights @ joint_errors(model, qpos, target) if spec.joint_weight.any() else 0.0
        if reach is None:
            return pose
        placed = mjx.kinematics(kinematics_model, empty.replace(qpos=qpos))
        position = (placed.site_xpos if reach.kind == "site" else placed.xpos)[reach.index]
        return pose + jnp.sum((position - reach.point) ** 2)

    def loss(states: State, controls):
        per_step = jax.vmap(state_loss)(states.qpos)
        return per_step[-1] if spec.loss == "final" else per_step.mean()

    def sample_initial_states(key, count):
        k_pos, k_vel = jax.random.split(key)
        dq = jax.random.uniform(k_pos, (count, model.nv), minval=-1.0, maxval=1.0) * spec.qpos_spread
        dv = jax.random.uniform(k_vel, (count, model.nv), minval=-1.0, maxval=1.0) * spec.qvel_spread
        qpos = jax.vmap(lambda d: perturb_qpos(model, spec.init.qpos, d))(dq)
        return State(qpos, spec.init.qvel + dv, jnp.broadcast_to(spec.init.act, (count, model.na)))

    episodes = None
    if config.episode_seconds:
        length = round(config.episode_seconds / timestep)
        if not 1 <= length <= MAX_EPISODE:
            raise InputError(f"{config_field(Config, 'episode_seconds')} {config.episode_seconds:g} is {length} steps of "
                             f"{timestep:g} s: choose between one step and {MAX_EPISODE}")
        # A state that is no longer finite ends its episode: it is reset, and nothing past it counts.
        episodes = Episodes(reset=lambda key: jax.tree.map(lambda a: a[0], sample_initial_states(key, 1)),
                            reward=lambda state: -state_loss(state.qpos), length=length,
                            done=lambda state: ~jnp.all(jnp.isfinite(jnp.concatenate([state.qpos, state.qvel]))))

    name = path.name.removesuffix(".gz").rsplit(".", 1)[0]  # runs name the model: cartpole_3, humanoid, ...
    as_list = lambda a: np.asarray(a, dtype=float).tolist()
    resolved = {
        "model_file": str(path.resolve()),
        "model_sha256": file_sha256(path),
        "timestep": float(lean.opt.timestep),
        "horizon_steps": horizon,
        **({"episode_steps": episodes.length} if episodes else {}),
        "loss": spec.loss,
        "joint_weight": dict(zip(joint_names(model), as_list(spec.joint_weight))),
        "init": {"qpos": as_list(spec.init.qpos), "qvel": as_list(spec.init.qvel), "act": as_list(spec.init.act)},
        "qpos_spread": as_list(spec.qpos_spread),
        "qvel_spread": as_list(spec.qvel_spread),
        "target_qpos": as_list(spec.target_qpos),
        "reach": None if reach is None else {reach.kind: reach.name, "point": as_list(reach.point)},
        "task_file": config.task_file if config.task_file != "none" else "",
        "step_derivative": sim.derivative,
        "solver": {"iterations": int(lean.opt.iterations), "tolerance": float(lean.opt.tolerance),
                   "solver": mujoco.mjtSolver(lean.opt.solver).name} if sim.effects.constraints else None,
    }
    return Task(
        name=name,
        dynamics=Dynamics(step=sim.step, policy=policy, loss=loss, horizon=horizon),
        # Every input's tangent goes through the constraint solver's implicit derivative: one pass for
        # all of them holds one copy of it (docs/performance.md), where per-input passes hold one each.
        plan=Plan(step_derivative=sim.derivative, known_columns=sim.known_columns,
                  jacobian_per_input=not sim.constraint_rows),
        init_params=lambda key, zero_output: mlp_init(key, sizes, zero_output),
        sample_initial_states=sample_initial_states,
        summary=f"{path.name}: {sim.summary}; horizon {horizon} steps, {spec.loss}-state loss"
                + (f" (reaching {reach.name})" if reach is not None else "")
                + (f"; episodes of {episodes.length} steps, each step's reward the negative state loss" if episodes else ""),
        resolved=resolved,
        episodes=episodes,
    )


def program_inputs(config: Config) -> dict:
    """What the task's compiled programs read besides the library and ``config``: the model, compiled
    (its includes and meshes inside)."""
    from stablebptt.runs.model_store import compiled_model
    return {"model": hashlib.sha256(compiled_model(config.model_path)).hexdigest()}
