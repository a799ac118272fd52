"""MuJoCo frames of rollouts, rendered headless: a backdrop, a camera framed on the rollout, frame strips.

    select_gl_backend()                    # first: before anything imports mujoco (stablebptt.render.gl_backend)
    model = render_model("stablebptt/models/cartpole_1.xml")
    camera = frame_camera(model, *rollout_extent(model, qpos), 320, 240)   # qpos: [T, nq]
    frames, _ = render_frames(model, qpos, camera, 320, 240)
    write_video("rollout.mp4", frames, fps=30)                            # stablebptt.render.media
    picks = strip_indices(len(qpos), 8)
    frames, masks = render_frames(model, qpos[picks], camera, 320, 240, supersample=2, with_masks=True)
    write_png("strip.png", frame_strip(frames, masks))

Nothing here imports mujoco at import time (it reads ``MUJOCO_GL`` once, when
first imported); the functions import it when called. The backend choice
(``stablebptt.render.gl_backend``) and the files written (``stablebptt.render.media``) live
in their own modules.
"""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from stablebptt.errors import InputError

BACKGROUND = (1.0, 1.0, 1.0)  # plain white behind models without a skybox of their own: print-friendly
AZIMUTH = 90.0  # look along +y: a planar system moving in the x-z plane (the MJCF convention) faces the camera
ELEVATION = -15.0  # slightly from above, so depth still reads
SUPERSAMPLE = 2  # render at 2x and average: smooth edges in the masks that frame strips blend with
# A longer rollout's video draws every k-th state: drawing frames is what a render's time goes to
# (a 1000-step episode, one frame a step, took two minutes for three 400x300 panels on two busy CPU cores).
MAX_VIDEO_FRAMES = 300


def brighten_headlight(headlight) -> None:
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
        from stablebptt.runs.model_store import load_compiled_model
        model = load_compiled_model(path)
        brighten_headlight(model.vis.headlight)
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
    brighten_headlight(spec.visual.headlight)
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


def video_stride(total: int, every: int = 0) -> int:
    """The steps between a video's frames for a rollout of ``total`` states: ``every``, or for 0 the
    smallest stride that keeps the video within ``MAX_VIDEO_FRAMES`` frames (1 for a rollout that fits)."""
    return every or max(1, -(-(total - 1) // (MAX_VIDEO_FRAMES - 1)))


def video_indices(total: int, stride: int) -> np.ndarray:
    """The states a video of a rollout of ``total`` states draws: every ``stride``-th from the first, and the last."""
    picks = np.arange(0, total, stride)
    return picks if picks[-1] == total - 1 else np.append(picks, total - 1)


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
