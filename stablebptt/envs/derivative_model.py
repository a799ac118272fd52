"""An environment's step whose derivative is not the one of what it simulates, its values the env's
own, bit for bit. Differentiated through another model: its contacts smoothed (``ContactSmoothing``),
or its control step's physics taken in fewer, longer steps (``gradient_substeps``), that model
linearised at the true state (``differentiated_through``).

Fewer physics steps in the derivative make the backward pass that much shorter: MuJoCo Playground's
walkers simulate 10 physics steps per control step, and a window's derivative runs through all of
them.

Or cut where contacts push hard (``contact_cut``): the derivative stops at a state whose
constraint forces pass a number of the model's body weights, so a window's later rewards reach no
earlier state or action through it (a foot's strike, whose derivative is the stiffest of a gait).
The loaded states are the task's ``Episodes.gradient_cut``, where a critic may value them.

Every one of these steps is traced as ``steps_traced`` says: inside ``differentiable_mjx``, with the
task's choices of the derivative through MJX."""
from __future__ import annotations

import contextlib
import copy
import functools
import importlib
from typing import Any, Callable

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from stablebptt.envs.protocol import EnvError
from stablebptt.physics import scene, state_carried
from stablebptt.physics.backward_contacts import ContactSmoothing, differentiated_through, smoothed_model
from stablebptt.physics.constraint_derivatives import differentiable_mjx
from stablebptt.physics.mjx_internals import collision_driver
from stablebptt.physics.mjx_patches import applied, choosing, tracing


def has_constraint_solver(env: Any) -> bool:
    """Whether ``env`` steps a MuJoCo model through MJX whose constraint solver can have rows (contacts,
    limits, equalities, friction loss): its ``mj_model`` (Playground's), or a Brax env's on the mjx backend.
    An env of plain JAX has none."""
    model = getattr(env, "mj_model", None)
    if model is None and getattr(env, "backend", None) == "mjx":
        model = getattr(getattr(env, "sys", None), "mj_model", None)
    return isinstance(model, mujoco.MjModel) and scene.analyze(model).constraints


def steps_traced(contact_geometry_held: bool, physics_steps_recomputed: bool, recomputed_as_asked: bool,
                 reward_context: Callable, label: str, camera_poses_held: bool = False,
                 physics_steps_carrying_state: bool = False) -> Callable[[Any], Callable]:
    """How a task's programs trace an env's step (``traced(env)``): inside ``differentiable_mjx``, its solver
    differentiated at its solution and the choices given (the cameras' poses held where nothing reads them:
    ``unread_outputs``; MuJoCo Playground's loop of physics steps carrying the state alone:
    ``carrying_state``), and ``reward_context``. Where recomputed physics steps or the state carried were
    asked for, a step that took neither (it calls no ``mujoco.mjx.step`` through MJX's package, or no
    ``mjx_env.step`` through Playground's module) is refused as its first trace ends, and again at every
    trace until one passes: the choice would change nothing. Only until then: a step the env jits itself is
    traced again from JAX's cache, which calls nothing."""
    def traced(env):
        unchecked = recomputed_as_asked or physics_steps_carrying_state  # whether the first trace is to be checked

        def env_step(state, action):
            nonlocal unchecked
            with contextlib.ExitStack() as stack:
                mjx_trace = stack.enter_context(differentiable_mjx(
                    implicit_solver=True, contact_geometry_held=contact_geometry_held,
                    physics_steps_recomputed=physics_steps_recomputed, camera_poses_held=camera_poses_held))
                loops = stack.enter_context(carrying_state()) if physics_steps_carrying_state else None
                stack.enter_context(reward_context())
                reached = env.step(state, action)
            if unchecked:
                # Checked until a trace passes: a first trace may run where a ValueError is caught (a start's
                # trace beside the compile), and every later one then says it again.
                if recomputed_as_asked and not mjx_trace.steps_recomputed:
                    raise EnvError(f"{label}: its step calls no mujoco.mjx.step through MJX's package (as "
                                   "mjx.step, the way MuJoCo Playground's envs call it), so no physics step can be "
                                   "recomputed in the backward pass: drop physics_steps_recomputed=True "
                                   "(--physics-step-residuals recomputed)")
                if loops is not None and not loops.taken:
                    raise EnvError(f"{label}: its step calls no MuJoCo Playground loop of physics steps "
                                   "(mjx_env.step, through its module), so none can carry the state alone: drop "
                                   "physics_steps_carrying_state=True (--physics-step-carry state)")
                unchecked = False
            return reached
        return env_step
    return traced


