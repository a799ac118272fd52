"""Headless rendering of rollouts: the OpenGL backend, MuJoCo frames framed on a rollout, frame strips, videos.

    select_gl_backend()                    # first: before anything imports mujoco
    model = render_model("models/cartpole_1.xml")
    camera = frame_camera(model, *rollout_extent(model, qpos), 320, 240)   # qpos: [T, nq]
    frames, _ = render_frames(model, qpos, camera, 320, 240)
    write_video("rollout.mp4", frames, fps=30)
    picks = strip_indices(len(qpos), 8)
    frames, masks = render_frames(model, qpos[picks], camera, 320, 240, supersample=2, with_masks=True)
    write_png("strip.png", frame_strip(frames, masks))

MuJoCo picks its OpenGL backend from ``MUJOCO_GL`` once, when it is first
imported, so nothing here imports mujoco at import time: ``select_gl_backend``
tries EGL and then OSMesa in short subprocesses and sets ``MUJOCO_GL`` to the
first that renders. The other functions import mujoco when called.
"""
from __future__ import annotations

import contextlib
import ctypes.util
import os
import subprocess
import sys
import warnings
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from stablebptt.errors import InputError
from stablebptt.storage import atomic_write

BACKENDS = ("egl", "osmesa")  # headless, in order of preference: EGL is the faster of the two
# Debian packages that make each backend work (Mesa's software renderers are enough; no GPU needed).
INSTALL = {
    "egl": "apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri libopengl0",
    "osmesa": "apt-get install libosmesa6",
}
# The shared libraries each backend loads first: when one is missing, say so rather than show a traceback's last line.
LIBRARIES = {"egl": ("EGL", "OpenGL"), "osmesa": ("OSMesa",)}
PROBE_TIMEOUT = 60.0
VIDEO_FORMATS = (".mp4", ".gif")
BACKGROUND = (1.0, 1.0, 1.0)  # plain white behind models without a skybox of their own: print-friendly
AZIMUTH = 90.0  # look along +y: a planar system moving in the x-z plane (the MJCF convention) faces the camera
ELEVATION = -15.0  # slightly from above, so depth still reads
SUPERSAMPLE = 2  # render at 2x and average: smooth edges in the masks that frame strips blend with

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
def _child_processes():
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
        with _child_processes():
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


def _brighten_headlight(headlight) -> None:
    if np.allclose(headlight.ambient, 0.1) and np.allclose(headlight.diffuse, 0.4):
        # MuJoCo's defaults, made for a dark background, leave colours murky on white.
        headlight.ambient, headlight.diffuse = [0.35] * 3, [0.55] * 3


def render_model(path: str | Path, framebuffer: tuple[int, int] = (640, 480), background: Sequence[float] = BACKGROUND):
    """The MJCF at ``path`` compiled for rendering: a plain backdrop and a large enough offscreen buffer.

    The dynamics are untouched (same qpos layout): a flat skybox is added when
    the model has none, MuJoCo's dim default headlight is brightened, and the
    offscreen framebuffer is enlarged to ``framebuffer`` when it is smaller.

    Args:
      path: the MJCF file, or a compiled ``.mjb`` or ``.mjb.gz`` (a run's copy; drawn without the backdrop).
      framebuffer: (width, height) of the largest render, supersampling included.
      background: RGB in [0, 1] of the backdrop.

    Returns:
      A ``mujoco.MjModel``.
    """
    import mujoco

    path = Path(path)
    if not path.is_file():
        raise InputError(f"model file {path} does not exist")
    if path.suffix in (".mjb", ".gz"):  # a run's compiled copy: no skybox can be added, the rest applies
        from stablebptt.runs import load_compiled_model
        model = load_compiled_model(path)
        _brighten_headlight(model.vis.headlight)
        model.vis.global_.offwidth = max(model.vis.global_.offwidth, int(framebuffer[0]))
        model.vis.global_.offheight = max(model.vis.global_.offheight, int(framebuffer[1]))
        return model
    try:
        spec = mujoco.MjSpec.from_file(str(path))
    except ValueError as error:
        raise InputError(f"cannot load {path}: {' '.join(str(error).split())}") from None
    if not any(texture.type == mujoco.mjtTexture.mjTEXTURE_SKYBOX for texture in spec.textures):
        spec.add_texture(name="stablebptt_backdrop", type=mujoco.mjtTexture.mjTEXTURE_SKYBOX,
                         builtin=mujoco.mjtBuiltin.mjBUILTIN_FLAT, rgb1=list(background), rgb2=list(background),
                         width=8, height=8)
    _brighten_headlight(spec.visual.headlight)
    visual = spec.visual.global_
    visual.offwidth = max(visual.offwidth, int(framebuffer[0]))
    visual.offheight = max(visual.offheight, int(framebuffer[1]))
    try:
        return spec.compile()
    except ValueError as error:
        raise InputError(f"cannot load {path}: {' '.join(str(error).split())}") from None


