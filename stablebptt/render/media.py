"""Pictures and videos out of pixels: figure pixels, tiles, PNG and MP4/GIF files written atomically, fresh names.

    write_video("rollout.mp4", tile([frames_a, frames_b]), fps=30)
    write_png("strip.png", image)
    video, picture = fresh_outputs(None, Path("runs/r/rollout"), "strip", gif=False, video=True)
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import numpy as np

from stablebptt.errors import InputError
from stablebptt.render.gl_backend import child_processes
from stablebptt.storage import atomic_write

VIDEO_FORMATS = (".mp4", ".gif")


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
        with child_processes(), writer:
            for frame in _even(frames):
                writer.append_data(frame)
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)
    return path


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
            raise InputError(f"{out}: give the video (--out) a file name ending in .mp4 or .gif")
        if gif and out.suffix.lower() != ".gif":
            raise InputError(f"a GIF (--gif) was asked for, but the video {out} (--out) ends in {out.suffix}: "
                             "drop one of the two")
        if not out.parent.is_dir():
            raise InputError(f"cannot write {out}: the directory {out.parent} does not exist")
        picture_path = _named_path(out.with_suffix(""), f"-{picture}.png")
        for path in (out, picture_path) if video else (picture_path,):
            if path.exists():
                raise InputError(f"{path} already exists: choose another video file (--out); rendering never "
                                 "overwrites")
        return out, picture_path
    candidate, number = default_stem, 1
    while (video and _named_path(candidate, suffix).exists()) or _named_path(candidate, f"-{picture}.png").exists():
        number += 1
        candidate = _named_path(default_stem, f"-{number}")
    return _named_path(candidate, suffix), _named_path(candidate, f"-{picture}.png")