class LoopsTaken:
    """The loops of physics steps a trace took carrying the state alone (``carrying_state``)."""
    taken = 0


@contextlib.contextmanager
def carrying_state():
    """Inside, MuJoCo Playground's loop of a control step's physics steps (``mjx_env.step``, which its envs call
    through the module) carries MuJoCo's integration state alone, its last step taken after the loop
    (``state_carried.steps``), in this thread's traces; yields a ``LoopsTaken`` filled as the context ends."""
    found, before = LoopsTaken(), tracing.loops_carrying_state
    with applied("state_carried", _state_carried_patch), choosing("physics_steps_carrying_state"):
        try:
            yield found
        finally:
            found.taken = tracing.loops_carrying_state - before


def _state_carried_patch() -> tuple:
    try:
        mjx_env = importlib.import_module("mujoco_playground._src.mjx_env")
    except ImportError:
        raise EnvError("the physics steps' loop carrying the state alone is MuJoCo Playground's, which is not "
                       "installed: drop physics_steps_carrying_state=True (--physics-step-carry state)") from None
    own = mjx_env.step

    def step(model, data, action, n_substeps=1):
        if not tracing.physics_steps_carrying_state:  # another thread's trace, or none asked
            return own(model, data, action, n_substeps)
        tracing.loops_carrying_state += 1
        return state_carried.steps(model, data.replace(ctrl=action), n_substeps)
    return ((mjx_env, "step", step),)


def jit_traced_once(function: Callable) -> Callable:
    """``jax.jit(function)`` whose one trace every program and check shares. JAX keys a jit's traces on
    the abstract mesh around the call: None where nothing set one (a check, the memory plan), the empty
    mesh where a transformed program is evaluated again (a custom derivative's forward pass inside the
    update), two traces of one step for one program. Called where none is set, it is called under the
    empty mesh, so both find the same trace; a caller's own mesh is kept."""
    jitted = jax.jit(function)

    @functools.wraps(function)
    def call(*arguments):
        # The caller's mesh again; where none is set, the empty mesh JAX gives for none.
        with jax.sharding.use_abstract_mesh(jax.sharding.get_abstract_mesh()):
            return jitted(*arguments)
    return call


def derivative_steps(traced: Callable[[Any], Callable], env: Any, smoothing: ContactSmoothing | None,
                     substeps: int | None, label: str) -> tuple[Callable, Callable | None]:
    """The step whose values a task keeps, ``traced(env)``, and the one whose derivative it takes (``joined``):
    ``traced`` of a copy of ``env`` on its contact-smoothed model and with ``substeps`` physics steps per
    control step; None where both are as ``env``'s own."""
    if smoothing is None and substeps is None:
        return traced(env), None
    needs = "contacts smoothed" if smoothing is not None else "fewer physics steps"
    model = mjx_model_of(env, f"{needs} in the derivative", label)
    other = copy.copy(env)  # the same env, stepping the derivative's model
    if smoothing is not None:
        check_contacts(env, "contacts smoothed in the derivative", label)
        other._mjx_model = smoothed_model(model, smoothing)
    if substeps is not None:
        _take_substeps(other, substeps, label)
    return traced(env), traced(other)


def mjx_model_of(env: Any, what: str, label: str) -> Any:
    """``env``'s MJX model, where it keeps one in ``_mjx_model`` as MuJoCo Playground's envs do; else
    ``EnvError`` naming ``what`` (the options that need it). Its own attribute: a wrapper's would be its
    inner env's, which the wrapper's step keeps using."""
    model = vars(env).get("_mjx_model")
    if model is None:
        raise EnvError(f"{label}: {what} need an env that keeps its MJX model in _mjx_model, as MuJoCo "
                       f"Playground's do; {type(env).__name__} does not")
    return model