def _moving_geoms(model) -> np.ndarray:
    """Indices of the geoms on bodies that can move (not welded to the world)."""
    return np.flatnonzero(model.body_weldid[model.geom_bodyid] != 0)


def rollout_extent(model, qpos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned box holding every moving geom over a whole rollout.

    Static geoms (a rail, a floor) are left out: they would make the box as
    large as the world. Each geom counts with its bounding box, so a pole's
    tip is inside, not only its body's origin.

    Args:
      model: the ``mujoco.MjModel``.
      qpos: positions over the rollout, shape [T, nq].

    Returns:
      ``(low, high)``, each of shape [3].
    """
    import mujoco

    data = mujoco.MjData(model)
    geoms = _moving_geoms(model)
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=float)
    # Corners of each geom's box in its own frame: [G, 8, 3].
    local = model.geom_aabb[geoms, None, :3] + signs[None] * model.geom_aabb[geoms, None, 3:]
    moving_bodies = np.flatnonzero(model.body_weldid != 0)
    points = []
    for q in np.asarray(qpos, dtype=float).reshape(-1, model.nq):
        data.qpos[:] = q
        mujoco.mj_kinematics(model, data)
        rotation = data.geom_xmat[geoms].reshape(-1, 3, 3)
        points.append(data.geom_xpos[geoms, None, :] + np.einsum("gij,gkj->gki", rotation, local))
        points.append(data.xpos[moving_bodies][:, None, :])  # bodies without geoms still count
    cloud = np.concatenate([p.reshape(-1, 3) for p in points]) if points else np.zeros((0, 3))
    if len(cloud) == 0:  # nothing moves: frame the whole model
        return model.stat.center - model.stat.extent / 2, model.stat.center + model.stat.extent / 2
    return cloud.min(axis=0), cloud.max(axis=0)


def frame_camera(model, low: np.ndarray, high: np.ndarray, width: int, height: int,
                 azimuth: float = AZIMUTH, elevation: float = ELEVATION, padding: float = 0.06):
    """A free camera aimed at the centre of a box, as close as it can be with the whole box in view.

    Args:
      model: the ``mujoco.MjModel`` (its vertical field of view is used).
      low, high: opposite corners of the box to show.
      width, height: frame size in pixels (the horizontal field of view follows from it).
      azimuth, elevation: camera direction in degrees, MuJoCo's convention.
      padding: margin around the box, as a fraction of its largest side.

    Returns:
      A ``mujoco.MjvCamera``.
    """
    import mujoco

    low, high = np.asarray(low, dtype=float), np.asarray(high, dtype=float)
    centre = (low + high) / 2
    # Pad by a share of the largest side; a point-like box still gets a visible size.
    half = (high - low) / 2 + padding * max(float(np.max(high - low)), 1e-3) + 1e-3
    a, e = np.radians(azimuth), np.radians(elevation)
    forward = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])  # as mjv_updateCamera
    up = np.array([-np.sin(e) * np.cos(a), -np.sin(e) * np.sin(a), np.cos(e)])
    right = np.cross(forward, up)
    corners = half * np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    tan_y = np.tan(np.radians(model.vis.global_.fovy) / 2)
    tan_x = tan_y * width / height
    # A corner at depth (distance + its offset along forward) must satisfy |x| <= depth tan_x and |y| <= depth tan_y.
    depth = corners @ forward
    distance = max(np.max(np.abs(corners @ right) / tan_x - depth), np.max(np.abs(corners @ up) / tan_y - depth))
    # Keep the nearest corner beyond the near clipping plane, or a deep box would be cut open.
    distance = max(distance, np.max(-depth) + 1.01 * model.vis.map.znear * model.stat.extent)
    camera = mujoco.MjvCamera()
    camera.type = mujoco.mjtCamera.mjCAMERA_FREE
    camera.lookat[:] = centre
    camera.distance = float(distance)
    camera.azimuth = azimuth
    camera.elevation = elevation
    return camera


def _downsample(image: np.ndarray, factor: int) -> np.ndarray:
    if factor == 1:
        return image.astype(np.float32)
    h, w = image.shape[0] // factor, image.shape[1] // factor
    return image.reshape(h, factor, w, factor, *image.shape[2:]).mean(axis=(1, 3), dtype=np.float32)


def render_frames(model, qpos: np.ndarray, camera, width: int, height: int, supersample: int = 1,
                  with_masks: bool = False) -> tuple[np.ndarray, np.ndarray | None]:
    """Render states headless; optionally also where the moving bodies cover each frame.

    Args:
      model: a ``mujoco.MjModel``, e.g. from ``render_model`` (its framebuffer must fit the size).
      qpos: positions to draw, shape [T, nq].
      camera: a ``mujoco.MjvCamera``, e.g. from ``frame_camera``.
      width, height: frame size in pixels.
      supersample: render at this multiple of the size and average down (MuJoCo's
        multisampling already smooths colour edges; this also smooths the masks).
      with_masks: also return the masks (one more render per frame).

    Returns:
      ``(frames, masks)``: uint8 [T, height, width, 3], and float32 [T, height, width]
      in [0, 1], the share of each pixel covered by bodies not welded to the world
      (None without ``with_masks``).
    """
    import mujoco

    data = mujoco.MjData(model)
    moving = np.zeros(model.ngeom + 1, dtype=bool)  # index -1 (no geom) lands on the extra last entry
    moving[_moving_geoms(model)] = True
    qpos = np.asarray(qpos, dtype=float).reshape(-1, model.nq)
    frames = np.empty((len(qpos), height, width, 3), dtype=np.uint8)
    masks = np.empty((len(qpos), height, width), dtype=np.float32) if with_masks else None
    with mujoco.Renderer(model, supersample * height, supersample * width) as renderer:
        for t, q in enumerate(qpos):
            data.qpos[:] = q
            mujoco.mj_forward(model, data)
            renderer.update_scene(data, camera)
            renderer.disable_segmentation_rendering()
            frames[t] = np.round(_downsample(renderer.render(), supersample)).astype(np.uint8)
            if with_masks:
                renderer.enable_segmentation_rendering()
                segments = renderer.render()
                geom = np.where(segments[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM), segments[..., 0], -1)
                masks[t] = _downsample(moving[geom].astype(np.float32), supersample)
    return frames, masks


def strip_indices(total: int, count: int) -> np.ndarray:
    """``count`` indices evenly spaced from 0 to ``total - 1``, both ends included."""
    return np.unique(np.round(np.linspace(0, total - 1, max(1, min(count, total)))).astype(int))


def frame_strip(frames: np.ndarray, masks: np.ndarray, min_alpha: float = 0.15, gamma: float = 1.5,
                margin: float | None = 0.05) -> np.ndarray:
    """Overlay states of a rollout on one image, earlier ones more transparent (the paper's Figure 4a).

    The last frame is the base (its static scenery included); the states are
    blended in where their moving bodies are, oldest first, with opacity rising
    from ``min_alpha`` to 1, so the final state ends on top, fully opaque.

    Args:
      frames: uint8 [K, H, W, 3], the states to show in time order, from one fixed camera
        (e.g. ``render_frames`` of ``qpos[strip_indices(T, 8)]``).
      masks: float [K, H, W] in [0, 1], where the moving bodies are.
      min_alpha: opacity of the first state.
      gamma: above 1 keeps early states faint for longer.
      margin: crop to the moving bodies plus this share of the image's larger side
        on every side (a tight figure for a paper); None keeps the whole frame.

    Returns:
      uint8 [h, w, 3], at most [H, W, 3].
    """
    if len(frames) == 0:
        raise ValueError("no frames to overlay")
    image = frames[-1].astype(np.float32)
    for rank, (frame, mask) in enumerate(zip(frames, masks)):
        progress = rank / max(len(frames) - 1, 1)
        alpha = min_alpha + (1.0 - min_alpha) * progress**gamma
        coverage = (alpha * mask)[..., None]
        image = (1.0 - coverage) * image + coverage * frame
    image = np.clip(np.round(image), 0, 255).astype(np.uint8)
    return image if margin is None else crop(image, np.max(masks, axis=0) > 0.02, margin)


def crop(image: np.ndarray, keep: np.ndarray, margin: float = 0.05) -> np.ndarray:
    """``image`` [H, W, ...] cut to the bounding box of ``keep`` [H, W] plus a margin (a share of max(H, W))."""
    rows, columns = np.flatnonzero(keep.any(axis=1)), np.flatnonzero(keep.any(axis=0))
    if len(rows) == 0:
        return image
    pad = int(round(margin * max(image.shape[:2])))
    top, bottom = max(rows[0] - pad, 0), min(rows[-1] + 1 + pad, image.shape[0])
    left, right = max(columns[0] - pad, 0), min(columns[-1] + 1 + pad, image.shape[1])
    return image[top:bottom, left:right]


def figure_pixels(figure) -> np.ndarray:
    """The RGB pixels of a matplotlib figure on an Agg canvas, uint8 [H, W, 3] (one animation frame)."""
    figure.canvas.draw()
    return np.array(figure.canvas.buffer_rgba())[..., :3]


def tile(images: Sequence[np.ndarray], columns: int | None = None, gap: int = 2,
         colour: Sequence[int] = (200, 200, 200)) -> np.ndarray:
    """Images of one size side by side (``columns`` per row), separated by ``gap`` pixels.

    Works on single images [H, W, 3] and on frame stacks [T, H, W, 3] alike.
    """
    images = [np.asarray(image) for image in images]
    columns = columns or len(images)
    rows = -(-len(images) // columns)
    *lead, h, w, c = images[0].shape
    canvas = np.empty((*lead, rows * h + (rows - 1) * gap, columns * w + (columns - 1) * gap, c), dtype=images[0].dtype)
    canvas[...] = np.asarray(colour, dtype=images[0].dtype)
    for index, image in enumerate(images):
        r, col = divmod(index, columns)
        canvas[..., r * (h + gap):r * (h + gap) + h, col * (w + gap):col * (w + gap) + w, :] = image
    return canvas


def _even(frames: np.ndarray) -> np.ndarray:
    """Pad to even height and width with the edge colour: H.264 in yuv420p needs both even."""
    pad_h, pad_w = frames.shape[1] % 2, frames.shape[2] % 2
    if not (pad_h or pad_w):
        return frames
    return np.pad(frames, ((0, 0), (0, pad_h), (0, pad_w), (0, 0)), mode="edge")


def write_png(path: str | Path, image: np.ndarray) -> Path:
    """Write an RGB(A) uint8 image as PNG, atomically."""
    import imageio.v3 as iio

    path = Path(path)
    atomic_write(path, iio.imwrite("<bytes>", np.asarray(image, dtype=np.uint8), extension=".png"))
    return path


def write_video(path: str | Path, frames: np.ndarray, fps: float = 30.0) -> Path:
    """Write frames [T, H, W, 3] uint8 as an MP4 (H.264) or a GIF, chosen by the suffix, atomically.

    The video is written to a temporary file next to ``path`` and renamed, so a
    reader never sees half a video and an interrupted run leaves no broken file.

    Args:
      path: ``*.mp4`` or ``*.gif``.
      frames: the frames, all of one size.
      fps: frames per second.

    Returns:
      ``path``.
    """
    import imageio.v2 as imageio
    import imageio.v3 as iio

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in VIDEO_FORMATS:
        raise InputError(f"{path}: a video must end in {' or '.join(VIDEO_FORMATS)}")
    frames = np.asarray(frames, dtype=np.uint8)
    if suffix == ".gif":
        # GIF delays count in hundredths of a second; loop forever.
        data = iio.imwrite("<bytes>", frames, extension=".gif", duration=round(1000 / fps, -1), loop=0)
        atomic_write(path, data)
        return path
    # ffmpeg picks the container from the name, so the temporary file keeps the suffix.
    temporary = path.with_name(f".{path.stem}.{os.getpid()}.tmp{suffix}")
    try:
        writer = imageio.get_writer(temporary, format="FFMPEG", mode="I", fps=fps, codec="libx264", quality=8,
                                    pixelformat="yuv420p", macro_block_size=2, ffmpeg_log_level="error",
                                    output_params=["-movflags", "+faststart"])
        with _child_processes(), writer:
            for frame in _even(frames):
                writer.append_data(frame)
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)
    return path



def draw_mujoco_rollouts(task_config, states, controls, titles, label, settings, video: Path | None,
                         strip: Path) -> list[Path]:
    """An MJCF task's rollouts (``task_config.model_path``): a video of them side by side and the
    frame strip of the first. ``settings`` has width, height (of a video panel), fps and strip_states."""
    strip_size = (2 * settings.width, 2 * settings.height)  # a picture for print: twice the video panel
    model = render_model(task_config.model_path, framebuffer=(SUPERSAMPLE * strip_size[0], SUPERSAMPLE * strip_size[1]))
    return _draw_qpos(model, states.qpos, settings, video, strip)


def draw_env_rollouts(task_config, states, controls, titles, label, settings, video: Path | None,
                      strip: Path) -> list[Path]:
    """An environment's rollouts, drawn from its own ``mj_model`` and the positions in its states'
    ``data`` (an ``mjx.Data``, as MuJoCo Playground's)."""
    from stablebptt.environments import load_env
    env = load_env(task_config.env)
    model = getattr(env, "mj_model", None)
    qpos = getattr(getattr(states, "data", None), "qpos", None)
    if model is None or qpos is None:
        raise InputError(f"{task_config.env} has no mj_model or its states no data.qpos: nothing to draw it from")
    strip_size = (2 * settings.width, 2 * settings.height)
    _brighten_headlight(model.vis.headlight)
    model.vis.global_.offwidth = max(model.vis.global_.offwidth, SUPERSAMPLE * strip_size[0])
    model.vis.global_.offheight = max(model.vis.global_.offheight, SUPERSAMPLE * strip_size[1])
    return _draw_qpos(model, np.asarray(qpos), settings, video, strip)


def _draw_qpos(model, qpos: np.ndarray, settings, video: Path | None, strip: Path) -> list[Path]:
    """Rollouts given as positions [N, T+1, nq]: the video side by side and the strip of the first."""
    strip_size = (2 * settings.width, 2 * settings.height)
    written = []
    cameras = [frame_camera(model, *rollout_extent(model, q), settings.width, settings.height) for q in qpos]
    if video is not None:
        panels = [render_frames(model, q, camera, settings.width, settings.height)[0] for q, camera in zip(qpos, cameras)]
        written.append(write_video(video, tile(panels), settings.fps))
    picks = strip_indices(len(qpos[0]), settings.strip_states)
    frames, masks = render_frames(model, qpos[0][picks], cameras[0], *strip_size, supersample=SUPERSAMPLE, with_masks=True)
    written.append(write_png(strip, frame_strip(frames, masks)))
    return written


def _named_path(stem: Path, ending: str) -> Path:
    """``stem`` with ``ending`` appended (not ``with_suffix``, which would eat a dot inside a model's name)."""
    return stem.with_name(stem.name + ending)


def fresh_outputs(out: Path | None, default_stem: Path, picture: str, gif: bool, video: bool) -> tuple[Path, Path]:
    """(video, picture) paths that do not exist yet.

    With ``out`` (a video file name; the picture is named after it) an existing file is an
    error; otherwise ``default_stem`` + ``.mp4``/``.gif`` and ``-<picture>.png``, with a
    suffix -2, -3, ... until neither exists.
    """
    suffix = ".gif" if gif else ".mp4"
    if out is not None:
        if out.suffix.lower() not in (".mp4", ".gif"):
            raise InputError(f"--out {out}: give a video file name ending in .mp4 or .gif")
        if gif and out.suffix.lower() != ".gif":
            raise InputError(f"--gif writes a GIF, but --out {out} ends in {out.suffix}: drop one of the two")
        if not out.parent.is_dir():
            raise InputError(f"cannot write {out}: the directory {out.parent} does not exist")
        picture_path = _named_path(out.with_suffix(""), f"-{picture}.png")
        for path in (out, picture_path) if video else (picture_path,):
            if path.exists():
                raise InputError(f"{path} already exists: choose another --out (render.py never overwrites)")
        return out, picture_path
    candidate, number = default_stem, 1
    while (video and _named_path(candidate, suffix).exists()) or _named_path(candidate, f"-{picture}.png").exists():
        number += 1
        candidate = _named_path(default_stem, f"-{number}")
    return _named_path(candidate, suffix), _named_path(candidate, f"-{picture}.png")
