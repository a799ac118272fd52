"""Drawing rollouts: the request a task's drawer gets, and the drawers of MuJoCo scenes.

A drawer is ``draw(request: DrawRequest) -> [written paths]``: it writes the video
(``request.video``, unless None) and the picture (``request.picture``) of the
rollouts it is given, sized by ``request.settings``. The registry names each task's
drawer (``stablebptt.tasks.Entry.draw``); scripts/render.py rolls a run out and asks::

    request = DrawRequest(task_config, states, controls, titles, "cart-pole, mode C",
                          DrawSettings(width=400, height=300), video=Path("rollout.mp4"),
                          picture=Path("rollout-strip.png"))
    written = draw_mujoco_rollouts(request)

The MuJoCo drawers here draw a video of the rollouts side by side (every state of a
rollout of up to ``MAX_VIDEO_FRAMES`` states, else evenly spaced ones) and the frame strip
of the first (``stablebptt.render.mujoco_frames``), from the positions the rollouts
visited; the pictures of tasks without a MuJoCo scene are ``stablebptt.apps.figures``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from stablebptt.errors import InputError
from stablebptt.render.media import tile, write_png, write_video
from stablebptt.render.mujoco_frames import (
    SUPERSAMPLE,
    brighten_headlight,
    frame_camera,
    frame_strip,
    render_frames,
    render_model,
    rollout_extent,
    strip_indices,
    video_indices,
    video_stride,
)

# A frame strip is a picture for print: STRIP_SCALE times the video panel, drawn at SUPERSAMPLE times that within an
# offscreen framebuffer of 8192 pixels a side (a panel of 2048 x 2048 drew on Mesa's renderer; 40000 did not).
STRIP_SCALE = 2
MIN_PANEL_PIXELS, MAX_PANEL_PIXELS = 16, 8192 // (STRIP_SCALE * SUPERSAMPLE)


@dataclass(frozen=True)
class DrawSettings:
    """How rollouts are drawn.

    Attributes:
      width, height: pixels of one rollout's video panel (pictures for print are drawn larger).
      fps: video frames per second (one frame per drawn step).
      strip_states: MuJoCo scenes: states overlaid in the frame strip.
      frame_every: MuJoCo scenes: the video draws every this many steps' state, and the last; 0: every
        step's for rollouts within ``MAX_VIDEO_FRAMES`` states, else the smallest stride that keeps
        the video within them (``video_stride``).
    """

    width: int = 400
    height: int = 300
    fps: float = 30.0
    strip_states: int = 8
    frame_every: int = 0

    def __post_init__(self):
        if not all(MIN_PANEL_PIXELS <= side <= MAX_PANEL_PIXELS for side in (self.width, self.height)):
            raise InputError(f"a video panel must be at least {MIN_PANEL_PIXELS}x{MIN_PANEL_PIXELS} pixels and at most "
                             f"{MAX_PANEL_PIXELS}x{MAX_PANEL_PIXELS}, got {self.width}x{self.height}")
        if not (math.isfinite(self.fps) and self.fps > 0):
            raise InputError(f"frames per second must be a positive number, got {self.fps}")
        if self.strip_states <= 0:
            raise InputError(f"a frame strip needs at least one state, got strip_states={self.strip_states}")
        if self.frame_every < 0:
            raise InputError(f"frame_every must be a number of steps, or 0 for one chosen by the rollout's length, got {self.frame_every}")

    @property
    def strip_size(self) -> tuple[int, int]:
        """A frame strip's pixels: a picture for print, ``STRIP_SCALE`` times the video panel."""
        return STRIP_SCALE * self.width, STRIP_SCALE * self.height


@dataclass(frozen=True)
class DrawRequest:
    """What a task's drawer gets: rollouts, their words, and where to write.

    Attributes:
      task_config: the task's configuration (its module's ``Config``).
      states: NumPy pytree, leaves [N, T+1, ...]: N rollouts, the initial state first.
      controls: NumPy pytree, leaves [N, T, ...].
      titles: one title per rollout (e.g. its loss).
      label: the configuration in a few words, the figure's title.
      settings: sizes and frame rate.
      video: the video to write (``.mp4`` or ``.gif``), or None for the picture alone.
      picture: the PNG to write (a frame strip, paths, a density: the task's ``Entry.picture``).
    """

    task_config: Any
    states: Any
    controls: Any
    titles: Sequence[str]
    label: str
    settings: DrawSettings
    video: Path | None
    picture: Path


Drawer = Callable[[DrawRequest], list]  # draw(request) -> the paths it wrote


def draw_mujoco_rollouts(request: DrawRequest) -> list[Path]:
    """An MJCF task's rollouts (``request.task_config.model_path``): a video of them side by side and
    the frame strip of the first."""
    settings = request.settings
    strip_size = settings.strip_size
    model = render_model(request.task_config.model_path,
                         framebuffer=(SUPERSAMPLE * strip_size[0], SUPERSAMPLE * strip_size[1]))
    return _draw_qpos(model, request.states.qpos, settings, request.video, request.picture)


def draw_env_rollouts(request: DrawRequest) -> list[Path]:
    """An environment's rollouts, drawn from its own ``mj_model`` and the positions in its states'
    ``data`` (an ``mjx.Data``, as MuJoCo Playground's)."""
    from stablebptt.envs.protocol import load_env
    env_name = request.task_config.env
    model = getattr(load_env(env_name), "mj_model", None)
    qpos = getattr(getattr(request.states, "data", None), "qpos", None)
    if model is None or qpos is None:
        raise InputError(f"{env_name} has no mj_model or its states no data.qpos: nothing to draw it from")
    settings = request.settings
    strip_size = settings.strip_size
    brighten_headlight(model.vis.headlight)
    model.vis.global_.offwidth = max(model.vis.global_.offwidth, SUPERSAMPLE * strip_size[0])
    model.vis.global_.offheight = max(model.vis.global_.offheight, SUPERSAMPLE * strip_size[1])
    return _draw_qpos(model, np.asarray(qpos), settings, request.video, request.picture)


def _draw_qpos(model, qpos: np.ndarray, settings: DrawSettings, video: Path | None, strip: Path) -> list[Path]:
    """Rollouts given as positions [N, T+1, nq]: the video side by side and the strip of the first."""
    strip_size = settings.strip_size
    written = []
    cameras = [frame_camera(model, *rollout_extent(model, q), settings.width, settings.height) for q in qpos]
    if video is not None:
        drawn = video_indices(len(qpos[0]), video_stride(len(qpos[0]), settings.frame_every))
        panels = [render_frames(model, q[drawn], camera, settings.width, settings.height)[0]
                  for q, camera in zip(qpos, cameras)]
        written.append(write_video(video, tile(panels), settings.fps))
    picks = strip_indices(len(qpos[0]), settings.strip_states)
    frames, masks = render_frames(model, qpos[0][picks], cameras[0], *strip_size, supersample=SUPERSAMPLE, with_masks=True)
    written.append(write_png(strip, frame_strip(frames, masks)))
    return written
