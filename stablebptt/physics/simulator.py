"""The simulator builder: from a MuJoCo model to one differentiable step, built once.

``build(model, SimulatorConfig(...))`` analyses the scene, makes the lean model
(only the effects the scene calls for, as the file sets them), puts it on MJX
once, chooses the step (generated body by body where it applies, MJX's stages
otherwise, or ``mjx.step``), how gradients pass through it (forward or reverse
mode) and the symmetries that spare tangents, and says all of it in one scene
line. Tasks, benchmarks and studies take a ``Simulator`` instead of assembling
these pieces themselves::

    sim = simulator.build(mujoco.MjModel.from_xml_path("pendulum.xml"))
    next_state = sim.step(lean_step.initial_state(sim.lean), jnp.zeros(sim.lean.nu))
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable

import jax
import mujoco

from stablebptt.errors import InputError, check_field_types, config_field, keywords_named
from stablebptt.flows.dynamics import KnownColumns
from stablebptt.physics import lean_step, mjx_support, scene, symmetries
from stablebptt.physics.effects import SceneEffects
from stablebptt.physics.lean_step import State

FORWARD_MODE_MAX_STATE = 64  # numbers in (qpos, qvel, act) up to which step Jacobians are built forward
# Forward mode pushes every tangent through the constraint solver's implicit derivative; reverse mode
# pulls one cotangent through it. Tangents x constraint rows above which reverse mode's epoch is the
# shorter (docs/performance.md): point_mass (12) and reacher (6) train 2-3x faster forward;
# ball_in_cup (650), finger (744), cheetah (3,504) and humanoid (23,028) 1.2-12x faster reverse.
FORWARD_MODE_MAX_SOLVER_WORK = 500
PIPELINES = ("lean", "stages", "mjx")
STEP_DERIVATIVES = ("auto", "forward", "reverse")


@keywords_named
@dataclass(frozen=True)
class SimulatorConfig:
    """How a model is simulated and differentiated; every default keeps the file's own settings."""

    integrator: str = field(default="", metadata={"help": "override the MJCF's integrator: euler, rk4 or implicitfast", "choices": ("", "euler", "rk4", "implicitfast")})
    dt: float = field(default=0.0, metadata={"help": "override the MJCF's time step; the simulated time stays the same unless --steps is given"})
    pipeline: str = field(default="lean", metadata={"help": "lean: a step generated body by body for trees of hinge, slide, ball and free joints (constraints from MJX), else stages; stages: only the MJX stages the scene needs; mjx: mjx.step with MuJoCo's default flags", "choices": PIPELINES})
    solver_iterations: int = field(default=0, metadata={"help": "constraint solver of scenes with contacts or limits: N runs exactly N Newton iterations (cheaper, different physics); 0 keeps the model's own solver"})
    step_derivative: str = field(default="auto", metadata={"help": "how gradients pass through a step: forward (every step's Jacobian by forward mode, all steps in one batch after the rollout), reverse, or auto (forward for states of at most 64 numbers whose tangents times constraint rows stay within 500)", "choices": STEP_DERIVATIVES})

    def __post_init__(self):
        check_field_types(self)  # its subclasses' fields too (mjcf.Config's)
        if not (math.isfinite(self.dt) and self.dt >= 0):
            raise InputError(f"{config_field(self, 'dt')} must be a finite positive time step (or 0 for the MJCF's own), got {self.dt}")
        if not 0 <= self.solver_iterations <= 10_000:
            raise InputError(f"{config_field(self, 'solver_iterations')} must be between 1 and 10000 (or 0 for the model's own), got {self.solver_iterations}")
        for name, allowed in (("pipeline", PIPELINES), ("step_derivative", STEP_DERIVATIVES),
                              ("integrator", ("", *mjx_support.INTEGRATORS))):
            if getattr(self, name) not in allowed:
                raise InputError(f"{config_field(self, name)} must be one of {', '.join(a or repr(a) for a in allowed)}, got {getattr(self, name)!r}")

    def conflicts(self) -> list[str]:
        """Options set together where one makes the other meaningless (``checks.check_options``)."""
        if self.pipeline == "mjx" and self.solver_iterations:
            return [f"{config_field(self, 'solver_iterations')} {self.solver_iterations} sets the solver of the lean "
                    f"and stages pipelines; {config_field(self, 'pipeline')} mjx keeps MuJoCo's own: drop one"]
        return []


