"""Scene analysis and the lean model: simulate only what a scene calls for.

``analyze(model)`` reads an ``mujoco.MjModel`` and finds which effects it can
need at all; ``lean_model`` switches the others off through MuJoCo's disable
flags (on a copy: the user's file and model are untouched); ``describe`` says
in one line what is simulated and what is skipped.

The rest of the pipeline lives beside it, each in its own module: the step over the minimal state (``stablebptt.physics.lean_step``:
``State``, ``make_step``), what MJX supports (``stablebptt.physics.mjx_support``:
``check_supported``, ``put_model``) and the symmetries that fix Jacobian
columns (``stablebptt.physics.symmetries``). ``stablebptt.physics.simulator`` assembles them.
"""
from __future__ import annotations

import copy

import mujoco
import numpy as np

from stablebptt.physics import mujoco_log  # noqa: F401  (MuJoCo's warnings to stderr, never to MUJOCO_LOG.TXT)
from stablebptt.physics.effects import SceneEffects
from stablebptt.physics.mjx_internals import collision_driver
from stablebptt.physics.mjx_support import INTEGRATORS

_DISABLE = mujoco.mjtDisableBit
_ENABLE = mujoco.mjtEnableBit



# (SceneEffects field, MuJoCo disable flag switched on when the effect is absent)
_FLAGS = (
    ("contacts", _DISABLE.mjDSBL_CONTACT),
    ("joint_limits", None),  # LIMIT covers joints and tendons: set below when both are absent
    ("equality", _DISABLE.mjDSBL_EQUALITY),
    ("friction_loss", _DISABLE.mjDSBL_FRICTIONLOSS),
    ("control_clamp", _DISABLE.mjDSBL_CLAMPCTRL),
)
_LABELS = {
    "contacts": "contacts", "joint_limits": "joint limits", "tendon_limits": "tendon limits",
    "equality": "equality constraints", "friction_loss": "friction loss", "springs": "springs",
    "dampers": "dampers", "gravity_compensation": "gravity compensation", "fluid": "fluid forces",
    "control_clamp": "control clamping", "activation": "actuator activation", "tendons": "tendons",
}


_PLANE, _HFIELD = int(mujoco.mjtGeom.mjGEOM_PLANE), int(mujoco.mjtGeom.mjGEOM_HFIELD)
_FREE, _SLIDE = int(mujoco.mjtJoint.mjJNT_FREE), int(mujoco.mjtJoint.mjJNT_SLIDE)


def _reach(model: mujoco.MjModel) -> tuple[np.ndarray, np.ndarray, mujoco.MjData]:
    """Per geom, a ball that holds it in every configuration: centres [ngeom, 3], radii [ngeom] (inf where
    nothing bounds it: a free joint, a slide, a mocap body), and the data at qpos0.

    A hinge or ball joint turns what hangs from it about its anchor, so the distance from its anchor to the
    next joint's anchor down the tree never changes. So a geom stays within the sum of those distances (at
    qpos0) and its own bounding radius of its first joint's anchor, which only the world carries. Joint
    ranges are not used: MuJoCo's limits are soft (a pushed slide passes its range), so a slide bounds
    nothing either, and the ball is loose, never wrong.
    """
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    centres, radii = data.geom_xpos.copy(), np.array(model.geom_rbound, dtype=float)
    for geom in range(model.ngeom):
        chain, body, bounded = [], int(model.geom_bodyid[geom]), True
        while body > 0:
            bounded &= model.body_mocapid[body] < 0
            chain = list(range(model.body_jntadr[body], model.body_jntadr[body] + model.body_jntnum[body])) + chain
            body = int(model.body_parentid[body])
        kinds = model.jnt_type[chain]
        if not bounded or np.any(np.isin(kinds, (_FREE, _SLIDE))) or chain and model.geom_type[geom] in (_PLANE, _HFIELD):
            radii[geom] = np.inf
            continue
        if not chain:
            continue  # fixed in the world
        anchors = np.vstack([data.xanchor[chain], data.geom_xpos[geom]])
        centres[geom] = anchors[0]
        radii[geom] += np.linalg.norm(np.diff(anchors, axis=0), axis=1).sum()
    return centres, radii, data


