"""Derivatives through MJX's constraint solver and contacts: the implicit solver derivative and MJX's NaN traps.

Everything here changes derivatives only; values stay MJX's own, except for the order in which
the elliptic-cone Newton Hessian is summed (``_update_gradient_by_blocks``: the same Hessian),
the cameras' poses where a trace holds them (``held_camera_poses``: a step that reads none), and
the acceleration stage's sensors of a model without constraint rows, which MJX leaves at zero and
MuJoCo's C computes, and the sensors after a step under RK4, the start state's as in C rather than
MJX's last stage's (``c_sensors.sensors_as_c_computes``: C's values). The
patches and each tracing thread's choices: ``mjx_patches``.

- ``solve_implicitly``: MJX's constraint solver, differentiated at the
  acceleration it finds (implicit function theorem), not through its
  iterations. Reverse mode therefore passes solvers of any iteration count
  (their while loop is never differentiated), and forward and reverse mode
  agree.
- ``differentiable_mjx()``: a context in which MJX's private modules carry the
  remedies below (with ``applied_forces``'s derivative of forces on bodies, and the position
  stage's derivatives without tree scans of ``kinematics_derivative`` and ``tree_sums``), applied
  while a step is traced and undone afterwards. Every
  step this library builds traces inside it; ``implicit_solver=True`` also
  routes ``mjx.forward``'s solver call (and so ``mjx.step`` inside any
  environment) through ``solve_implicitly``. ``physics_steps_recomputed=True``
  has reverse mode store the state each ``mjx.step`` starts from, the solver's solution and
  the values of MJX's functions this package differentiates (``values_kept.KEPT_VALUES``),
  and run the rest of the step again in the backward pass (``jax.checkpoint``), rather than
  store its intermediates;
  ``camera_poses_held=True`` leaves the cameras' poses in the data as they came.
  These choices are flags of the tracing thread over patches shared by all
  threads: programs traced at once in several threads each take their own.

The remedies are written against ``mjx_internals.WRITTEN_FOR``; entering the
context with another MJX installed warns once (``mjx_internals.check_version``).
"""
from __future__ import annotations

import contextlib
import dataclasses
import functools
import threading
import types

import jax
import jax.numpy as jnp
import numpy as np
from jax.ad_checkpoint import checkpoint_name

from stablebptt.physics import applied_forces, kinematics_derivative, mass_solve, tree_sums
from stablebptt.physics.c_sensors import sensors_as_c_computes
from stablebptt.physics.backward_contacts import CLOSED_FORM_PAIRS, geometry_held
from stablebptt.physics.mjx_internals import collision_convex, collision_driver, mjx, smooth, solver, support
from stablebptt.physics.mjx_internals import types as mjx_types
from stablebptt.physics.mjx_patches import applied, choosing, tracing
from stablebptt.physics.values_kept import KEPT_VALUES


SOLVER_SOLUTION = "stablebptt_solver_solution"  # the solver's answer, by name: a rematerialised step keeps it
_KEPT_ACROSS_RECOMPUTE = (SOLVER_SOLUTION, KEPT_VALUES)


def solve_implicitly(model: mjx.Model, data: mjx.Data) -> mjx.Data:
    """MJX's constraint solver, differentiated implicitly at the acceleration it finds.

    The solver minimizes a convex cost in the acceleration, so at its minimum
    the cost's gradient g vanishes and d qacc = -H^-1 (d g at fixed qacc), H
    the cost's Hessian: one Newton step's tangent, taken at the solution. Its
    value is 0 there, so values are the solver's; its tangent is the solution's
    (implicit function theorem), not that of the iterations that found it.
    Differentiating the iterations instead goes wrong where the start is already
    optimal: a joint at rest in friction loss (dm_control's finger) keeps the
    unconstrained acceleration's tangent, off by 10x in the constraint force.
    The iterations themselves are not differentiated at all, so reverse mode
    passes the model's own solver (its while loop) as forward mode does. Where
    the model allows at most ``BOUNDED_SOLVER_ITERATIONS``, that loop runs as one
    of exactly its iterations (``_solver_while_loop``): the same solution.
    """
    with _solver_loop_bound(model.opt.iterations):
        solved = _SOLVE(model, jax.lax.stop_gradient(data))
    # Named, a step rematerialised in the backward pass (``_step_as_chosen``) keeps the solution rather than
    # running the solver's iterations again: they have no derivative, only values.
    solved = solved.tree_replace({
        "qacc": checkpoint_name(solved.qacc, SOLVER_SOLUTION),
        "qfrc_constraint": checkpoint_name(solved.qfrc_constraint, SOLVER_SOLUTION),
        "_impl.efc_force": checkpoint_name(solved._impl.efc_force, SOLVER_SOLUTION)})
    newton = model.replace(opt=model.opt.replace(solver=mjx_types.SolverType.NEWTON))
    at_solution = solver.Context.create(newton, data.replace(qacc=solved.qacc), grad=False)
    # The theorem holds H where the solution is: only g's tangent is taken, not H's (whose term,
    # H^-1 dH H^-1 g, is the solver's residual g carried along, and which XLA would otherwise compile
    # through the Hessian's assembly and Cholesky factorisation).
    correction = -_newton_direction(newton, data, at_solution, hold_hessian=True)[1]  # ~0 in value
    qacc = solved.qacc + correction - jax.lax.stop_gradient(correction)
    # At the minimum M qacc - qfrc_smooth - qfrc_constraint = 0: the constraint force's tangent.
    balance = support.mul_m(model, data, qacc) - data.qfrc_smooth
    qfrc_constraint = solved.qfrc_constraint + balance - jax.lax.stop_gradient(balance)
    return data.tree_replace({"qacc": qacc, "qfrc_constraint": qfrc_constraint,
                              "_impl.efc_force": solved._impl.efc_force})


