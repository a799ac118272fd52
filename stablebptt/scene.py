"""Scene analysis and the lean model: simulate only what a scene calls for.

``analyze(model)`` reads an ``mujoco.MjModel`` and finds which effects it can
need at all; ``lean_model`` switches the others off through MuJoCo's disable
flags (on a copy: the user's file and model are untouched); ``describe`` says
in one line what is simulated and what is skipped.

The rest of the pipeline lives beside it, each in its own module, and stays
importable from here: the step over the minimal state (``stablebptt.lean_step``:
``State``, ``make_step``), what MJX supports (``stablebptt.mjx_support``:
``check_supported``, ``put_model``) and the symmetries that fix Jacobian
columns (``stablebptt.symmetries``). ``stablebptt.simulator`` assembles them.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass

import mujoco
import numpy as np

from stablebptt import mujoco_log  # noqa: F401  (MuJoCo's warnings to stderr, never to MUJOCO_LOG.TXT)
from stablebptt.mjx_internals import collision_driver
# Importable from here, where they lived before: code written against stablebptt.scene keeps working.
from stablebptt.lean_step import (State, generated_step_applies, implicit_derivative_applies, initial_state,
                                  make_step)
from stablebptt.mjx_support import INTEGRATORS, check_supported, constraint_rows, put_model
from stablebptt.symmetries import symmetries

__all__ = [  # the analysis made here, and the names re-exported above
    "SceneEffects", "analyze", "diagnostics", "diagnostics_bits", "with_options", "lean_model", "fixed_iterations",
    "describe", "State", "generated_step_applies", "implicit_derivative_applies", "initial_state", "make_step",
    "INTEGRATORS", "check_supported", "constraint_rows", "put_model", "symmetries",
]

_DISABLE = mujoco.mjtDisableBit
_ENABLE = mujoco.mjtEnableBit


@dataclass(frozen=True)
class SceneEffects:
    """Which optional effects a scene can produce. False means: provably never."""

    contacts: bool
    joint_limits: bool
    tendon_limits: bool
    equality: bool
    friction_loss: bool
    springs: bool
    dampers: bool
    gravity_compensation: bool
    fluid: bool
    control_clamp: bool
    activation: bool
    tendons: bool
    sensors: bool

    @property
    def constraints(self) -> bool:
        """Whether the constraint solver can ever have rows."""
        return self.contacts or self.joint_limits or self.tendon_limits or self.equality or self.friction_loss

    @property
    def passive(self) -> bool:
        return self.springs or self.dampers or self.gravity_compensation or self.fluid


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


def analyze(model: mujoco.MjModel) -> SceneEffects:
    """Find the effects ``model`` can produce, from its structure and parameters alone."""
    disabled = lambda bit: bool(model.opt.disableflags & bit)
    contacts = not disabled(_DISABLE.mjDSBL_CONTACT) and not disabled(_DISABLE.mjDSBL_CONSTRAINT) and (
        next(iter(collision_driver.geom_pairs(model)), None) is not None)
    constraints_on = not disabled(_DISABLE.mjDSBL_CONSTRAINT)
    return SceneEffects(
        contacts=contacts,
        joint_limits=constraints_on and bool(np.any(model.jnt_limited)),
        tendon_limits=constraints_on and bool(model.ntendon and np.any(model.tendon_limited)),
        equality=constraints_on and bool(model.neq and np.any(model.eq_active0)),
        friction_loss=constraints_on and bool(np.any(model.dof_frictionloss > 0)
                                              or (model.ntendon and np.any(model.tendon_frictionloss > 0))),
        springs=bool(np.any(model.jnt_stiffness != 0) or (model.ntendon and np.any(model.tendon_stiffness != 0))),
        dampers=bool(np.any(model.dof_damping != 0) or (model.ntendon and np.any(model.tendon_damping != 0))),
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
    if not effects.contacts:
        # No pair can ever touch (or contacts are off): MJX need not know the geoms' collision types.
        lean.geom_contype[:] = 0
        lean.geom_conaffinity[:] = 0
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
    simulated = [label for name, label in _LABELS.items() if getattr(effects, name)]
    skipped = [label for name, label in _LABELS.items() if not getattr(effects, name)]
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
