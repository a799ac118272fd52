"""Sensors as MuJoCo's C computes them: the acceleration stage's of a model without constraint rows, and RK4's.

Where a model can have no constraint rows (constraints disabled, or no contact, joint limit,
equality or friction loss possible), MJX's forward pass returns before its acceleration-stage
sensors: an accelerometer, a force or torque sensor, a frame's linear or angular acceleration, an
actuator's force stay at zero where MuJoCo's C computes them. Code traced inside
``sensors_as_c_computes`` runs MJX's own ``sensor_acc`` after that forward pass. Touch and
contact sensors are left out of it: with no rows there is no contact, their value is C's zero, and
MJX's function has no contact to read them from.

Inside it too, a step under RK4 keeps the sensors of the state it began from, as C's does: C computes
no sensors in RK4's stages, where MJX's step returns those of its last stage (a state neither the
step's start nor its end). Its other outputs stay MJX's: ``qacc``, ``cacc`` and ``cfrc_ext`` are its
last stage's, where C's ``qacc`` is the acceleration RK4 applied and its ``cacc`` and ``cfrc_ext`` the
start's.
"""
from __future__ import annotations

import contextlib
import functools

import mujoco
import numpy as np

from stablebptt.physics.mjx_internals import mjx, sensor
from stablebptt.physics.mjx_internals import forward as mjx_forward
from stablebptt.physics.mjx_patches import applied, choosing, tracing

_CONTACTS_READ = (mujoco.mjtSensor.mjSENS_TOUCH, mujoco.mjtSensor.mjSENS_CONTACT)


def _with_acceleration_sensors(forward):
    """MJX's forward pass, then, where this thread's trace asks, its acceleration-stage sensors where the model
    has such sensors and no constraint rows."""
    @functools.wraps(forward)
    def forward_with_acceleration_sensors(model, data):
        data = forward(model, data)
        rows = getattr(data._impl, "efc_J", None)  # None: MJX's Warp backend, which computes its own
        if not tracing.c_sensors or rows is None or rows.size:
            return data
        stages = np.asarray(model.sensor_needstage)
        computed = np.where(np.isin(np.asarray(model.sensor_type), _CONTACTS_READ), 0, stages)
        if not np.any(computed == mujoco.mjtStage.mjSTAGE_ACC):
            return data
        return sensor.sensor_acc(model.replace(sensor_needstage=computed), data)
    return forward_with_acceleration_sensors


def _with_start_sensors(rungekutta4):
    """MJX's RK4 integrator, where this thread's trace asks, with the sensors of the data it was given: the
    step's forward pass computed them at the state the step began from."""
    @functools.wraps(rungekutta4)
    def rungekutta4_with_start_sensors(model, data):
        stepped = rungekutta4(model, data)
        return stepped.replace(sensordata=data.sensordata) if tracing.c_sensors else stepped
    return rungekutta4_with_start_sensors


@contextlib.contextmanager
def sensors_as_c_computes():
    """MJX code traced within, in this thread, computes the acceleration stage's sensors also where the model
    has no constraint rows, and under RK4 keeps the sensors of the state a step began from, as MuJoCo's C
    does. Every other value is MJX's own. Reentrant; undone on exit."""
    with applied("sensors as C computes them", lambda: (
            (mjx_forward, "forward", _with_acceleration_sensors(mjx_forward.forward)),
            (mjx, "forward", _with_acceleration_sensors(mjx.forward)),
            (mjx_forward, "rungekutta4", _with_start_sensors(mjx_forward.rungekutta4)),
            (mjx, "rungekutta4", _with_start_sensors(mjx.rungekutta4)))), \
            choosing("c_sensors"):
        yield
