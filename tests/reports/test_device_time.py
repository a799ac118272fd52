"""A program's device time by the scope its ops were traced in (benchmarks/device_time.py): ops nested
in a loop's event counted once, the innermost MJX stage named, and the profiler's ops matched to the
compiled program's instructions."""
from __future__ import annotations

import importlib.util
import re

import jax
import jax.numpy as jnp
import mujoco

from stablebptt.physics.constraint_derivatives import differentiable_mjx
from stablebptt.physics.mjx_internals import mjx

from conftest import ROOT

_spec = importlib.util.spec_from_file_location("device_time", ROOT / "benchmarks" / "device_time.py")
device_time = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(device_time)


def test_an_op_nested_in_a_loops_event_counts_once():
    # A loop's event spans two ops of its body, then a separate op; a second loop holds a nested loop.
    events = [(0, 100, "while"), (10, 20, "add"), (40, 20, "mul"), (100, 10, "copy"),
              (200, 50, "outer"), (205, 40, "inner"), (210, 5, "sin")]
    times = dict(device_time._self_times(events))
    assert times == {"while": 60, "add": 20, "mul": 20, "copy": 10, "outer": 10, "inner": 35, "sin": 5}
    assert sum(times.values()) == 100 + 10 + 50  # the lines' busy time, each nanosecond once


def test_an_op_starting_with_its_loop_counts_inside_it():
    # The profiler's own order: by start, an enclosing event before an op that starts with it.
    events = [(0, 20, "add"), (0, 100, "while"), (40, 20, "mul")]
    times = dict(device_time._self_times(events))
    assert times == {"while": 60, "add": 20, "mul": 20}


def test_an_op_counts_in_the_innermost_mjx_stage_it_was_traced_in():
    assert device_time.stage_of("jit(update)/transpose(jvp(env_step))/step/forward/fwd_position/vmap()/add") \
        == "fwd_position"
    assert device_time.stage_of("jit(f)/step/forward/solve_implicitly/while/body/jit(_cholesky)/cholesky") \
        == "solve_implicitly"
    assert device_time.stage_of("jit(update)/jvp(env_step)/step/forward/solve/while/body/select_n") == "solve"
    assert device_time.stage_of("jit(update)/jvp(policy)/dot_general") == "other"


def test_an_op_counts_in_its_direction_and_an_op_xla_made_unnamed_in_neither():
    assert device_time.part_of("jit(update)/transpose(jvp(env_step))/step/forward/fwd_position/smooth.crb/add") \
        == ("reverse", "fwd_position/smooth.crb")
    assert device_time.part_of("jit(update)/jvp(policy)/dot_general") == ("forward", "other")
    assert device_time.part_of("") == ("unnamed", "")


def test_the_split_prints_each_part_once_its_share_and_ops_and_what_lies_outside_the_stages(
        monkeypatch, capsys):
    # Four ops of a profiled call, 10 ms in all: a reverse op of a stage's call (in a loop: 20 kernels), a
    # forward op of the policy (outside every stage), and two ops XLA made with no name stack (a copy twice,
    # under one kind).
    names = {"fusion.1": "jit(update)/transpose(jvp(env_step))/step/forward/fwd_position/smooth.crb/add",
             "fusion.2": "jit(update)/jvp(policy)/dot_general"}
    times = {"fusion.1": 0.005, "fusion.2": 0.002, "copy.3": 0.002, "copy.4": 0.001}
    kernels = {"fusion.1": 20.0, "fusion.2": 1.0, "copy.3": 1.0, "copy.4": 3.0}
    monkeypatch.setattr(device_time, "op_names", lambda compiled: names)
    monkeypatch.setattr(device_time, "op_profile", lambda compiled, inputs: (times, kernels))
    device_time.split(None, None, "update", top=4)
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "update: 10.0 ms of device time a call, over 4 ops launching 25 kernels"
    rows = {tuple(line.split()[:2]): line for line in lines[1:4]}
    assert rows["reverse", "fwd_position/smooth.crb"].split()[-7:] == ["5.0", "ms", "50.0%", "1", "ops", "20",
                                                                      "kernels"]
    assert rows["unnamed", "(no"].split()[-7:] == ["3.0", "ms", "30.0%", "2", "ops", "4", "kernels"]
    assert "(no name stack)" in rows["unnamed", "(no"]
    assert rows["forward", "other"].split()[-7:] == ["2.0", "ms", "20.0%", "1", "ops", "1", "kernels"]
    # Outside the stages: the unnamed copies by their kind, then the policy's op by its name stack.
    assert lines[4].split() == ["unnamed", "other:", "3.0", "ms", "copy"]
    assert lines[5].split() == ["forward", "other:", "2.0", "ms", "jvp(policy)/dot_general"]
    assert lines[6] == "  costliest name stacks:" and len(lines) == 7 + 3  # three names: the copies are one