@jax.custom_jvp
def _sqrt_flat_at_zero(x):
    return jnp.sqrt(x)


@_sqrt_flat_at_zero.defjvp
def _sqrt_flat_at_zero_jvp(primals, tangents):
    (x,), (x_dot,) = primals, tangents
    root = jnp.sqrt(x)
    return root, jnp.where(x > 0, x_dot / (2 * jnp.where(x > 0, root, 1.0)), 0.0)


# MJX's elliptic-cone line search takes the square root of a contact's squared
# tangential force, exactly 0 for a contact that does not slide: its slope there
# is 0 / 0 and turns every forward-mode step Jacobian into NaN, although the
# terms it feeds are masked out at 0. MJX's solver module alone gets a square
# root whose slope at 0 is 0; values are unchanged.
_SOLVER_NUMPY = type(jnp)("jax.numpy, square root flat at zero")
_SOLVER_NUMPY.__dict__.update({**vars(jnp), "sqrt": _sqrt_flat_at_zero})


@jax.custom_jvp
def _quotient_carrier(deriv_0, deriv_1):
    return deriv_0


@_quotient_carrier.defjvp
def _quotient_carrier_jvp(primals, tangents):
    (deriv_0, deriv_1), (deriv_0_dot, deriv_1_dot) = primals, tangents
    return deriv_0, deriv_0_dot - (deriv_0 / deriv_1) * deriv_1_dot


_SOLVE = solver.solve

# MJX's solver loops while its own test says go on: at most the model's iterations, ending early where
# the cost stops improving. On a GPU a loop of unknown length sends its test to the host and waits for
# the answer after every iteration, once per physics step; a loop of known length runs without. With a
# bound here, a model allowing at most that many iterations (MuJoCo Playground's envs allow 2-4) runs
# exactly its iterations, each taken only where MJX's test still says go on and otherwise keeping the
# state as it stood, as a batch's while loop already steps every state until the last is done and keeps
# each one where its own test stopped it: MJX's values (bit for bit in float64; in float32 XLA may fuse
# the two loops' arithmetic apart, the last digit; tests/envs/test_mjx_and_playground.py).
# 0: MJX's loop everywhere, the default. Timed with a bound of BOUND_OVER_PLAYGROUND_ITERATIONS
# (`benchmarks/update_program.py --bounded-solver-loop`), the walker's update at 1,280 envs on one H200
# took 215.2 against 217.1 ms, its forward window 58.9 against 63.0 ms; on the 2-core CPU the forward
# window ran 10-25% slower (docs/performance.md, "The update against its floor").
BOUNDED_SOLVER_ITERATIONS = 0
BOUND_OVER_PLAYGROUND_ITERATIONS = 8
_loop_bound = threading.local()


@contextlib.contextmanager
def _solver_loop_bound(iterations: int):
    """MJX's solver loop, traced within, runs exactly ``iterations`` times where they are few enough."""
    outer = getattr(_loop_bound, "iterations", None)
    _loop_bound.iterations = iterations if 1 < iterations <= BOUNDED_SOLVER_ITERATIONS else None
    try:
        yield
    finally:
        _loop_bound.iterations = outer


