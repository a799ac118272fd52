"""What MJX computes that an environment never reads: not simulated.

MJX computes every sensor of a model and every camera's pose at every physics step, and the
gradient path differentiates them. MuJoCo Playground's humanoid has an accelerometer, 6 force and 6
torque sensors, whose stage (``smooth.rne_postconstraint``) made nearly a third of its update's
compile on one H100, and its env reads one velocity sensor; every suite env has two to five
cameras, whose poses only a renderer reads (docs/performance.md, "The update against its floor":
"Sensors no one reads", "Cameras no one reads"). ``outputs_read`` finds, from the traced reset and
step, which sensors' values and whether the cameras' poses anything the env returns reads besides
the state's own copy of MJX's data; ``unread_outputs_off`` gives an env whose model leaves the
unread sensors out (their stage set to none, as MJX skips them) and says whether its step may leave
the cameras' poses as they came; its returns are the same to the bit. Where the trace does not tell
(a read it cannot follow, a field only the sensors' stages write read), every sensor and camera stays.
"""
from __future__ import annotations

import contextlib
import copy
import os
from typing import Any, Callable, Literal, NamedTuple

import jax
import jax.extend
import jax.numpy as jnp
import mujoco
import numpy as np

from stablebptt.engine import program_store
from stablebptt.envs.protocol import with_reset_traced_once
from stablebptt.physics.c_sensors import sensors_as_c_computes
from stablebptt.physics.constraint_derivatives import held_camera_poses

# Data fields only the sensors' stages write (MJX's sensor_vel and sensor_acc): read, every sensor stays.
_SENSOR_STAGE_FIELDS = ("cacc", "cfrc_int", "cfrc_ext", "subtree_linvel", "subtree_angmom")
_SENSOR_MODULE = os.path.join("mjx", "_src", "sensor.py")
_CAMERA_POSES = ("cam_xpos", "cam_xmat")
# Operations that write into an array and give it on, read by nothing: followed to what they give.
_WRITES = ("scatter", "dynamic_update_slice", "copy")


def _is_var(atom) -> bool:
    return isinstance(atom, jax.extend.core.Var)


def _in_sensor_stage(equation) -> bool:
    traceback = equation.source_info.traceback
    return traceback is not None and any(frame.file_name.endswith(_SENSOR_MODULE) for frame in traceback.frames)


def _inner(equation) -> list:
    return [getattr(inner, "jaxpr", inner) for inner in jax.extend.core.jaxprs_in_params(equation.params)]


def _follow(jaxpr, tracked: set, sensors_apart: bool = True) -> tuple[set[int] | None, set[int]]:
    """The elements of the vector ``tracked`` (ids of variables of ``jaxpr`` that hold it) that ``jaxpr``
    reads, and the outputs it reaches as it is; None where a use is not one of those followed.
    ``sensors_apart``: uses by MJX's sensor stage are not reads (the sensors' own are told apart)."""
    tracked, read = set(tracked), set()
    for equation in jaxpr.eqns:
        places = [place for place, atom in enumerate(equation.invars) if _is_var(atom) and id(atom) in tracked]
        if not places:
            continue
        name, params = equation.primitive.name, equation.params
        if sensors_apart and name not in _WRITES and _in_sensor_stage(equation):  # read by the stages that go with the sensors
            continue
        if name == "slice" and len(params["start_indices"]) == 1 and params["strides"] in (None, (1,)):
            read.update(range(params["start_indices"][0], params["limit_indices"][0]))
            continue
        if name in _WRITES:
            if places != [0]:  # written into another array, or its values used as indices
                return None, set()
            tracked.add(id(equation.outvars[0]))
            continue
        found = _through_call(equation, places, sensors_apart)
        if found is None:
            return None, set()
        inner_read, reached = found
        read |= inner_read
        tracked |= {id(equation.outvars[place]) for place in reached}
    return read, {place for place, atom in enumerate(jaxpr.outvars) if _is_var(atom) and id(atom) in tracked}


def _through_call(equation, places: list[int], sensors_apart: bool) -> tuple[set[int], set[int]] | None:
    """A call's reads of its arguments at ``places`` and the results they reach: a call that passes its
    arguments on one for one (jit, a custom derivative, a checkpoint), a loop's carry, a branch's operands."""
    name, params, inner = equation.primitive.name, equation.params, _inner(equation)
    if name == "scan":
        body = inner[0]
        consts, carried = _scan_parts(equation, body)
        if any(place >= consts + carried for place in places):  # a loop's sliced inputs: not followed
            return None
        return _loop(body, set(places), consts, carried, sensors_apart)
    if name == "while":
        if not {"cond_jaxpr", "body_jaxpr", "cond_nconsts", "body_nconsts"} <= set(params):
            return None
        cond, body = params["cond_jaxpr"].jaxpr, params["body_jaxpr"].jaxpr
        cond_consts, body_consts = params["cond_nconsts"], params["body_nconsts"]
        if any(place < cond_consts for place in places):
            return None
        found = _loop(body, {place - cond_consts for place in places}, body_consts, len(body.outvars), sensors_apart)
        if found is None:
            return None
        read, reached = found
        first_carried = cond_consts + body_consts
        carried = reached | {place - first_carried for place in places if place >= first_carried}
        cond_read, _ = _follow(cond, {id(cond.invars[cond_consts + carry]) for carry in carried}, sensors_apart)
        return None if cond_read is None else (read | cond_read, reached)
    if name == "cond":
        read, reached = set(), set()
        for branch in inner:
            found = _follow(branch, {id(branch.invars[place - 1]) for place in places if place > 0}, sensors_apart)
            if found[0] is None or 0 in places:
                return None
            read |= found[0]
            reached |= found[1]
        return read, reached
    one_for_one = len(inner) == 1 and (len(inner[0].invars), len(inner[0].outvars)) == (len(equation.invars),
                                                                                         len(equation.outvars))
    if one_for_one:
        found = _follow(inner[0], {id(inner[0].invars[place]) for place in places}, sensors_apart)
        return None if found[0] is None else found
    return None


