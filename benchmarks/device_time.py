"""Where one call of a compiled program spends its time on the device, by the JAX scope of each XLA op:
the profiler's op events (``jax.profiler.trace``) matched to the compiled HLO's instructions, whose
metadata carries the name stack JAX traced them under. MJX names the stages of its step
(``fwd_position``: kinematics, collision and the constraint rows; ``fwd_velocity``; ``fwd_actuation``;
``fwd_acceleration``; ``solve``: the constraint solver; the integrator), and reverse mode's ops sit under
``transpose(...)``. XLA fuses ops of different scopes into one kernel: a fusion counts where its root
op was traced, so the split is as fine as the fusions.

Used by ``benchmarks/update_program.py --profile``.
"""
from __future__ import annotations

import collections
import contextlib
import functools
import glob
import os
import re
import shutil
import tempfile

import jax

# The solver's scope is named by the function MJX's forward pass calls, ``solve`` (the patch that routes it in
# stablebptt's traces carries its name, physics/constraint_derivatives.py).
STAGES = ("fwd_position", "fwd_velocity", "fwd_actuation", "fwd_acceleration", "solve", "solve_implicitly", "euler",
          "implicit", "rungekutta4")
# The modules MJX's forward pass calls into within its stages; ``calls_named`` gives each call a scope.
NAMED_MODULES = ("smooth", "collision_driver", "constraint", "passive", "sensor", "derivative")
_CALL = re.compile(r"^(?:%s)\.\w+$" % "|".join(NAMED_MODULES))
_INSTRUCTION = re.compile(r"^\s*(?:ROOT\s+)?%?([\w.\-]+)\s*=.*?metadata=\{[^}]*op_name=\"([^\"]*)\"")


def op_names(compiled) -> dict[str, str]:
    """Each instruction of ``compiled``'s optimised HLO that carries a name stack, by its name."""
    found = {}
    for line in compiled.as_text().splitlines():
        matched = _INSTRUCTION.match(line)
        if matched:
            found[matched.group(1)] = matched.group(2)
    return found


def stage_of(op_name: str) -> str:
    """The MJX stage whose scope ``op_name`` lies in (the innermost named), else ``other``."""
    parts = re.split(r"[/()]", op_name)
    for part in reversed(parts):
        if part in STAGES:
            return part
    return "other"


def part_of(op_name: str) -> tuple[str, str]:
    """(direction, MJX stage and the call within it) of an op traced as ``op_name``: direction ``reverse``
    under a transpose, else ``forward``. An op XLA made with no name stack (a loop's copies, a scatter
    expanded into a loop, a layout change) is ``("unnamed", "")``: nothing says which pass it serves."""
    if not op_name:
        return "unnamed", ""
    direction = "reverse" if "transpose(" in op_name else "forward"
    return direction, "/".join(filter(None, (stage_of(op_name), call_of(op_name))))


def call_of(op_name: str) -> str:
    """The outermost call ``calls_named`` scoped within the MJX stage of ``op_name`` (``smooth.crb``,
    ``collision_driver.collision``, ...), else ""."""
    found = ""
    for part in reversed(re.split(r"[/()]", op_name)):
        if part in STAGES:
            break
        if _CALL.match(part):
            found = part
    return found


class _Named:
    """One of MJX's modules as its forward pass sees it: each function called in a JAX scope of its name,
    looked up at each call (a patch applied to the module since is the one called)."""

    def __init__(self, module, label: str):
        self._module, self._label = module, label

    def __getattr__(self, name: str):
        found = getattr(self._module, name)
        if not callable(found) or isinstance(found, type):
            return found

        @functools.wraps(found)
        def named(*args, **kwargs):
            with jax.named_scope(f"{self._label}.{name}"):
                return found(*args, **kwargs)
        return named


@contextlib.contextmanager
def calls_named():
    """MJX code traced within has every call of its forward pass into NAMED_MODULES in a scope of its own
    (``smooth.kinematics``, ``collision_driver.collision``, ...): ``split`` then divides each stage by call.
    The scopes name ops, nothing else; undone on exit."""
    from stablebptt.physics.mjx_internals import forward
    before = {label: getattr(forward, label) for label in NAMED_MODULES}
    for label, module in before.items():
        setattr(forward, label, _Named(module, label))
    try:
        yield
    finally:
        for label, module in before.items():
            setattr(forward, label, module)