def _solver_while_loop(cond_fun, body_fun, init_val):
    """``jax.lax.while_loop`` for MJX's solver module: bounded where ``_solver_loop_bound`` set a bound."""
    bound = getattr(_loop_bound, "iterations", None)
    if bound is None:
        return jax.lax.while_loop(cond_fun, body_fun, init_val)

    def iteration(_, value):
        going = cond_fun(value)
        return jax.tree.map(lambda new, old: jnp.where(going, new, old), body_fun(value), value)

    return jax.lax.fori_loop(0, bound, iteration, init_val)


class _Forwarding(types.ModuleType):
    """A module that is ``original`` but for the attributes given."""

    def __init__(self, original: types.ModuleType, **replaced):
        super().__init__(f"{original.__name__}, the solver's loop bounded")
        self._original = original
        self.__dict__.update(replaced)

    def __getattr__(self, name):  # only for what is not replaced
        return getattr(self._original, name)


# MJX's solver module takes its loop from here (jax.lax.while_loop) and everything else from JAX.
_SOLVER_JAX = _Forwarding(jax, lax=_Forwarding(jax.lax, while_loop=_solver_while_loop))
_LS_POINT_CREATE = solver._LSPoint.create


def _ls_point_create_stable(cls, *args, **kwargs):
    point = _LS_POINT_CREATE.__func__(cls, *args, **kwargs)
    return point.replace(deriv_0=_quotient_carrier(point.deriv_0, point.deriv_1),
                         deriv_1=jax.lax.stop_gradient(point.deriv_1))


# MJX's line search steps to alpha - deriv_0 / deriv_1, and those are the only
# differentiable use of a point's two derivatives (everywhere else they are
# compared). The slope of a quotient in deriv_1 is -deriv_0 / deriv_1**2, which
# XLA evaluates as deriv_0 / (deriv_1 * deriv_1): where the search direction is
# rounding noise (no constraint active, the unconstrained acceleration already
# optimal), deriv_1 is ~1e-20 and its square underflows float32 to 0, giving
# inf, and NaN against the zero cotangent such a step gets. Points carry the
# same values, but deriv_1's tangent moves into deriv_0's as
# d deriv_0 - (deriv_0 / deriv_1) d deriv_1 (deriv_1 itself gets none), so the
# quotient's derivative, (d deriv_0 - ratio d deriv_1) / deriv_1, is unchanged
# and has no square, in forward and reverse mode alike.


def _closest_segment_point_plane_stable(a, b, p0, plane_normal):
    n = plane_normal
    along = jnp.sum(n * (b - a))
    denominator = along + 1e-6 * (along == 0.0)
    numerator = jnp.sum(p0 * n) - jnp.sum(n * a)
    raw = jax.lax.stop_gradient(numerator / denominator)
    on_segment = (raw >= 0) & (raw <= 1)
    t = jnp.where(on_segment, numerator / jnp.where(on_segment, denominator, 1.0), jnp.clip(raw, 0, 1))
    return a + t * (b - a)


# MJX clips a capsule's or box's edge against a convex body's side planes at
# t = distance / (normal . edge), clipped to [0, 1]. For a plane nearly
# parallel to the edge the quotient is huge and clipped away, so its cotangent
# is 0, but the quotient's slope in the denominator, -t / denominator, is inf in
# float32: 0 x inf gives NaN in reverse mode (manipulator, stacker). Here a
# clipped t is a constant, as its derivative already says, and the quotient is
# only formed where it lands on the segment; values are unchanged.

_UPDATE_GRADIENT = solver._update_gradient


def _update_gradient_by_blocks(model: mjx.Model, data: mjx.Data, ctx: solver.Context) -> solver.Context:
    """MJX's Newton gradient step, its elliptic-cone Hessian summed block by block.

    MJX adds each contact's cone block into a dense [rows, rows] matrix, one traced update per contact,
    and then forms J^T (that matrix) J: for manipulator's 281 contacts, 1208 rows, 281 updates of a
    1208 x 1208 matrix per Newton iteration and per trace. The same Hessian is
    J^T diag(D active) J + the sum over contacts of J_c^T H_c J_c, J_c the contact's rows: one gather
    and one contraction per cone dimension. Other solvers and cones are MJX's own.
    """
    if not (model.opt.solver == mjx_types.SolverType.NEWTON and model.opt.cone == mjx_types.ConeType.ELLIPTIC):
        return _UPDATE_GRADIENT(model, data, ctx)
    grad, mgrad = _newton_direction(model, data, ctx)
    return ctx.replace(grad=grad, Mgrad=mgrad)


