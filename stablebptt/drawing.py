"""Drawers of MuJoCo scenes for the task registry: an MJCF task's rollouts and an environment's.

Each draws a video of the rollouts side by side and the frame strip of the first
(``stablebptt.rendering``), from the positions the rollouts visited.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from stablebptt.errors import InputError
from stablebptt.media import tile, write_png, write_video
from stablebptt.rendering import (SUPERSAMPLE, brighten_headlight, frame_camera, frame_strip, render_frames,
                                  render_model, rollout_extent, strip_indices)


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
    brighten_headlight(model.vis.headlight)
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
