"""An MJCF read as a task declares it (stablebptt/models/README.md's convention), the task options over it.

    model = load_model(Path("stablebptt/models/cartpole_3.xml"))
    spec = read_spec(model, mjcf.Config(poles=3))   # horizon, loss, weights, initial states, target

The file's ``<custom>`` fields and keyframes give the horizon, the loss, per-joint
weights, the initial states and their spread, and the target; ``tasks.mjcf`` turns
a ``Spec`` into a differentiable task. Joints are found by name and type, so
nothing here knows about carts or poles.
"""
from __future__ import annotations

import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import jax.numpy as jnp
import mujoco
import numpy as np

from stablebptt.errors import InputError, config_field
from stablebptt.physics import mujoco_log
from stablebptt.physics.lean_step import State
from stablebptt.runs import model_store


class TaskOptions(Protocol):
    """The task options a spec reads over the file's own declarations (``mjcf.Config`` has them)."""

    loss: str
    reach: str
    loss_joints: str
    init_pose: str
    target_pose: str
    spread: float

DEFAULT_HORIZON = 100
DEFAULT_SPREAD = 0.1  # per-dof half-width of the initial-state noise when the MJCF declares none
MAX_HORIZON = 100_000  # steps; beyond it the rollout's stored states alone outgrow any machine
# Joint types as plain ints: MuJoCo's enums do not compare equal to NumPy integers.
FREE, BALL, SLIDE, HINGE = (int(t) for t in (mujoco.mjtJoint.mjJNT_FREE, mujoco.mjtJoint.mjJNT_BALL,
                                            mujoco.mjtJoint.mjJNT_SLIDE, mujoco.mjtJoint.mjJNT_HINGE))


def model_file_missing(path: Path) -> str:
    """What is wrong with a model file that is no file."""
    return f"model file {path} {'is a folder, not a file' if path.is_dir() else 'does not exist'}"


def load_model(path: Path) -> mujoco.MjModel:
    """Load an MJCF (or a compiled ``.mjb``, or ``.mjb.gz`` as runs keep it); any failure becomes one clear InputError line."""
    if not path.is_file():
        raise InputError(model_file_missing(path))
    try:
        with mujoco_log.collected() as warnings:
            if path.suffix in (".mjb", ".gz"):
                model = model_store.load_compiled_model(path)
            else:
                model = mujoco.MjModel.from_xml_path(str(path))
    except InputError:
        raise
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
class Reach:
    """A site's (or body's) world position the loss pulls toward a point."""

    kind: str  # "site" or "body"
    name: str
    index: int
    point: np.ndarray  # [3], metres


@dataclass(frozen=True)
class Spec:
    """The task an MJCF declares, after the task options and defaults."""

    horizon: int  # steps at the MJCF's own time step
    loss: str  # "final" or "mean"
    joint_weight: np.ndarray  # [njnt]; all zero when only a reach is in the loss
    init: State
    qpos_spread: np.ndarray  # [nv], tangent space
    qvel_spread: np.ndarray  # [nv]
    target_qpos: np.ndarray  # [nq]
    reach: Reach | None
    unused_keyframes: tuple[str, ...]


def _joint(model: mujoco.MjModel, name: str, option: str) -> int:
    index = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)
    if index < 0:
        raise InputError(f"{option}: no joint named {name!r} (joints: {', '.join(joint_names(model))})")
    return index