def _newton_direction(model: mjx.Model, data: mjx.Data, ctx: solver.Context,
                      hold_hessian: bool = False) -> tuple[jax.Array, jax.Array]:
    """The solver cost's gradient g in the acceleration and H^-1 g (``hold_hessian``: H without a tangent)."""
    grad = ctx.Ma - data.qfrc_smooth - ctx.qfrc_constraint
    hessian = _newton_hessian(model, data, ctx)
    if hold_hessian:
        hessian = jax.lax.stop_gradient(hessian)
    return grad, jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(hessian), grad)


def _newton_hessian(model: mjx.Model, data: mjx.Data, ctx: solver.Context) -> jax.Array:
    """The Hessian of the constraint solver's cost in the acceleration, symmetrised as MJX's Newton solver
    has it: M + J^T diag(D active) J, plus each elliptic cone's J_c^T H_c J_c (``ctx`` from
    ``solver._update_constraint``)."""
    jacobian, contact = data._impl.efc_J, data._impl.contact
    hessian = (jacobian.T * (data._impl.efc_D * ctx.active)) @ jacobian
    if model.opt.cone == mjx_types.ConeType.ELLIPTIC:
        cones = np.asarray(contact.dim) > 1  # static: the contacts' dimensions and rows are known while tracing
        dims, addresses = np.asarray(contact.dim)[cones], np.asarray(contact.efc_address)[cones]
        for dim in sorted(set(dims.tolist())):
            which = np.flatnonzero(dims == dim)  # ctx.h holds one block per cone contact, in this order
            rows = jacobian[addresses[which][:, None] + np.arange(dim)]  # [contacts, dim, nv]
            hessian = hessian + jnp.einsum("cki,ckl,clj->ij", rows, ctx.h[which, :dim, :dim], rows)
    hessian = support.full_m(model, data) + hessian
    return (hessian + hessian.T) * 0.5


# (module, attribute, replacement) of every remedy; applied forces' derivative through subtree sums among them.
_REMEDIES = (
    (solver, "jp", _SOLVER_NUMPY),
    (solver, "_update_gradient", _update_gradient_by_blocks),
    (solver._LSPoint, "create", classmethod(_ls_point_create_stable)),
    (collision_convex, "_closest_segment_point_plane", _closest_segment_point_plane_stable),
    *applied_forces.REMEDIES,
    *kinematics_derivative.REMEDIES,
    *tree_sums.REMEDIES,
    *mass_solve.REMEDIES,
)


def _solve_as_chosen(solve):
    """MJX's constraint solver ``solve``, differentiated at its solution where this thread's trace asks
    (``solve_implicitly``); its loop is bounded only within that (``_solver_loop_bound``, a thread's own).
    It carries ``solve``'s name: MJX's forward pass names the solver's scope after the function it calls."""
    @functools.wraps(solve)
    def solve_as_chosen(model, data):
        return (solve_implicitly if tracing.implicit_solver else solve)(model, data)
    return solve_as_chosen


def _collision_as_chosen(collide):
    """``collide`` (an MJX collision function of one geom-type pair), its geometry held where this thread's
    trace asks (``backward_contacts.geometry_held``). A flag of the thread, not a patch of its own:
    programs are traced in several threads at once."""
    held = geometry_held(collide)

    def collide_as_chosen(model, data, key, geoms):
        return (held if tracing.geometry_held else collide)(model, data, key, geoms)
    collide_as_chosen.ncon = collide.ncon
    return collide_as_chosen


@contextlib.contextmanager
def _contact_geometry_held():
    # MJX looks its pairs' functions up in this table at every collision: those with a closed form are
    # wrapped while any held trace runs, the table as it stands then (another patch of it kept).
    def table():
        return ((collision_driver, "_COLLISION_FUNC", {
            types: _collision_as_chosen(collide) if types in CLOSED_FORM_PAIRS else collide
            for types, collide in collision_driver._COLLISION_FUNC.items()}),)
    with applied("geometry", table), choosing("geometry_held"):
        yield


def _step_as_chosen(step):
    """``mjx.step`` rematerialized where this thread's trace asks: reverse mode keeps the step's inputs, the
    solver's solution and the values ``KEPT_VALUES`` names, and runs the rest of the step again in the backward pass, so
    a loop of physics steps (MuJoCo Playground's control step) stores one state per physics step instead of
    every intermediate of each step."""
    def step_as_chosen(model, data):
        if not tracing.physics_steps_recomputed:
            return step(model, data)
        tracing.steps_recomputed += 1
        # A new function at every call: jax.checkpoint keeps the program it traced per function and
        # shapes, and the step's program depends on the trace's other choices (the held geometry, the
        # implicit solver). prevent_cse off: within a loop of physics steps JAX's guard against XLA
        # merging the recomputation back into the forward pass is not needed, and is a barrier.
        # The solver's solution is kept (``SOLVER_SOLUTION``): its iterations are not run again; so are the
        # values of MJX's functions this package differentiates (``KEPT_VALUES``), whose tangents read them
        # and the functions' inputs.
        kept = jax.checkpoint_policies.save_only_these_names(*_KEPT_ACROSS_RECOMPUTE)
        return jax.checkpoint(lambda model, data: step(model, data), prevent_cse=False, policy=kept)(model, data)
    return step_as_chosen