def check_contacts(env: Any, what: str, label: str) -> None:
    """``EnvError`` where ``env``'s model cannot be seen to have contacts, so that ``what`` (an option on
    its contacts' derivative) would change nothing: no MJX model in ``_mjx_model``, or no pair of geoms
    that can touch (contacts or all constraints switched off in its flags, or no pair MJX collides)."""
    model = mjx_model_of(env, what, label)
    if scene.contacts_switched_off(model.opt):
        raise EnvError(f"{label}: its model switches contacts off (opt.disableflags), so {what} change nothing: "
                       f"drop the contact gradient's options")
    if next(iter(collision_driver.geom_pairs(model)), None) is None:
        raise EnvError(f"{label}: its model has no pair of geoms that can touch, so {what} change nothing: drop "
                       f"the contact gradient's options")


def joined(value_step: Callable, derivative_step: Callable | None) -> Callable:
    """``value_step``'s values with ``derivative_step``'s derivative (``derivative_steps``); ``value_step``
    itself where there is no other model."""
    return value_step if derivative_step is None else differentiated_through(value_step, derivative_step)


def own_substeps(env: Any) -> int | None:
    """The physics steps ``env`` simulates per control step, where it says (MuJoCo Playground's
    ``n_substeps``, from its ``_sim_dt``); else None."""
    count = getattr(env, "n_substeps", None) if "_sim_dt" in vars(env) else None
    return count if isinstance(count, int) else None


def _take_substeps(env: Any, substeps: int, label: str) -> None:
    """``env`` (a copy) set to step its control step in ``substeps`` physics steps of equal length."""
    own = own_substeps(env)
    if own is None:
        raise EnvError(f"{label}: fewer physics steps in the derivative need an env that keeps its physics step in "
                       f"_sim_dt and its count per control step in n_substeps, as MuJoCo Playground's do; "
                       f"{type(env).__name__} does not")
    if own % substeps:  # env_task refuses a count below 1
        raise EnvError(f"{label} simulates {own} physics step{'s' if own != 1 else ''} per control step: "
                       f"gradient_substeps (--gradient-substeps), the derivative's count, must divide it, "
                       f"got {substeps}")
    factor = own // substeps
    env._sim_dt = env._sim_dt * factor
    model = env._mjx_model
    env._mjx_model = model.replace(opt=model.opt.replace(timestep=model.opt.timestep * factor))


def contact_load(env: Any, label: str) -> Callable[[Any], jax.Array]:
    """``load(state)``: the norm of the constraint forces MJX's solver applied (``qfrc_constraint``, from
    the state's MJX data) over the weight of ``env``'s model, in body weights. For envs that keep their
    model in ``_mjx_model`` and whose states carry MJX's data, as MuJoCo Playground's do."""
    model = mjx_model_of(env, "derivative cuts at contact loads", label)
    weight = float(np.sum(model.body_mass) * np.linalg.norm(model.opt.gravity))
    if weight <= 0:
        raise EnvError(f"{label}: its model weighs nothing (no mass under gravity), so a contact load in body "
                       "weights has no scale: drop the contact gradient cut")

    def load(state) -> jax.Array:
        forces = getattr(getattr(state, "data", None), "qfrc_constraint", None)
        if forces is None:
            raise EnvError(f"{label}: a derivative cut at contact loads reads the constraint forces of MJX's data in "
                           f"the state (state.data.qfrc_constraint), as MuJoCo Playground's states carry them; "
                           f"{type(env).__name__}'s state does not")
        return jnp.linalg.norm(jax.lax.stop_gradient(forces), axis=-1) / weight
    return load


def loaded_states(env: Any, body_weights: float, label: str) -> Callable[[Any], jax.Array]:
    """``loaded(state)``: whether the state's ``contact_load`` passes ``body_weights``. An env that cannot
    take it is refused here."""
    load = contact_load(env, label)
    return lambda state: load(state) > body_weights


def contact_cut(loaded: Callable[[Any], jax.Array]) -> Callable[[Callable], Callable]:
    """``cut(step)``: ``step`` whose values stay its own and whose derivative stops at a state starting
    it that is ``loaded`` (``loaded_states``). The state the step reaches keeps its derivative, so the
    reward of a loaded state still reaches the actions before it; what follows it does not."""
    def cut(step: Callable) -> Callable:
        def cut_step(state, action):
            held_now = loaded(state)
            held = jax.tree.map(lambda leaf: jnp.where(held_now, jax.lax.stop_gradient(leaf), leaf)
                                if jnp.issubdtype(leaf.dtype, jnp.floating) else leaf, state)
            return step(held, action)
        return cut_step
    return cut