def _number(text: str, option: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise InputError(f"{option}: {text!r} is not a number") from None
    if not math.isfinite(value):
        raise InputError(f"{option}: values must be finite, got {text}")
    return value


def _pose(model: mujoco.MjModel, text: str, base, option: str):
    """``(qpos, keyframe or None)`` of a pose option: a keyframe's name, or JOINT=VALUE pairs set on ``base``."""
    qpos = np.array(base.qpos if base is not None else model.qpos0)
    if not text:
        return qpos, base
    if "=" not in text:
        key = _keyframe(model, text)
        if key is None:
            names = [model.key(k).name for k in range(model.nkey)]
            raise InputError(f"{option}: no keyframe named {text!r} (keyframes: {', '.join(names) or 'none'}); "
                             "or give JOINT=VALUE,...")
        return np.array(key.qpos), key
    for pair in text.split(","):
        name, _, value = pair.partition("=")
        joint = _joint(model, name.strip(), option)
        if int(model.jnt_type[joint]) not in (HINGE, SLIDE):
            raise InputError(f"{option}: joint {name.strip()!r} is a free or ball joint; set it through a keyframe")
        qpos[model.jnt_qposadr[joint]] = _number(value, option)
    return qpos, None


def _reach(model: mujoco.MjModel, text: str, option: str) -> Reach | None:
    if not text:
        return None
    name, _, point = text.partition("=")
    values = [_number(v, option) for v in point.split(",")] if point else []
    if len(values) != 3:
        raise InputError(f"{option} must be NAME=X,Y,Z (a site or body and a point in metres), got {text!r}")
    for kind, object_type in (("site", mujoco.mjtObj.mjOBJ_SITE), ("body", mujoco.mjtObj.mjOBJ_BODY)):
        index = mujoco.mj_name2id(model, object_type, name.strip())
        if index >= 0:
            return Reach(kind, name.strip(), index, np.array(values))
    raise InputError(f"{option}: no site or body named {name.strip()!r}")


def read_spec(model: mujoco.MjModel, config: TaskOptions) -> Spec:
    """The task of stablebptt/models/README.md's convention in ``model``, with ``config``'s task options over it."""
    option = lambda name: config_field(config, name)  # noqa: E731
    if model.nu == 0:
        raise InputError("no actuators: add an <actuator> so the controller can act")
    horizon = _numeric(model, "bptt_horizon", 1, np.array([DEFAULT_HORIZON]))
    if not (horizon[0] == round(horizon[0]) and 1 <= horizon[0] <= MAX_HORIZON):
        raise InputError(f"<numeric name=\"bptt_horizon\"> must be a whole number of steps from 1 to {MAX_HORIZON}, "
                         f"got {horizon[0]:g}")
    loss = config.loss or _text(model, "bptt_loss", "final")
    if loss not in ("final", "mean"):
        raise InputError(f'<text name="bptt_loss"> must be "final" or "mean", got "{loss}"')
    weights = _numeric(model, "bptt_joint_weight", model.njnt, np.ones(model.njnt))
    if np.any(weights < 0):
        raise InputError("bptt_joint_weight needs non-negative weights")
    reach = _reach(model, config.reach, option("reach"))
    if config.loss_joints == "none" or (reach is not None and not config.loss_joints):
        weights = np.zeros(model.njnt)
    elif config.loss_joints:
        chosen = {_joint(model, name.strip(), option("loss_joints")) for name in config.loss_joints.split(",")}
        weights = np.where(np.isin(np.arange(model.njnt), sorted(chosen)), weights, 0.0)
    if not np.any(weights > 0) and reach is None:
        raise InputError("the loss compares nothing: give a joint a positive weight (bptt_joint_weight, "
                         f"{option('loss_joints')}) or a point to reach ({option('reach')})")
    init_key, target_key = _keyframe(model, "init"), _keyframe(model, "target")
    for key, label in ((init_key, "init"), (target_key, "target")):
        if key is not None and not all(np.all(np.isfinite(getattr(key, f))) for f in ("qpos", "qvel", "act")):
            raise InputError(f'<key name="{label}"> must hold finite numbers')
    init_qpos, chosen_init = _pose(model, config.init_pose, init_key, option("init_pose"))
    target_qpos, chosen_target = _pose(model, config.target_pose, target_key, option("target_pose"))
    velocity_from = chosen_init if chosen_init is not None else init_key
    init = State(
        jnp.asarray(init_qpos),
        jnp.asarray(velocity_from.qvel if velocity_from is not None else np.zeros(model.nv)),
        jnp.asarray(velocity_from.act if velocity_from is not None else np.zeros(model.na)),
    )
    used = {key.name for key in (init_key, target_key, chosen_init, chosen_target) if key is not None}
    qpos_spread = _numeric(model, "bptt_qpos_spread", model.nv, np.full(model.nv, DEFAULT_SPREAD))
    qvel_spread = _numeric(model, "bptt_qvel_spread", model.nv, np.full(model.nv, DEFAULT_SPREAD))
    _check_spread(config.spread, option("spread"),
                  (init_qpos, qpos_spread, "positions"), (init.qvel, qvel_spread, "velocities"))
    return Spec(
        horizon=int(horizon[0]),
        loss=loss,
        joint_weight=weights,
        init=init,
        qpos_spread=config.spread * qpos_spread,
        qvel_spread=config.spread * qvel_spread,
        target_qpos=target_qpos,
        reach=reach,
        unused_keyframes=tuple(model.key(k).name or f"#{k}" for k in range(model.nkey) if model.key(k).name not in used),
    )


def _check_spread(spread: float, option: str, *parts: tuple) -> None:
    """Refuse a spread whose initial states square past the largest number of the run's precision.

    The step squares velocities (centrifugal and Coriolis forces, kinetic energy) and the
    loss squares slide positions; a state above the square root of the largest float makes
    them infinite in the first epoch, whatever is trained. ``option``: how errors name the
    spread; ``parts``: (centre, declared half-widths per dof, what they are).
    """
    dtype = jnp.result_type(float)  # float32, or float64 under --x64
    largest = float(np.sqrt(np.finfo(dtype).max))
    for centre, widths, what in parts:
        centre, width = float(np.max(np.abs(centre), initial=0.0)), float(np.max(widths, initial=0.0))
        if width > 0 and centre + spread * width > largest:
            raise InputError(f"{option} {spread:g} spreads the initial {what} up to "
                             f"{centre + spread * width:.3g}, past {largest:.3g}, above which their squares "
                             f"(in the dynamics and the loss) overflow {np.dtype(dtype).name}: give at most "
                             f"{(largest - centre) / width:.3g}")



def joint_names(model: mujoco.MjModel) -> list[str]:
    return [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j) or f"joint {j}" for j in range(model.njnt)]
