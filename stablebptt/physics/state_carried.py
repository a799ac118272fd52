"""Physics steps whose loop carries MuJoCo's integration state alone (``steps``).

Of the data it is given, ``mjx.step`` reads only what MuJoCo integrates and takes as input (its
``mjSTATE_INTEGRATION``: time, positions, velocities, activations, their history, the controls, the
applied forces, the mocap poses, the active equalities, the user data, the plugins' state, and the
solver's warm start): every other field it computes again or passes on as it was. A loop of steps over
the whole data carries every computed field from one step to the next, and in reverse mode its
cotangent, though the next step reads none of them. ``steps`` carries the state alone and takes the
last step after the loop, so the data it returns holds that step's computed fields as the whole data's
loop does: the same physics, its values the same to rounding (tests/physics/test_state_carried.py), in
a program that holds the step twice. On one H100 FishSwim's update took 13.6% less time and its forward
window 16.5% less, and its update compiled 6.2 s longer (docs/performance.md, "The fish's update on the
GPU"). Training takes it with ``--physics-step-carry state`` (``env_task(physics_steps_carrying_state=True)``).
"""
from __future__ import annotations

import jax

from stablebptt.physics.mjx_internals import mjx

READ_BY_STEP = ("time", "qpos", "qvel", "act", "history", "qacc_warmstart", "plugin_state", "ctrl", "qfrc_applied",
                "xfrc_applied", "eq_active", "mocap_pos", "mocap_quat", "userdata")


def steps(model: mjx.Model, data: mjx.Data, count: int) -> mjx.Data:
    """``count`` calls of ``mjx.step`` from ``data``, the loop carrying ``READ_BY_STEP`` alone. ``mjx.step`` is
    looked up at each call, so a patch of it (``differentiable_mjx``'s) is the step taken."""
    if count > 1:
        def physics_step(state: dict, _) -> tuple[dict, None]:
            reached = mjx.step(model, data.replace(**state))
            return {name: getattr(reached, name) for name in READ_BY_STEP}, None
        carried = jax.lax.scan(physics_step, {name: getattr(data, name) for name in READ_BY_STEP}, (), count - 1)[0]
        data = data.replace(**carried)
    return mjx.step(model, data) if count > 0 else data