def test_the_profilers_ops_are_the_compiled_programs_instructions():
    def spin(x):
        return jax.lax.scan(lambda carry, _: (jnp.sin(carry) @ carry, None), x, None, length=20)[0]
    x = jnp.eye(64) * 0.5
    compiled = jax.jit(spin).lower(x).compile()
    times, kernels = device_time.op_profile(compiled, (x,), calls=3)
    names = device_time.op_names(compiled)
    assert times and all(spent >= 0 for spent in times.values())
    assert sum(spent for op, spent in times.items() if op in names) > 0.5 * sum(times.values())
    # The loop body's ops (its sine and product) launch one kernel a call per iteration, the loop itself one (on
    # this CPU: a GPU's profiler may count its condition's every check), each a call's mean over the three.
    in_body = [op for op in kernels if "while/body/closed_call" in names.get(op, "")]
    assert in_body and all(kernels[op] == 20 for op in in_body)
    loops = [op for op in kernels if op.startswith("while")]
    assert loops and all(kernels[op] == 1 for op in loops)


def _ball_on_the_floor_lowered() -> str:
    """A step of a ball resting on the floor (solver rows), lowered through this library's patches, with the
    name stacks of its ops."""
    model = mujoco.MjModel.from_xml_string(
        '<mujoco><worldbody><geom type="plane" size="1 1 0.1"/><body pos="0 0 0.05"><freejoint/>'
        '<geom type="sphere" size="0.06"/></body></worldbody></mujoco>')
    mjx_model, data = mjx.put_model(model, impl="jax"), mjx.put_data(model, mujoco.MjData(model), impl="jax")
    with differentiable_mjx(implicit_solver=True):
        return jax.jit(lambda data: mjx.step(mjx_model, data)).lower(data).as_text(debug_info=True)


def test_the_solver_routed_by_this_library_keeps_its_stage_name():
    text = _ball_on_the_floor_lowered()
    scopes = set(re.findall(r"forward/(solve\w*)/", text))
    assert scopes == {"solve"} and all(scope in device_time.STAGES for scope in scopes)


def test_each_call_of_mjxs_stages_is_named_while_asked_and_only_then():
    from stablebptt.physics.mjx_internals import forward, smooth
    with device_time.calls_named():
        text = _ball_on_the_floor_lowered()
        with differentiable_mjx():
            assert forward.smooth.factor_m.__wrapped__ is smooth.factor_m  # wrapped, around the remedy in place then
    assert forward.smooth is smooth
    calls = {device_time.call_of(name) for name in re.findall(r'loc\("([^"]*)"', text)}
    assert {"smooth.kinematics", "smooth.crb", "smooth.factor_m", "collision_driver.collision",
            "constraint.make_constraint", "smooth.rne"} <= calls
    assert device_time.call_of("jit(f)/step/forward/fwd_position/collision_driver.collision/smooth.x/add") \
        == "collision_driver.collision"  # the outermost call within the stage
    assert device_time.call_of("jit(f)/step/forward/fwd_position/vmap()/add") == ""