@contextlib.contextmanager
def _physics_steps_recomputed():
    # Environments call mjx.step through MJX's package (MuJoCo Playground's mjx_env.step does): patched
    # there while any such trace runs, each call asking its thread's flag.
    with applied("recomputed", lambda: ((mjx, "step", _step_as_chosen(mjx.step)),)), \
            choosing("physics_steps_recomputed"):
        yield


def _camlight_as_chosen(camlight):
    """MJX's camera poses (``smooth.camlight``), or where this thread's trace asks, the data's poses left as
    the step found them: neither computed nor differentiated."""
    def camlight_as_chosen(model, data):
        return data if tracing.camera_poses_held else camlight(model, data)
    return camlight_as_chosen


@contextlib.contextmanager
def held_camera_poses():
    """MJX code traced within leaves the cameras' poses in its data as they came in (``cam_xpos``,
    ``cam_xmat``: MJX computes them in every forward pass, for the sensors and the renderer that read
    them). For a step nothing it returns reads them by (``envs.unread_outputs``); every other value is
    MJX's own. Reentrant; undone on exit."""
    with applied("cameras", lambda: ((smooth, "camlight", _camlight_as_chosen(smooth.camlight)),)), \
            choosing("camera_poses_held"):
        yield


@dataclasses.dataclass
class MjxTrace:
    """What the code traced within one ``differentiable_mjx`` context did, complete once the context has ended."""
    steps_recomputed: int = 0  # calls of mujoco.mjx.step recomputed in the backward pass


@contextlib.contextmanager
def differentiable_mjx(implicit_solver: bool = False, contact_geometry_held: bool = False,
                       physics_steps_recomputed: bool = False, camera_poses_held: bool = False):
    """Trace MJX code with its derivative traps remedied (and, optionally, its solver differentiated implicitly,
    and the contacts of ``backward_contacts.CLOSED_FORM_PAIRS`` with their points and frames held in the
    derivative and their distances differentiated by the closed form: ``backward_contacts.geometry_held``;
    each ``mjx.step`` recomputed in reverse mode's backward pass rather than its intermediates stored:
    ``physics_steps_recomputed``; the cameras' poses left as the data had them: ``held_camera_poses``).

    Values are MJX's own either way (held camera poses aside), its acceleration sensors computed also where
    the model has no constraint rows and RK4's sensors the start state's, as C's
    (``sensors_as_c_computes``). Reentrant; undone on exit, so MJX outside
    this library is unchanged. Use it around the tracing of a step::

        with differentiable_mjx(implicit_solver=True):
            next_state = env.step(state, action)   # mjx.step inside: reverse mode passes its solver

    It yields an ``MjxTrace``: with ``physics_steps_recomputed``, an env that calls no ``mujoco.mjx.step``
    through MJX's package (one that bound the function before the context opened) counts none.
    """
    trace, before = MjxTrace(), tracing.steps_recomputed
    with contextlib.ExitStack() as stack:
        stack.enter_context(applied("remedies", _REMEDIES))
        stack.enter_context(sensors_as_c_computes())
        if implicit_solver:
            stack.enter_context(applied("implicit", lambda: ((solver, "solve", _solve_as_chosen(solver.solve)),
                                                              (solver, "jax", _SOLVER_JAX))))
            stack.enter_context(choosing("implicit_solver"))
        if contact_geometry_held:
            stack.enter_context(_contact_geometry_held())
        if physics_steps_recomputed:
            stack.enter_context(_physics_steps_recomputed())
        if camera_poses_held:
            stack.enter_context(held_camera_poses())
        try:
            yield trace
        finally:
            trace.steps_recomputed = tracing.steps_recomputed - before


def traced_differentiably(function, implicit_solver: bool = False):
    """``function`` traced inside ``differentiable_mjx`` whenever it is called."""
    def wrapped(*args, **kwargs):
        with differentiable_mjx(implicit_solver):
            return function(*args, **kwargs)

    return wrapped