def op_profile(compiled, inputs, calls: int = 1) -> tuple[dict[str, float], dict[str, float]]:
    """Device seconds and kernels per HLO instruction, each per call, over ``calls`` calls of ``compiled`` under
    the profiler: the profiler's events of each op, a fusion's one per execution (so an op in a loop's body
    counts once per iteration), a library call's (a Cholesky factor, a triangular solve) one per kernel it
    launches, often several."""
    from jax._src.lib import _profile_data  # the profiler's reader of its own trace, shipped with jaxlib
    with tempfile.TemporaryDirectory() as folder:
        with jax.profiler.trace(folder):
            for _ in range(calls):
                jax.block_until_ready(compiled(*inputs))
        paths = glob.glob(f"{folder}/**/*.xplane.pb", recursive=True)
        data = _profile_data.ProfileData.from_file(paths[-1])
        if os.environ.get("DEVICE_TIME_TRACES"):  # a folder to keep the trace in, for a closer look
            os.makedirs(os.environ["DEVICE_TIME_TRACES"], exist_ok=True)
            shutil.copy(paths[-1], os.path.join(os.environ["DEVICE_TIME_TRACES"], f"{len(os.listdir(os.environ['DEVICE_TIME_TRACES']))}.xplane.pb"))
    seconds: collections.Counter = collections.Counter()
    kernels: collections.Counter = collections.Counter()
    device_planes = [plane for plane in data.planes if plane.name.startswith("/device:")]
    for plane in device_planes or [plane for plane in data.planes if plane.name == "/host:CPU"]:
        lines = list(plane.lines)
        derived = [line for line in lines if line.name == "XLA Ops"]  # where the profiler derived it, its ops once
        for line in derived or lines:
            ops = [(event.start_ns, event.duration_ns, str(dict(event.stats)["hlo_op"]))
                   for event in line.events if "hlo_op" in dict(event.stats)]
            for op, spent in _self_times(ops):
                seconds[op] += spent * 1e-9 / calls
                kernels[op] += 1
    return dict(seconds), {op: count / calls for op, count in kernels.items()}


def _self_times(ops):
    """(op, time less the ops nested in it) for ``ops`` as (start, duration, op) on one line of the trace: a
    loop's event spans its body's ops, which count on their own."""
    # By start, the longer first where two start together: an enclosing event before what it holds.
    ops = sorted(ops, key=lambda op: (op[0], -op[1]))
    open_ops: list[list] = []  # [end, op, self time] of the ops enclosing the current one
    for start, duration, op in ops:
        while open_ops and open_ops[-1][0] <= start:
            _, done, spent = open_ops.pop()
            yield done, spent
        if open_ops:
            open_ops[-1][2] -= duration
        open_ops.append([start + duration, op, duration])
    for _, done, spent in reversed(open_ops):
        yield done, spent


def split(compiled, inputs, label: str, top: int = 12) -> None:
    """Prints ``compiled``'s device time per call by direction (forward, reverse) and MJX stage (and the
    call within it, where the program was traced inside ``calls_named``) with the distinct ops each ran (HLO
    instructions: a loop body's counted once) and the kernels they launched a call (``op_profile``), the
    largest name stacks of its parts outside every stage, then its ``top`` costliest name stacks."""
    names = op_names(compiled)
    times, kernels = op_profile(compiled, inputs)
    total = sum(times.values())
    by_part: collections.Counter = collections.Counter()
    ops_in: collections.Counter = collections.Counter()  # distinct ops (a loop body's once, however often it runs)
    kernels_in: collections.Counter = collections.Counter()
    by_name: collections.Counter = collections.Counter()
    in_other: collections.Counter = collections.Counter()
    for op, spent in times.items():
        name = names.get(op, "")
        part = part_of(name)
        by_part[part] += spent
        ops_in[part] += 1
        kernels_in[part] += kernels[op]
        named = re.sub(r"\d+", "#", name.split("/", 1)[-1])[-160:] or re.sub(r"\.\d+$", "", op)
        by_name[named] += spent
        if part[1] in ("other", ""):
            in_other[(part[0], named)] += spent
    print(f"{label}: {total * 1e3:.1f} ms of device time a call, over {len(times)} ops launching "
          f"{sum(kernels.values()):.0f} kernels", flush=True)
    buffered = sum(spent for op, spent in times.items() if op.startswith("command_buffer"))
    if buffered > 0.1 * total:  # a CUDA graph's time has no op of its own: it counts as "unnamed" below
        print(f"  {buffered * 1e3:.1f} ms ({buffered / total:.0%}) ran in CUDA command buffers, not split by op "
              f"(XLA_FLAGS=--xla_gpu_enable_command_buffer= runs the ops one by one)", flush=True)
    for (direction, stage), spent in by_part.most_common():
        print(f"  {direction:8s} {stage or '(no name stack)':40s} {spent * 1e3:8.1f} ms  {spent / total:6.1%}"
              f"  {ops_in[direction, stage]:6d} ops  {kernels_in[direction, stage]:9.0f} kernels", flush=True)
    # "other" gathers what no MJX stage holds (policy, critic, observation, reward): its largest parts by name,
    # and XLA's unnamed ops by kind. A call of MJX's named outside its stages (other/sensor.sensor_vel) has its
    # own row above.
    for (direction, name), spent in in_other.most_common(top // 2):
        print(f"  {direction:8s} other: {spent * 1e3:8.1f} ms  {name[-120:]}", flush=True)
    print("  costliest name stacks:", flush=True)
    for name, spent in by_name.most_common(top):
        print(f"  {spent * 1e3:8.1f} ms  {name}", flush=True)