def touchable_pairs(model: mujoco.MjModel) -> list[tuple[int, int]]:
    """The geom pairs MJX would collide that can ever touch: every explicit ``<pair>``, and each other pair
    whose balls (``_reach``) come within the two geoms' margins, or a ball within margin of a plane fixed in
    the world (whose collision is with the whole half-space below it)."""
    centres, radii, data = _reach(model)

    def can_touch(first, second):
        # MJX adds the two margins; the slack covers rounding where MJX simulates in float32.
        margin = model.geom_margin[first] + model.geom_margin[second] + 1e-6 * (1 + min(radii[first], radii[second]))
        for plane, other in ((first, second), (second, first)):
            if model.geom_type[plane] == _PLANE:
                if not np.isfinite(radii[plane]) or not np.isfinite(radii[other]):
                    return True
                normal = data.geom_xmat[plane].reshape(3, 3)[:, 2]
                return (centres[other] - centres[plane]) @ normal - radii[other] <= margin
        return np.linalg.norm(centres[first] - centres[second]) <= radii[first] + radii[second] + margin

    return [(first, second) for first, second, pair in collision_driver.geom_pairs(model)
            if pair >= 0 or can_touch(first, second)]


def contacts_switched_off(options) -> bool:
    """Whether a model's options (MuJoCo's ``opt`` or MJX's) switch its contacts off: their flag, or all
    constraints'."""
    return bool(int(options.disableflags) & (int(_DISABLE.mjDSBL_CONTACT) | int(_DISABLE.mjDSBL_CONSTRAINT)))


def analyze(model: mujoco.MjModel) -> SceneEffects:
    """Find the effects ``model`` can produce, from its structure and parameters alone."""
    disabled = lambda bit: bool(model.opt.disableflags & bit)
    contacts = not contacts_switched_off(model.opt) and bool(touchable_pairs(model))
    constraints_on = not disabled(_DISABLE.mjDSBL_CONSTRAINT)
    return SceneEffects(
        contacts=contacts,
        joint_limits=constraints_on and bool(np.any(model.jnt_limited)),
        tendon_limits=constraints_on and bool(model.ntendon and np.any(model.tendon_limited)),
        equality=constraints_on and bool(model.neq and np.any(model.eq_active0)),
        friction_loss=constraints_on and bool(np.any(model.dof_frictionloss > 0)
                                              or (model.ntendon and np.any(model.tendon_frictionloss > 0))),
        # MuJoCo keeps a spring's or damper's higher-order terms apart from its linear coefficient.
        springs=any(np.any(np.asarray(a) != 0) for a in (model.jnt_stiffness, model.jnt_stiffnesspoly,
                                                         model.tendon_stiffness, model.tendon_stiffnesspoly)),
        dampers=any(np.any(np.asarray(a) != 0) for a in (model.dof_damping, model.dof_dampingpoly,
                                                         model.tendon_damping, model.tendon_dampingpoly)),
        gravity_compensation=bool(np.any(model.body_gravcomp != 0)),
        fluid=bool(model.opt.density > 0 or model.opt.viscosity > 0),
        control_clamp=bool(model.nu and np.any(model.actuator_ctrllimited)),
        activation=bool(model.na),
        tendons=bool(model.ntendon),
        sensors=bool(model.nsensor),
    )


# Enable flags that only compute diagnostics (no force, state or step depends on
# them): switched off on the simulated copy and named in the scene line.
_DIAGNOSTICS = {int(_ENABLE.mjENBL_ENERGY): "energy", int(_ENABLE.mjENBL_FWDINV): "forward-inverse comparison"}


def diagnostics(model: mujoco.MjModel) -> list[str]:
    """The diagnostics ``model`` enables: they change no dynamics, so the simulated copy skips them."""
    return [label for bit, label in _DIAGNOSTICS.items() if model.opt.enableflags & bit]


def diagnostics_bits(model: mujoco.MjModel) -> list[int]:
    """The enable flags of ``diagnostics(model)``."""
    return [bit for bit in _DIAGNOSTICS if model.opt.enableflags & bit]



def with_options(model: mujoco.MjModel, integrator: str | None = None, timestep: float | None = None) -> mujoco.MjModel:
    """A copy of ``model`` with its integrator and time step overridden where given."""
    copied = copy.copy(model)
    if integrator is not None:
        copied.opt.integrator = INTEGRATORS[integrator]
    if timestep is not None:
        copied.opt.timestep = timestep
    return copied


