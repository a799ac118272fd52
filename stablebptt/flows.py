"""The gradient flows of backpropagation through time and their combination.

A controller ``policy(params, state) -> control`` drives a simulator
``step(state, control) -> state`` for ``horizon`` steps and a loss is taken on
the visited states and controls. The flows differ only in where the backward
pass is cut, never in the forward values (Schnell & Thuerey, ICLR 2024):

====  ==========================  ===========================  ======================
flow  policy sees                 simulator sees               gradient
====  ==========================  ===========================  ======================
R     x_t                         x_t                          regular BPTT
M     stop_gradient(x_t)          x_t                          physics path only
S     stop_gradient(x_t)          stop_gradient(x_t)           one-step only
====  ==========================  ===========================  ======================

The combined update C keeps g_M where it agrees in sign with g_R, else 0.

All flows a training step needs come from ONE forward rollout, in one of two
ways (``Dynamics.step_derivative``):

- ``"reverse"``: every step is a ``custom_vjp`` that stores the simulator's
  and the policy's pullbacks once and, in the reverse pass, pulls back one
  cotangent per flow through them together.
- ``"forward"``: the rollout stores only states and controls. A step's
  Jacobian depends on nothing but its own (x_t, u_t), so the Jacobians of ALL
  steps are built afterwards in one batched forward-mode pass (not one small
  pass per step), and the reverse pass becomes a linear recurrence of small
  matrix products, one adjoint per flow. The policy's parameter gradient is
  then one batched pullback over every visited state.

``reference_rollout`` is the literal stop_gradient transcription of the table,
kept as the definition both paths are tested against.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.flatten_util import ravel_pytree

PyTree = Any
FLOWS = ("R", "M", "S")

# Which parts of the pulled-back state cotangent each flow keeps:
# (through the simulator, through the policy's input).
_KEEPS = {"R": (True, True), "M": (True, False), "S": (False, False)}


class KnownColumns(NamedTuple):
    """Columns of a step's state Jacobian known in advance, over the flattened state.

    Column ``columns[:, i]`` is d step(x, u) / d x[indices[i]] at every (x, u):
    a symmetry, such as a shift that passes straight through to the next state.
    Both arrays are static NumPy arrays.
    """

    indices: np.ndarray  # [known] entries of the flattened state
    columns: np.ndarray  # [state, known]


@dataclass(frozen=True)
class Dynamics:
    """What BPTT differentiates: a policy, a simulator step and a trajectory loss.

    Attributes:
      step: ``step(state, control) -> state``; a pytree of float arrays.
      policy: ``policy(params, state) -> control``; observation included.
      loss: ``loss(states, controls) -> scalar`` for ONE trajectory, where
        ``states`` stacks x_1..x_T and ``controls`` stacks u_0..u_{T-1}.
      horizon: number of steps T.
      step_derivative: how the reverse pass differentiates ``step``:
        ``"reverse"`` pulls cotangents back through it step by step (best for
        large states); ``"forward"`` builds every step's full Jacobian by
        forward mode, all steps in one batched pass after the rollout, and
        runs the reverse pass on them (see the module docstring). For small
        states simulated by many tiny operations (MJX) this replaces thousands
        of tiny sequential kernels by a few large ones.
      unroll: steps per iteration of the rollout loops (``lax.scan``'s
        ``unroll``). On a GPU, where each step is dozens of tiny kernels, 5-10
        cuts the kernels and copies per step; on a CPU 1 is fastest and
        compiles quickest.
      known_columns: optional, for ``"forward"``: columns of the step's state
        Jacobian that a symmetry fixes (``KnownColumns``), e.g. the position and
        velocity of a system nothing ties to the world (translation and Galilean
        boost). No tangent is pushed through the simulator for them.
      jacobian_chunk: for ``"forward"``: examples whose step Jacobians are
        computed at once (None: all T x batch); bounds the memory of large scenes
        (``stablebptt.memory.plan_memory`` chooses it).
      rematerialize: for ``"reverse"``: store only each step's inputs and
        recompute the step in the backward pass, trading one more forward pass
        for the memory of every step's intermediates.
      jacobian_per_input: for ``"forward"``: one forward pass per input leaf
        (True: each skips the stages its input does not reach) or one pass for
        all (False: one copy of the differentiated step, far quicker to compile
        for large scenes); see ``step_jacobians``.
      policy_gradient: for ``"reverse"``: ``"batched"`` computes each flow's
        parameter gradient after the reverse pass, in one batched pullback over
        every visited state (few large matrix products; the flows that do not
        pass through the policy's input then skip it per step), at the price of
        one more policy forward pass over those states; ``"per-step"`` pulls
        every flow back through the policy at every step (cheaper where the
        policy's batched backward pass is slow: XLA's CPU convolutions).
    """

    step: Callable[[PyTree, PyTree], PyTree]
    policy: Callable[[PyTree, PyTree], PyTree]
    loss: Callable[[PyTree, PyTree], jax.Array]
    horizon: int
    step_derivative: str = "reverse"
    unroll: int = 1
    known_columns: KnownColumns | None = None
    jacobian_chunk: int | None = None
    rematerialize: bool = False
    jacobian_per_input: bool = True
    policy_gradient: str = "batched"


@dataclass(frozen=True)
class Mode:
    """A training mode: the flows its update needs and how it combines their gradients.

    Attributes:
      name: the ``--mode`` value.
      flows: the flows it needs, in canonical order (``FLOWS``).
      combine: ``combine(gradients) -> update``, ``gradients`` a dict flow -> gradient pytree.
      description: a few words for help texts.
    """

    name: str
    flows: tuple[str, ...]
    combine: Callable[[dict[str, PyTree]], PyTree]
    description: str


def _only(flow: str) -> Callable[[dict[str, PyTree]], PyTree]:
    return lambda gradients: gradients[flow]


# Every mode, in the paper's order. A new combination of flows is one more row here.
MODE_TABLE: dict[str, Mode] = {mode.name: mode for mode in (
    Mode("R", ("R",), _only("R"), "regular BPTT"),
    Mode("M", ("M",), _only("M"), "the physics path"),
    Mode("S", ("S",), _only("S"), "one step"),
    Mode("C", ("R", "M"), lambda gradients: sign_agreement(gradients["M"], gradients["R"]),
         "combined: g_M where its sign agrees with g_R"),
)}
MODES = tuple(MODE_TABLE)


def flows_needed(mode: str, with_cosine: bool = True) -> tuple[str, ...]:
    """The flows a mode's update needs, in canonical order (R, M, S).

    Any mode also computes M and R when the cosine of the two is logged, which
    is cheap because the forward pass is shared.
    """
    if mode not in MODE_TABLE:
        raise ValueError(f"unknown mode {mode!r}: choose one of {', '.join(MODES)}")
    needed = set(MODE_TABLE[mode].flows)
    if with_cosine:
        needed |= {"M", "R"}
    return tuple(f for f in FLOWS if f in needed)


def _stack(tree: PyTree, copies: int) -> PyTree:
    return jax.tree.map(lambda a: jnp.broadcast_to(a, (copies,) + jnp.shape(a)), tree)


def _first(tree: PyTree) -> PyTree:
    return jax.tree.map(lambda a: a[0], tree)


def differentiable(leaf) -> bool:
    """Whether a state leaf carries a derivative: float and complex arrays do; integers, booleans and
    PRNG keys (a step counter, a contact index, an environment's key) pass through a rollout untouched."""
    return jnp.issubdtype(jnp.result_type(leaf), jnp.inexact)


class Parts(NamedTuple):
    """A state split into its differentiable leaves and the rest, to be put back by ``join``."""

    floats: list
    others: list
    treedef: Any
    is_float: tuple[bool, ...]


def split(tree: PyTree) -> Parts:
    leaves, treedef = jax.tree.flatten(tree)
    is_float = tuple(differentiable(leaf) for leaf in leaves)
    return Parts([a for a, f in zip(leaves, is_float) if f], [a for a, f in zip(leaves, is_float) if not f],
                 treedef, is_float)


def join(parts: Parts, floats: list | None = None, others: list | None = None) -> PyTree:
    """The state of ``parts`` with its float leaves (or its other leaves) replaced where given."""
    floats, others = iter(parts.floats if floats is None else floats), iter(parts.others if others is None else others)
    return jax.tree.unflatten(parts.treedef, [next(floats) if f else next(others) for f in parts.is_float])


def _no_cotangent(leaf) -> np.ndarray:
    """The cotangent JAX expects for a leaf with no derivative."""
    return np.zeros(np.shape(leaf), dtype=jax.dtypes.float0)


def _multi_adjoint_step(dynamics: Dynamics, flows: tuple[str, ...]):
    """One simulator step of a whole batch whose reverse pass carries one adjoint per flow (``"reverse"``).

    ``step(params, state_copies, control_offsets)``: states hold ``len(flows)``
    identical copies along a leading axis, then the batch; only the cotangents
    of the copies differ. The forward pass computes the step once. The batch
    lives inside the custom_vjp on purpose: one batched pullback per step,
    not one per example.

    The controls are ``policy(params, x) + control_offsets`` (the offsets are
    zeros), so the offsets' cotangent is each flow's adjoint of every control.
    With ``Dynamics.policy_gradient == "batched"`` the reverse pass returns no
    parameter cotangent: the parameter gradient is one batched pullback over
    all visited states afterwards (``_policy_gradients``), and the policy is
    pulled back per step only for the flows whose state cotangent passes
    through it (R). With ``"per-step"`` each step returns every flow's
    parameter cotangent (``params`` then holds one copy per flow).
    """
    copies = len(flows)
    # NumPy, not jnp: constants created under a trace would be tracers closed
    # over by the custom_vjp.
    keep_sim = np.array([_KEEPS[f][0] for f in flows])
    through_net = [index for index, f in enumerate(flows) if _KEEPS[f][1]]
    per_step = dynamics.policy_gradient == "per-step"
    batch_policy = jax.vmap(dynamics.policy, in_axes=(None, 0))
    batch_step = jax.vmap(dynamics.step)

    def select(mask, a):
        # where, not multiply: a cut path must not turn inf into NaN.
        return jnp.where(mask.reshape((copies,) + (1,) * (a.ndim - 1)), a, jnp.zeros_like(a))

    def forward(params, states):
        # Only float leaves are differentiated; the others (counters, keys, indices) ride along.
        parts = split(states)
        policy = batch_policy if per_step else lambda params, s: batch_policy(jax.lax.stop_gradient(params), s)
        controls, policy_pullback = jax.vjp(lambda p, floats: policy(p, join(parts, floats)), params, parts.floats)

        def float_step(floats, controls):
            reached = split(batch_step(join(parts, floats), controls))
            return reached.floats, reached.others

        next_floats, step_pullback, next_others = jax.vjp(float_step, parts.floats, controls, has_aux=True)
        return join(parts, next_floats, next_others), controls, (policy_pullback, step_pullback)

    def outputs(next_states, controls, control_offsets):
        return _stack(next_states, copies), jax.tree.map(jnp.add, _stack(controls, copies), control_offsets)

    params_of = _first if per_step else lambda params: params

    @jax.custom_vjp
    def step(params, state_copies, control_offsets):
        next_states, controls, _ = forward(params_of(params), _first(state_copies))
        return outputs(next_states, controls, control_offsets)

    def step_fwd(params, state_copies, control_offsets):
        states = _first(state_copies)
        next_states, controls, pullbacks = forward(params_of(params), states)
        residuals = (params_of(params), states) if dynamics.rematerialize else pullbacks
        return outputs(next_states, controls, control_offsets), (residuals, params)

    def step_bwd(saved, cotangents):
        residuals, params = saved
        policy_pullback, step_pullback = forward(*residuals)[2] if dynamics.rematerialize else residuals
        next_state_ct, control_ct = cotangents
        # Leaves without a derivative get float0 cotangents, which mark them here.
        parts = split_cotangent(next_state_ct)
        state_ct_sim, control_ct_sim = jax.vmap(step_pullback)(parts.floats)
        control_ct = jax.tree.map(jnp.add, control_ct, control_ct_sim)
        state_ct = [select(keep_sim, sim) for sim in state_ct_sim]
        if per_step:  # one pullback per flow gives its parameter cotangent and, for R, its state's
            params_ct, net = jax.vmap(policy_pullback)(control_ct)
            net = [select(np.isin(np.arange(copies), through_net), a) for a in net]
            return params_ct, join(parts, [a + b for a, b in zip(state_ct, net)]), control_ct
        if through_net:
            rows = np.array(through_net)
            net = jax.vmap(lambda ct: policy_pullback(ct)[1])(jax.tree.map(lambda a: a[rows], control_ct))
            state_ct = [total.at[rows].add(part) for total, part in zip(state_ct, net)]
        return jax.tree.map(jnp.zeros_like, params), join(parts, state_ct), control_ct

    step.defvjp(step_fwd, step_bwd)
    return step


def split_cotangent(cotangent: PyTree) -> Parts:
    """A cotangent split as ``split`` splits its primal: float0 leaves belong to leaves without a derivative."""
    leaves, treedef = jax.tree.flatten(cotangent)
    is_float = tuple(leaf.dtype != jax.dtypes.float0 for leaf in leaves)
    return Parts([a for a, f in zip(leaves, is_float) if f], [a for a, f in zip(leaves, is_float) if not f],
                 treedef, is_float)


def _ravel_examples(tree: PyTree, leading_axes: int) -> jax.Array:
    """Each example of ``tree`` (after ``leading_axes`` batch axes) as one flat vector."""
    ravel = lambda example: ravel_pytree(example)[0]
    for _ in range(leading_axes):
        ravel = jax.vmap(ravel)
    return ravel(tree)


def step_jacobians(step, states: PyTree, controls: PyTree, known: KnownColumns | None = None,
                   chunk: int | None = None, per_input: bool = True) -> tuple[jax.Array, jax.Array]:
    """Jacobians of ``step`` at every example of a batch, by forward mode.

    With ``per_input`` (the default), one forward pass per input leaf (a state
    leaf such as qpos or qvel, or the control), with the other leaves held
    fixed. A simulator therefore sees which inputs vary (a ``custom_jvp`` with
    ``symbolic_zeros=True`` gets symbolic zeros for the others) and can skip the
    stages they do not reach: velocity tangents need no kinematics, control
    tangents only the actuators. Without it, one pass pushes every tangent at
    once: more work per tangent, but one copy of the differentiated step in the
    program, which compiles several times faster for large scenes. Columns in
    ``known`` are copied, not computed. ``chunk`` examples at a time (default:
    all) bound the memory.

    Returns:
      ``(state_jacobian [batch, state, state], control_jacobian [batch, state, control])``
      over the flattened state and control pytrees (``ravel_pytree`` order of the state's float
      leaves; its other leaves have no derivative).
    """
    state_size = sum(leaf.size for leaf in split(jax.tree.map(lambda a: a[0], states)).floats)  # the output is a state too
    known_at = {} if known is None else {int(i): np.asarray(c) for i, c in zip(known.indices, np.transpose(known.columns))}

    def one(state, control):
        parts = split(state)  # leaves without a derivative are held, not differentiated
        leaves, treedef = jax.tree.flatten((parts.floats, control))
        sizes = [leaf.size for leaf in leaves]
        offsets = np.cumsum([0] + sizes)
        # Input groups pushed together: each leaf alone, or all leaves in one pass.
        groups = [[index] for index in range(len(leaves))] if per_input else [list(range(len(leaves)))]
        blocks = []
        for group in groups:
            columns_of_group = [offsets[index] + k for index in group for k in range(sizes[index])]
            copied = np.zeros((state_size, len(columns_of_group)), np.result_type(*[leaves[i].dtype for i in group]))
            free = []
            for position, column in enumerate(columns_of_group):
                if column in known_at:  # only state columns are ever known
                    copied[:, position] = known_at[column]
                else:
                    free.append(position)
            if not free:
                blocks.append(jnp.asarray(copied))
                continue

            def of_group(flat, group=group):  # step's flat output as a function of the group's inputs
                inputs, start = list(leaves), 0
                for index in group:
                    inputs[index] = flat[start:start + sizes[index]].reshape(leaves[index].shape)
                    start += sizes[index]
                floats, control = jax.tree.unflatten(treedef, inputs)
                return ravel_pytree(split(step(join(parts, floats), control)).floats)[0]

            point = jnp.concatenate([leaves[index].ravel() for index in group])
            # Constant unit tangents for the free entries only: no scatter of a tangent to trace.
            basis = np.eye(len(columns_of_group), dtype=copied.dtype)[free]
            columns = jax.vmap(lambda tangent: jax.jvp(of_group, (point,), (tangent,))[1], out_axes=1)(basis)
            if len(free) < len(columns_of_group):
                columns = copied + jnp.matmul(columns, basis, precision=jax.lax.Precision.HIGHEST)
            blocks.append(columns)
        jacobian = jnp.concatenate(blocks, axis=1)  # columns in ravel_pytree order of (state, control)
        return jacobian[:, :state_size], jacobian[:, state_size:]

    if chunk is None:
        return jax.vmap(one)(states, controls)
    return jax.lax.map(lambda example: one(*example), (states, controls), batch_size=chunk)


def _merge(tree: PyTree, axes: int) -> PyTree:
    """Merge the first ``axes`` axes of every leaf into one."""
    return jax.tree.map(lambda a: a.reshape((math.prod(a.shape[:axes]),) + a.shape[axes:]), tree)


def _linearized_gradients(dynamics: Dynamics, flows: tuple[str, ...], params: PyTree, initial_states: PyTree):
    """``flow_gradients`` by rollout, batched step Jacobians and an adjoint recurrence (``"forward"``)."""
    horizon, batch_size = dynamics.horizon, jax.tree.leaves(initial_states)[0].shape[0]
    batch_policy = jax.vmap(dynamics.policy, in_axes=(None, 0))
    batch_step = jax.vmap(dynamics.step)

    def advance(states, _):
        controls = batch_policy(params, states)
        return batch_step(states, controls), (states, controls)

    final, (visited, controls) = jax.lax.scan(advance, initial_states, None, length=horizon, unroll=dynamics.unroll)
    # visited holds x_0..x_{T-1}, [T, batch, ...]; the loss sees x_1..x_T.
    reached = jax.tree.map(lambda past, last: jnp.concatenate([past[1:], last[None]]), visited, final)

    reached_parts = split(reached)

    def batch_loss(floats, controls):
        return jax.vmap(dynamics.loss, in_axes=(1, 1))(join(reached_parts, floats), controls).mean()

    loss, (state_grad, control_grad) = jax.value_and_grad(batch_loss, argnums=(0, 1))(reached_parts.floats, controls)
    state_grad, control_grad = _ravel_examples(state_grad, 2), _ravel_examples(control_grad, 2)

    # Every step's Jacobians in one batched pass over [T * batch] examples.
    state_jacobian, control_jacobian = step_jacobians(dynamics.step, _merge(visited, 2), _merge(controls, 2),
                                                       dynamics.known_columns, dynamics.jacobian_chunk,
                                                       dynamics.jacobian_per_input)
    unmerge = lambda a: a.reshape((horizon, batch_size) + a.shape[1:])
    state_jacobian, control_jacobian = unmerge(state_jacobian), unmerge(control_jacobian)

    visited_parts = split(visited)
    unravel_floats = ravel_pytree([a[0, 0] for a in visited_parts.floats])[1]
    flat_visited = _ravel_examples(visited_parts.floats, 2)

    def flat_policy(params, flat_state, others):
        return ravel_pytree(dynamics.policy(params, join(visited_parts, unravel_floats(flat_state), others)))[0]

    policy_jacobian = None
    if "R" in flows:  # only R pulls adjoints back through the policy's input
        state_size, control_size = flat_visited.shape[-1], control_grad.shape[-1]
        jacobian = jax.jacrev if control_size < state_size else jax.jacfwd
        policy_jacobian = jax.vmap(jax.vmap(jacobian(flat_policy, argnums=1), in_axes=(None, 0, 0)),
                                   in_axes=(None, 0, 0))(params, flat_visited, visited_parts.others)  # [T, batch, control, state]

    copies = len(flows)
    keep_sim = np.array([_KEEPS[f][0] for f in flows]).reshape(copies, 1, 1)
    keep_net = np.array([_KEEPS[f][1] for f in flows]).reshape(copies, 1, 1)

    def vector_times_jacobian(vectors, jacobians):
        """[copies, batch, rows] x [batch, rows, columns] -> [copies, batch, columns].

        Multiply and sum, not a matrix product: XLA fuses the products of one
        step into a few loops in full float32 (GPUs would take TF32 matmuls),
        where batched matrix products of a few rows each cost a library call apiece.
        """
        return jnp.sum(vectors[..., :, None] * jacobians[None], axis=-2)

    def pull_back(adjoint, step):
        """From the adjoint of x_{t+1} per flow [copies, batch, state] to that of x_t, and u_t's."""
        state_jac, control_jac, policy_jac, direct_state, direct_control = step
        control_adjoint = direct_control + vector_times_jacobian(adjoint, control_jac)
        through_sim = vector_times_jacobian(adjoint, state_jac)
        # where, not multiply: a cut path must not turn inf into NaN.
        state_adjoint = direct_state + jnp.where(keep_sim, through_sim, 0.0)
        if policy_jac is not None:
            through_net = vector_times_jacobian(control_adjoint, policy_jac)
            state_adjoint = state_adjoint + jnp.where(keep_net, through_net, 0.0)
        return state_adjoint, control_adjoint

    # The loss's direct gradient on x_t (none on x_0, which is not a result of the rollout).
    direct_state = jnp.concatenate([jnp.zeros_like(state_grad[:1]), state_grad[:-1]])
    _, control_adjoints = jax.lax.scan(
        pull_back, _stack(state_grad[-1], copies),
        (state_jacobian, control_jacobian, policy_jacobian, direct_state, control_grad),
        reverse=True, unroll=dynamics.unroll)  # [T, copies, batch, control]

    return loss, _policy_gradients(dynamics, params, visited, control_adjoints)


def _policy_gradients(dynamics: Dynamics, params: PyTree, visited: PyTree, control_adjoints: jax.Array) -> PyTree:
    """Each flow's parameter gradient: the sum over steps and examples of (du_t/dparams)^T adjoint(u_t).

    One batched pullback over every visited state (``visited``: x_0..x_{T-1},
    [T, batch, ...]), one per flow (``control_adjoints``: [T, copies, batch,
    control], flattened controls): a few large matrix products instead of small
    ones per step.
    """
    horizon, copies, batch_size = control_adjoints.shape[:3]
    examples = _merge(visited, 2)  # [T * batch, ...], leaves without a derivative included

    def flat_controls(params):
        return _ravel_examples(jax.vmap(dynamics.policy, in_axes=(None, 0))(params, examples), 1)

    _, policy_pullback = jax.vjp(flat_controls, params)
    per_flow = jnp.moveaxis(control_adjoints, 1, 0).reshape((copies, horizon * batch_size, -1))
    return jax.vmap(lambda adjoint: policy_pullback(adjoint)[0])(per_flow)


def flow_losses(dynamics: Dynamics, flows: tuple[str, ...], params: PyTree, initial_states: PyTree,
                control_offsets: PyTree):
    """Mean batch loss once per flow copy (identical values, distinct gradients), and the visited states.

    ``params`` holds one copy per flow (leading axis) where
    ``dynamics.policy_gradient`` is ``"per-step"``. Differentiated with respect
    to ``control_offsets`` (zeros added to the controls, [T, copies, batch, ...]),
    it gives every flow's adjoint of every control. Returns ``(losses [copies], x_0..x_{T-1})``.
    """
    step = _multi_adjoint_step(dynamics, flows)
    copies = len(flows)

    def body(state_copies, offsets):
        next_copies, control_copies = step(params, state_copies, offsets)
        return next_copies, (_first(state_copies), next_copies, control_copies)

    _, (visited, states, controls) = jax.lax.scan(body, _stack(initial_states, copies), control_offsets,
                                                  unroll=dynamics.unroll)
    # scan stacks time first, [T, copies, batch, ...]; the loss wants one trajectory's [T, ...].
    per_trajectory = jax.vmap(jax.vmap(dynamics.loss, in_axes=(1, 1)), in_axes=(1, 1))(states, controls)
    return per_trajectory.mean(axis=1), visited


def flow_gradients(dynamics: Dynamics, flows: tuple[str, ...], params: PyTree, initial_states: PyTree):
    """Mean batch loss and the gradient of every flow from one forward rollout.

    Args:
      dynamics: the system to differentiate.
      flows: names from ``FLOWS``, e.g. ``("R", "M")``.
      params: policy parameters.
      initial_states: a batch of initial states (leading axis = batch).

    Returns:
      ``(loss, grads)`` where each leaf of ``grads`` has a leading axis of
      length ``len(flows)`` in the order of ``flows``.
    """
    if dynamics.step_derivative == "forward":
        return _linearized_gradients(dynamics, flows, params, initial_states)

    control = jax.eval_shape(jax.vmap(dynamics.policy, in_axes=(None, 0)), params, initial_states)
    offsets = jax.tree.map(lambda a: jnp.zeros((dynamics.horizon, len(flows)) + a.shape, a.dtype), control)
    per_step = dynamics.policy_gradient == "per-step"

    def total(params, offsets):
        per_flow, visited = flow_losses(dynamics, flows, params, initial_states, offsets)
        return per_flow.sum(), (per_flow[0], visited)

    (params_grads, control_adjoints), (loss, visited) = jax.grad(total, argnums=(0, 1), has_aux=True)(
        _stack(params, len(flows)) if per_step else params, offsets)
    if per_step:
        return loss, params_grads
    return loss, _policy_gradients(dynamics, params, visited, _ravel_examples(control_adjoints, 3))


class Trajectory(NamedTuple):
    states: PyTree  # x_1..x_T
    controls: PyTree  # u_0..u_{T-1}


def reference_rollout(dynamics: Dynamics, params: PyTree, initial_state: PyTree, flow: str = "R") -> Trajectory:
    """The rollout with stop_gradient placed literally as in the table above."""
    cut_sim = not _KEEPS[flow][0]
    cut_net = not _KEEPS[flow][1]

    def body(state, _):
        control = dynamics.policy(params, jax.lax.stop_gradient(state) if cut_net else state)
        next_state = dynamics.step(jax.lax.stop_gradient(state) if cut_sim else state, control)
        return next_state, (next_state, control)

    _, (states, controls) = jax.lax.scan(body, initial_state, None, length=dynamics.horizon, unroll=dynamics.unroll)
    return Trajectory(states, controls)


def reference_losses(dynamics: Dynamics, params: PyTree, initial_states: PyTree, flow: str = "R") -> jax.Array:
    """The loss of each trajectory from a batch of initial states."""
    def one(x0):
        trajectory = reference_rollout(dynamics, params, x0, flow)
        return dynamics.loss(trajectory.states, trajectory.controls)

    return jax.vmap(one)(initial_states)


def reference_loss(dynamics: Dynamics, params: PyTree, initial_states: PyTree, flow: str = "R") -> jax.Array:
    """Mean loss over a batch of initial states; differentiate it for the flow's gradient."""
    return reference_losses(dynamics, params, initial_states, flow).mean()


def sign_agreement(grad_m: PyTree, grad_r: PyTree) -> PyTree:
    """The combined update C: g_M where sign(g_M) == sign(g_R), else 0, element-wise."""
    return jax.tree.map(lambda m, r: jnp.where(jnp.sign(m) == jnp.sign(r), m, jnp.zeros_like(m)), grad_m, grad_r)


def tree_cosine(a: PyTree, b: PyTree) -> jax.Array:
    """Cosine similarity of two pytrees seen as flat vectors (0 if either is 0)."""
    dot = sum(jnp.vdot(x, y) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)))
    norms = optax.tree.norm(a) * optax.tree.norm(b)
    return jnp.where(norms > 0, dot / jnp.where(norms > 0, norms, 1.0), 0.0)


def select_flow(mode: str, flows: tuple[str, ...]) -> optax.GradientTransformation:
    """An optax transform turning stacked flow gradients into the update of ``mode``.

    Its input is the output of ``flow_gradients`` (a leading flow axis); its
    output is a plain gradient pytree, so it heads an ordinary chain::

        optimizer = optax.chain(select_flow("C", ("R", "M")),
                                optax.clip(1.0), optax.adam(1e-3))
    """
    needed = flows_needed(mode, with_cosine=False)
    missing = [f for f in needed if f not in flows]
    if missing:
        raise ValueError(f"mode {mode} needs flows {needed}, but only {flows} are computed")

    def update(updates, state, params=None):
        del params
        rows = {flow: jax.tree.map(lambda a, i=flows.index(flow): a[i], updates) for flow in needed}
        return MODE_TABLE[mode].combine(rows), state

    return optax.GradientTransformation(lambda params: optax.EmptyState(), update)
