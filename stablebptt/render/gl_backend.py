"""Headless OpenGL for MuJoCo: which backend renders here, chosen before MuJoCo loads.

    select_gl_backend()          # first: before anything imports mujoco

MuJoCo picks its OpenGL backend from ``MUJOCO_GL`` once, when it is first
imported, so nothing here imports mujoco: ``select_gl_backend`` tries EGL and
then OSMesa in short subprocesses and sets ``MUJOCO_GL`` to the first that
renders, or says which system package to install.
"""
from __future__ import annotations

import contextlib
import ctypes.util
import os
import subprocess
import sys
import warnings
from typing import Callable, Sequence

from stablebptt.errors import InputError

BACKENDS = ("egl", "osmesa")  # headless, in order of preference: EGL is the faster of the two
# Debian packages that make each backend work (Mesa's software renderers are enough; no GPU needed).
INSTALL = {
    "egl": "apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri libopengl0",
    "osmesa": "apt-get install libosmesa6",
}
# The shared libraries each backend loads first: when one is missing, say so rather than show a traceback's last line.
LIBRARIES = {"egl": ("EGL", "OpenGL"), "osmesa": ("OSMesa",)}
PROBE_TIMEOUT = 60.0

# Rendered in the probe subprocess: a lit red sphere must not come out blank.
_PROBE = """
import mujoco
model = mujoco.MjModel.from_xml_string(
    '<mujoco><worldbody><light pos="0 0 3"/><geom size=".5" rgba="1 0 0 1"/></worldbody></mujoco>')
data = mujoco.MjData(model)
mujoco.mj_forward(model, data)
with mujoco.Renderer(model, 32, 32) as renderer:
    renderer.update_scene(data)
    pixels = renderer.render()
assert pixels.std() > 0, "it rendered a blank image"
"""


@contextlib.contextmanager
def child_processes():
    """Silence JAX's warning about fork in a threaded process: the children here exec at once (ffmpeg, a probe)."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called", category=RuntimeWarning)
        yield


class NoHeadlessGL(InputError):
    """No OpenGL backend renders here; the message names the system package to install."""


def probe_gl_backend(backend: str, timeout: float = PROBE_TIMEOUT) -> str | None:
    """Try MuJoCo's offscreen renderer with ``MUJOCO_GL=backend`` in a fresh Python process.

    Args:
      backend: ``"egl"``, ``"osmesa"`` or ``"glfw"``.
      timeout: seconds before the attempt counts as failed.

    Returns:
      None when a frame was rendered, else a short reason (the last line the attempt printed).
    """
    env = dict(os.environ, MUJOCO_GL=backend)
    if backend in BACKENDS:
        env["PYOPENGL_PLATFORM"] = backend  # PyOpenGL must load the same platform library as MuJoCo
    try:
        with child_processes():
            result = subprocess.run([sys.executable, "-c", _PROBE], env=env, capture_output=True, text=True,
                                    timeout=timeout)
    except subprocess.TimeoutExpired:
        return f"no frame within {timeout:g} s"
    if result.returncode == 0:
        return None
    missing = [f"lib{name}" for name in LIBRARIES.get(backend, ()) if ctypes.util.find_library(name) is None]
    if missing:
        return f"{' and '.join(missing)} not found"
    lines = [line.strip() for line in result.stderr.splitlines() if line.strip()]
    reason = lines[-1] if lines else f"exit code {result.returncode}"
    return reason if len(reason) <= 80 else reason[:77] + "..."


def select_gl_backend(backends: Sequence[str] = BACKENDS,
                      probe: Callable[[str], str | None] = probe_gl_backend) -> str:
    """Find a headless OpenGL backend that renders and set ``MUJOCO_GL`` to it.

    Call it before anything imports mujoco, which reads ``MUJOCO_GL`` once. A
    ``MUJOCO_GL`` already set by the user is the only backend tried.

    Args:
      backends: backends to try, in order.
      probe: ``probe(backend) -> None or reason``; ``probe_gl_backend`` by default.

    Returns:
      The backend now in ``MUJOCO_GL``.

    Raises:
      NoHeadlessGL: no backend renders; the message says which package to install.
      RuntimeError: mujoco was imported before, with no backend chosen.
    """
    requested = os.environ.get("MUJOCO_GL", "").strip().lower()
    if not requested and "mujoco" in sys.modules:
        raise RuntimeError("mujoco was imported before select_gl_backend() chose MUJOCO_GL: call it first")
    candidates = (requested,) if requested else tuple(backends)
    reasons = {}
    for backend in candidates:
        reason = probe(backend)
        if reason is None:
            os.environ["MUJOCO_GL"] = backend
            if backend in BACKENDS:
                os.environ["PYOPENGL_PLATFORM"] = backend
            return backend
        reasons[backend] = reason
    if requested:
        fix = INSTALL.get(requested, f"unset MUJOCO_GL to try {' and '.join(BACKENDS)}")
        raise NoHeadlessGL(f"MUJOCO_GL={requested} cannot render here ({reasons[requested]}): {fix}")
    tried = "; ".join(f"{backend.upper()}: {reason}" for backend, reason in reasons.items())
    install = " or ".join(f"'{INSTALL[backend]}'" for backend in candidates if backend in INSTALL)
    raise NoHeadlessGL(f"no headless OpenGL for MuJoCo ({tried}): install it with {install}")