def _scan_parts(equation, body) -> tuple[int, int]:
    """A scan's constants and carried values, counted from its shapes (JAX's parameters that count them have
    changed between versions): a carried value keeps its shape through the loop, a scanned one has the loop's
    axis outside it; its inputs are constants, carried values and scanned ones, in that order."""
    def same(outer, inside) -> bool:
        return tuple(outer.aval.shape) == tuple(inside.aval.shape)
    carried = next((place for place, (outer, inside) in enumerate(zip(equation.outvars, body.outvars))
                    if not same(outer, inside)), len(equation.outvars))
    scanned = sum(not same(outer, inside) for outer, inside in zip(equation.invars, body.invars))
    return len(equation.invars) - carried - scanned, carried


def _loop(body, places: set[int], consts: int, carried: int, sensors_apart: bool):
    """A loop body's reads of its inputs at ``places`` (``consts`` constants, then ``carried`` carried values), the
    carried ones fed back until no more are reached; the loop's results they reach (its carry, in the same places)."""
    while True:
        read, reached = _follow(body, {id(body.invars[place]) for place in places}, sensors_apart)
        if read is None or any(place >= carried for place in reached):  # stacked per iteration: not followed
            return None
        fed_back = places | {consts + place for place in reached}
        if fed_back == places:
            return read, reached
        places = fed_back


def _paths(tree) -> list[str]:
    """Each leaf's path, in the order the tree's leaves are a program's inputs and outputs."""
    return [jax.tree_util.keystr(leaf_path) for leaf_path, _ in jax.tree_util.tree_flatten_with_path(tree)[0]]


def _first_written(jaxpr, variable):
    """The array whose writes in ``jaxpr`` (operand first) made ``variable``: every value between is followed."""
    producers = {id(out): equation for equation in jaxpr.eqns for out in equation.outvars}
    while id(variable) in producers and producers[id(variable)].primitive.name in _WRITES:
        variable = producers[id(variable)].invars[0]
    return variable


def _elements_read(jaxpr, inputs: list, kept_output: int, sensors_apart: bool = True) -> set[int] | None:
    """The elements of one vector that ``jaxpr`` reads, held at input places ``inputs`` and output place
    ``kept_output`` (the returned state's own copy, not a read), followed from the array the output was
    written into (a reset that reads the sensors between two of MJX's forward passes reads the first's)."""
    tracked = {id(jaxpr.invars[place]) for place in inputs} | {id(_first_written(jaxpr, jaxpr.outvars[kept_output]))}
    read, reached = _follow(jaxpr, tracked, sensors_apart)
    if read is None or reached - {kept_output}:
        return None
    return read


class LeftOut(NamedTuple):
    """An env with what nothing it returns reads left out (``unread_outputs_off``), and what that was."""
    env: Any  # its reset jitted, traced once for every program and check (``protocol.with_reset_traced_once``)
    sensors: int  # sensors left out of its MJX model
    camera_poses_held: bool  # its step may leave the cameras' poses as they came (``differentiable_mjx``)


def outputs_read(env: Any, model: Any, step_context: Callable = contextlib.nullcontext,
                 sensors: bool = True) -> dict:
    """What of MJX's outputs ``env``'s reset or step gives on anything read from, besides the state's own
    data: ``"sensors"``, for each sensor of ``model`` (``env``'s MJX model) whether its values are read
    (asked where ``sensors``; None where the traces do not tell), and ``"camera poses"``: False where
    nothing in the step reads the cameras' poses (a sensor of the step among the readers), None where
    something does or the trace does not tell. The step is traced inside
    ``step_context()`` (the task's reward repair) with the cameras' poses held (``held_camera_poses``),
    so that a read of them anywhere in it is a read of the poses it was given; where ``sensors`` is
    False, the reset only for its shapes (``jax.eval_shape``: a jitted reset's one trace)."""
    key, action = jax.random.PRNGKey(0), jax.ShapeDtypeStruct((int(env.action_size),), jnp.result_type(float))
    try:
        with sensors_as_c_computes():  # as the task traces the reset and the step
            if sensors:
                reset, state = jax.make_jaxpr(env.reset, return_shape=True)(key)
            else:
                reset, state = None, jax.eval_shape(env.reset, key)
        with step_context(), held_camera_poses(), sensors_as_c_computes():
            step, reached = jax.make_jaxpr(env.step, return_shape=True)(state, action)
    except Exception:  # noqa: BLE001 - an env whose reset or step does not trace: the protocol's check names why
        return {"sensors": None, "camera poses": None}
    paths = _paths(state), _paths(reached), _paths((state, action))
    return {"sensors": _sensors_read(reset, step, paths, model) if sensors else None,
            "camera poses": _camera_poses_read(step, paths)}