@dataclass(frozen=True)
class Simulator:
    """A model made ready for BPTT.

    Attributes:
      model: the model as given.
      lean: the model simulated (integrator, time step and solver as configured,
        effects the scene does not call for switched off).
      effects: the scene analysis (what the scene calls for).
      mjx_model: ``lean`` on MJX, put once (kinematics for losses use it too).
      step: ``step(State, ctrl) -> State``, differentiable in both modes.
      derivative: ``"forward"`` or ``"reverse"``: how the flows pass the step.
      known_columns: the step Jacobian's columns a symmetry fixes (forward mode).
      constraint_rows: rows of the constraint system simulated (0 without constraints).
      summary: the scene line: what is simulated and how it is differentiated.
    """

    model: mujoco.MjModel
    lean: mujoco.MjModel
    effects: SceneEffects
    mjx_model: Any
    step: Callable[[State, jax.Array], State]
    derivative: str
    known_columns: KnownColumns | None
    constraint_rows: int
    summary: str

    @property
    def state_size(self) -> int:
        """Numbers in a ``State`` (qpos, qvel, act)."""
        return self.lean.nq + self.lean.nv + self.lean.na


def build(model: mujoco.MjModel, config: SimulatorConfig = SimulatorConfig()) -> Simulator:
    """The simulator of ``model``: lean model, MJX model, step, derivative mode and scene line.

    Raises:
      InputError: MJX cannot simulate the model, or the options contradict each other.
    """
    effects = scene.analyze(model)
    if config.pipeline == "mjx":  # the baseline: MuJoCo's default flags, only integrator and dt overridden
        lean = scene.with_options(model, config.integrator or None, config.dt or None)
        for bit in scene.diagnostics_bits(lean):  # diagnostics change no dynamics, and MJX has none
            lean.opt.enableflags &= ~bit
    else:
        iterations = config.solver_iterations or None  # None: the model's own solver, as the file says
        lean = scene.lean_model(model, effects, config.integrator or None, config.dt or None, iterations)
    mjx_model = mjx_support.put_model(lean)
    # mjx.step simulates every constraint, the other pipelines the scene's.
    rows = mjx_support.constraint_rows(mjx_model) if effects.constraints or config.pipeline == "mjx" else 0
    # mjx.step runs MuJoCo's solver as a while loop of dynamic length: forward mode goes through
    # it, reverse mode cannot (the other pipelines differentiate the solver at its solution).
    solver_loop = config.pipeline == "mjx" and rows > 0
    if solver_loop and config.step_derivative == "reverse":
        raise InputError(f"{config_field(config, 'pipeline')} mjx runs MuJoCo's constraint solver as a loop that reverse "
                         f"mode cannot differentiate: give {config_field(config, 'step_derivative')} forward, or take "
                         f"{config_field(config, 'pipeline')} lean or stages, which differentiate the solver at its solution")
    state_size = lean.nq + lean.nv + lean.na
    tangents = state_size + lean.nu
    derivative = "forward" if solver_loop else config.step_derivative
    if derivative == "auto":
        # Forward mode costs one batched pass per state number; reverse mode one
        # pass through every tiny MJX operation: small states favour forward,
        # unless every tangent also goes through a large constraint system.
        derivative = ("forward" if state_size <= FORWARD_MODE_MAX_STATE and tangents * rows <= FORWARD_MODE_MAX_SOLVER_WORK
                      else "reverse")
    # Jitted, the step's Python (MJX's stages, the generated terms) runs once per example shape: every
    # program a run builds (the update, its vmapped pullbacks, the evaluation, the plan's measurements)
    # takes the one traced step instead of tracing it anew.
    step = jax.jit(lean_step.make_step(lean, effects, config.pipeline, mjx_model=mjx_model))

    summary = scene.describe(effects, lean, model) + (f"; pipeline: {config.pipeline}" if config.pipeline != "lean" else "")
    generated = config.pipeline == "lean" and lean_step.generated_step_applies(lean, effects)
    if generated:
        summary += "; step: generated body by body" + (", constraints by MJX" if effects.constraints else "")
    summary += f"; step gradients: {derivative} mode"
    if solver_loop and config.step_derivative == "auto":
        summary += " (mjx.step's solver loop has no reverse mode)"
    elif config.step_derivative == "auto" and derivative == "reverse" and state_size <= FORWARD_MODE_MAX_STATE:
        summary += f" ({tangents} tangents x {rows} constraint rows: cheaper than forward)"
    if (generated and not effects.constraints) or (
            config.pipeline in ("lean", "stages") and lean_step.implicit_derivative_applies(lean, effects)):
        summary += " through inverse dynamics"
    known_columns, symmetric_joints = symmetries.symmetries(lean, effects)
    if derivative == "forward" and symmetric_joints:
        summary += f" (symmetries: no tangent for {', '.join(symmetric_joints)})"
    return Simulator(model=model, lean=lean, effects=effects, mjx_model=mjx_model, step=step, derivative=derivative,
                     known_columns=known_columns, constraint_rows=rows, summary=summary)