def lean_model(model: mujoco.MjModel, effects: SceneEffects, integrator: str | None = None,
               timestep: float | None = None, solver_iterations: int | None = None) -> mujoco.MjModel:
    """A copy of ``model`` with every absent effect and every diagnostic switched off.

    Args:
      solver_iterations: None keeps the model's own constraint solver. A
        number N sets exactly N Newton iterations (tolerance 0, which MuJoCo's
        C step honours too): cheaper, and different physics where N does not
        reach the solution. Either way the solver's iterations are not
        differentiated (``constraint_derivatives.solve_implicitly``).
    """
    lean = with_options(model, integrator, timestep)
    for bit in diagnostics_bits(lean):
        lean.opt.enableflags &= ~bit
    # Sensors feed no loss, so they are never simulated; MJX still checks every
    # sensor's type, so the copy's become clocks, which it supports.
    lean.opt.disableflags |= _DISABLE.mjDSBL_SENSOR
    lean.sensor_type[:] = mujoco.mjtSensor.mjSENS_CLOCK
    # A geom that can touch nothing (``touchable_pairs``) is no geom MJX collides: it drops out of the
    # collision program, which for dm_control's finger was most of what XLA compiled.
    touching = {geom for pair in touchable_pairs(lean) for geom in pair} if effects.contacts else set()
    untouchable = np.array([geom not in touching for geom in range(lean.ngeom)], dtype=bool)
    lean.geom_contype[untouchable] = 0
    lean.geom_conaffinity[untouchable] = 0
    for name, bit in _FLAGS:
        if bit is not None and not getattr(effects, name):
            lean.opt.disableflags |= bit
    if not (effects.joint_limits or effects.tendon_limits):
        lean.opt.disableflags |= _DISABLE.mjDSBL_LIMIT
    if not effects.passive:
        # MJX zeroes ALL passive forces (springs, dampers, gravity compensation,
        # fluid) when either flag is set, unlike MuJoCo's C step: only both, and
        # only when the scene has none of them.
        lean.opt.disableflags |= _DISABLE.mjDSBL_SPRING | _DISABLE.mjDSBL_DAMPER
    if not effects.constraints:
        lean.opt.disableflags |= _DISABLE.mjDSBL_CONSTRAINT
    elif solver_iterations is not None:
        _fix_iterations(lean, solver_iterations)
    if not effects.dampers:
        # Euler's implicit damping refactors the mass matrix: pointless without damping.
        lean.opt.disableflags |= _DISABLE.mjDSBL_EULERDAMP
    # The dense mass matrix means a LAPACK call (CPU) or cuBLAS triangular solves
    # (GPU) per step and more in its derivatives; MJX's sparse path is plain fused
    # arithmetic, and faster on both (scripts/bench.py, rows "dense mass matrix").
    lean.opt.jacobian = mujoco.mjtJacobian.mjJAC_SPARSE
    return lean


def _fix_iterations(model: mujoco.MjModel, iterations: int) -> None:
    model.opt.solver = mujoco.mjtSolver.mjSOL_NEWTON
    model.opt.iterations = iterations
    model.opt.tolerance = 0.0  # never stop early: exactly ``iterations``


def fixed_iterations(model: mujoco.MjModel) -> bool:
    """Whether ``model``'s Newton solver runs a fixed number of iterations (tolerance 0)."""
    return model.opt.tolerance == 0 and int(model.opt.solver) == int(mujoco.mjtSolver.mjSOL_NEWTON)


def describe(effects: SceneEffects, model: mujoco.MjModel, original: mujoco.MjModel | None = None) -> str:
    """One line: what is simulated, what is skipped, and any solver setting chosen for gradients.

    ``original``, the user's model, names the diagnostics the simulated copy skips.
    """
    labels = dict(_LABELS)
    if original is not None:
        pairs, touchable = len(list(collision_driver.geom_pairs(original))), len(touchable_pairs(original))
        if touchable < pairs:
            labels["contacts"] = (f"contacts ({touchable} of {pairs} geom pairs can touch)" if touchable
                                  else "contacts (no geom pair can touch)")
    simulated = [label for name, label in labels.items() if getattr(effects, name)]
    skipped = [label for name, label in labels.items() if not getattr(effects, name)]
    skipped += ["sensors"] + [f"{label} diagnostic" for label in diagnostics(original if original is not None else model)]
    integrator = {v: k for k, v in INTEGRATORS.items()}.get(int(model.opt.integrator), str(model.opt.integrator))
    line = (f"scene: {model.nq} qpos, {model.nv} dof, {model.nu} actuators, {integrator} at dt {model.opt.timestep:g}; "
            f"simulated: rigid-body dynamics{''.join(', ' + s for s in simulated)}; skipped: {', '.join(skipped) or 'nothing'}")
    if effects.constraints:
        if fixed_iterations(model):
            count = int(model.opt.iterations)
            line += f"; constraint solver: {count} Newton iteration{'s' if count > 1 else ''}, fixed"
            if original is not None and not fixed_iterations(original):
                line += f" (the model's own: {_solver_name(original)}, tolerance {original.opt.tolerance:g})"
        else:
            line += (f"; constraint solver: the model's own ({_solver_name(model)}, at most {model.opt.iterations} iterations, "
                     f"tolerance {model.opt.tolerance:g})")
    return line


def _solver_name(model: mujoco.MjModel) -> str:
    name = mujoco.mjtSolver(model.opt.solver).name[len("mjSOL_"):].capitalize()
    return "CG" if name == "Cg" else name