def _field_places(name: str, paths: tuple[list[str], list[str], list[str]]) -> tuple[int, int, int] | None:
    """Where MJX's data field ``name`` lies among the reset's outputs, the step's outputs and its inputs;
    None where a state does not carry it there."""
    reset_paths, step_paths, input_paths = paths
    path = next((path for path in reset_paths if path.endswith(f".{name}")), None)
    if path is None or path not in step_paths or f"[0]{path}" not in input_paths:
        return None
    return reset_paths.index(path), step_paths.index(path), input_paths.index(f"[0]{path}")


def _sensors_read(reset, step, paths, model) -> list[bool] | None:
    read: set[int] = set()
    for name in ("sensordata",) + _SENSOR_STAGE_FIELDS:
        places = _field_places(name, paths)
        if places is None:  # a field this MJX does not have; a state without MJX's sensor data: not told
            if name == "sensordata" or any(path.endswith(f".{name}") for path in paths[0]):
                return None
            continue
        at_reset, at_step, given = places
        elements = [_elements_read(reset.jaxpr, [], at_reset), _elements_read(step.jaxpr, [given], at_step)]
        if any(found is None for found in elements) or (name != "sensordata" and any(elements)):
            return None
        if name == "sensordata":
            read = elements[0] | elements[1]
    addresses, sizes = np.asarray(model.sensor_adr), np.asarray(model.sensor_dim)
    return [bool(read & set(range(address, address + size))) for address, size in zip(addresses, sizes)]


def _camera_poses_read(step, paths) -> Literal[False] | None:
    """False where the step (traced with the poses held) reads neither camera field; else None."""
    for name in _CAMERA_POSES:
        places = _field_places(name, paths)
        # Held, a pose is the one the step was given: any use of it but the state's own copy reads it.
        if places is None or _elements_read(step.jaxpr, [places[2]], places[1], sensors_apart=False) != set():
            return None
    return False


def unread_outputs_off(env: Any, answer_key: dict | None = None, step_context: Callable = contextlib.nullcontext,
                       searched_alone: bool = True) -> LeftOut:
    """``env`` with its reset traced once (``protocol.with_reset_traced_once``) and what nothing it returns
    reads left out (``outputs_read``, its step traced inside ``step_context()``; kept under ``answer_key``
    as ``program_store.kept_answer`` keeps answers): where its MJX model (``_mjx_model``, MuJoCo
    Playground's) has a sensor of the acceleration stage, the costly one (MJX's ``rne_postconstraint``
    at every physics step, the contacts' forces for a touch), a shallow copy whose model leaves out
    every sensor nothing reads; where it has cameras, whether its step may leave their poses as they
    came. The search traces the env's step and, for the sensors, its reset: 0.9-2.5 s of a suite env's
    start on the 2-core CPU (docs/performance.md, "Cameras no one reads"). ``env`` is left as it is.
    ``searched_alone`` False: something the search cannot trace reads the states too (a user's surrogate
    reward, another env's step): nothing is left out."""
    shared = with_reset_traced_once(env)
    model = vars(env).get("_mjx_model") if hasattr(env, "__dict__") else None
    costly = bool(np.any(np.asarray(getattr(model, "sensor_needstage", ())) == mujoco.mjtStage.mjSTAGE_ACC))
    cameras = int(getattr(model, "ncam", 0) or 0) > 0
    if not (costly or cameras) or not searched_alone:
        return LeftOut(shared, 0, False)
    searched = env if costly else shared  # the reset's reads searched in its own trace; else its shapes alone
    # The key names the env, and so its model: whether its sensors are searched is not keyed apart.
    read = program_store.kept_answer(answer_key, "outputs read",
                                     lambda: outputs_read(searched, model, step_context, costly))
    held, sensors = cameras and read["camera poses"] is False, read["sensors"]
    if not costly or sensors is None or all(sensors):
        return LeftOut(shared, 0, held)
    copied = copy.copy(env)
    try:
        copied._mjx_model = model.replace(sensor_needstage=np.where(sensors, np.asarray(model.sensor_needstage), 0))
    except (AttributeError, TypeError):  # a frozen dataclass's FrozenInstanceError is an AttributeError
        return LeftOut(shared, 0, held)
    return LeftOut(with_reset_traced_once(copied), len(sensors) - sum(sensors), held)
