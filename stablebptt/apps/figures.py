"""Task-specific pictures of rollouts: repulsion paths (the paper's Figure 3a) and quantum densities (Figure 5a).

Every function takes NumPy rollouts with the initial state first (``[N, T+1, ...]``
for N rollouts of T steps) and draws on matplotlib's Agg canvas: no pyplot, no
display. ``*_paths`` / ``*_density`` write a PNG; ``*_frames`` return the frames of
an animation, uint8 [T+1, H, W, 3], for ``stablebptt.render.media.write_video``.

    repulsion_paths(positions, "paths.png", physics=repulsion.Physics())
    frames = quantum_frames(states, controls, dt=0.0625, target=3)
"""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import matplotlib
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection
from matplotlib.colors import to_rgb
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from stablebptt.render.drawing import DrawRequest
from stablebptt.render.media import figure_pixels, write_video
from stablebptt.reports.plots import render
from stablebptt.tasks import quantum, repulsion

# Okabe-Ito colours (readable with colour blindness), as the learning curves use.
DRIVER_COLOUR = "#0072B2"
EVADER_COLOUR = "#E69F00"
TARGET_COLOUR = "#222222"
DENSITY_MAP = "magma"
DPI = 200  # of the static pictures: sharp in print
STYLE = {"font.size": 9, "axes.titlesize": 9, "axes.labelsize": 9, "legend.fontsize": 8,
         "xtick.labelsize": 8, "ytick.labelsize": 8, "axes.spines.top": False, "axes.spines.right": False}


def _figure(width_in: float, height_in: float, dpi: float = 100) -> Figure:
    figure = Figure(figsize=(width_in, height_in), dpi=dpi, layout="constrained")
    FigureCanvasAgg(figure)  # explicit headless canvas: never touches pyplot or a display
    return figure


def _fading_line(ax, xy: np.ndarray, colour: str, width: float, min_alpha: float = 0.2) -> LineCollection:
    """A path that fades towards white into the past: earlier is fainter, as in the frame strips.

    The fade is blended into opaque colours rather than drawn with transparency,
    where the overlapping ends of neighbouring segments would show as dots.
    """
    segments = np.stack([xy[:-1], xy[1:]], axis=1)
    strength = np.linspace(min_alpha, 1.0, max(len(segments), 1))[: len(segments), None]
    colours = 1.0 - strength * (1.0 - np.array(to_rgb(colour)))
    lines = LineCollection(segments, colors=colours, linewidths=width, capstyle="round", joinstyle="round")
    ax.add_collection(lines)
    return lines


def _square_limits(points: np.ndarray, padding: float = 0.08) -> tuple[tuple[float, float], tuple[float, float]]:
    """x and y limits of one square window holding all ``points`` [..., 2] and the origin."""
    flat = np.concatenate([np.reshape(points, (-1, 2)), np.zeros((1, 2))])
    low, high = flat.min(axis=0), flat.max(axis=0)
    centre, half = (low + high) / 2, (1 + padding) * max(float(np.max(high - low)) / 2, 0.5)
    return (centre[0] - half, centre[0] + half), (centre[1] - half, centre[1] + half)


def _repulsion_view(positions: np.ndarray, drivers: int):
    """The window of the task: every evader path and every agent's start (with the target).

    Drivers may swing far out (nothing keeps them near); following them would
    shrink the herd to a dot, so their paths are cut at the frame instead.
    """
    return _square_limits(np.concatenate([positions[:, :, drivers:].reshape(-1, 2), positions[:, 0].reshape(-1, 2)]))


def _repulsion_axes(ax, limits, title: str | None, fill: bool = False) -> None:
    """Limits, the target and labels; equal scales in a square box, or (``fill``) set later by ``_fill_axes``."""
    ax.set_xlim(*limits[0])
    ax.set_ylim(*limits[1])
    if not fill:
        ax.set_aspect("equal", adjustable="box")
    ax.plot([0], [0], marker="+", markersize=10, markeredgewidth=1.6, color=TARGET_COLOUR, zorder=5)
    ax.grid(True, alpha=0.25, linewidth=0.6)
    ax.set_xlabel("x")
    ax.set_ylabel("y")
    if title:
        ax.set_title(title)


def _fill_axes(figure: Figure, axes, limits) -> None:
    """Widen square ``limits`` to each axes' shape after layout: equal scales that fill a wide panel."""
    figure.canvas.draw()  # runs the layout, which fixes the axes boxes
    for ax in axes:
        box = ax.get_window_extent()
        ratio = box.width / box.height
        (x0, x1), (y0, y1) = limits
        if ratio >= 1:
            centre, half = (x0 + x1) / 2, (x1 - x0) / 2 * ratio
            ax.set_xlim(centre - half, centre + half)
        else:
            centre, half = (y0 + y1) / 2, (y1 - y0) / 2 / ratio
            ax.set_ylim(centre - half, centre + half)
    figure.set_layout_engine("none")  # keep the boxes the limits were fitted to


def _legend_handles() -> list[Line2D]:
    return [
        Line2D([], [], color=DRIVER_COLOUR, linewidth=2.0, label="driver (controlled)"),
        Line2D([], [], color=EVADER_COLOUR, linewidth=1.6, label="evader"),
        Line2D([], [], linestyle="none", marker="o", markerfacecolor="white", markeredgecolor="0.3", label="start"),
        Line2D([], [], linestyle="none", marker="o", color="0.3", label="end"),
        Line2D([], [], linestyle="none", marker="+", markersize=9, markeredgewidth=1.6, color=TARGET_COLOUR, label="target"),
    ]


def repulsion_paths(positions: np.ndarray, path: str | Path, titles: Sequence[str] | None = None,
                    title: str | None = None, physics: repulsion.Physics = repulsion.Physics()) -> Path:
    """Driver and evader paths of some rollouts, one panel each, earlier parts fainter.

    Args:
      positions: [N, T+1, agents, 2], drivers first (``repulsion.State.position`` with x_0 prepended).
      path: the PNG to write (atomically).
      titles: one panel title per rollout, e.g. its loss.
      title: the figure title.
      physics: tells how many agents are drivers.

    Returns:
      ``path``.
    """
    positions = np.asarray(positions, dtype=float)
    count = len(positions)
    limits = _repulsion_view(positions, physics.drivers)
    with matplotlib.rc_context(STYLE):
        figure = _figure(2.6 * count + 0.2, 3.25)
        axes = figure.subplots(1, count, squeeze=False)[0]
        for index, (ax, rollout) in enumerate(zip(axes, positions)):
            for agent in range(rollout.shape[1]):
                is_driver = agent < physics.drivers
                colour = DRIVER_COLOUR if is_driver else EVADER_COLOUR
                _fading_line(ax, rollout[:, agent], colour, 2.0 if is_driver else 1.4)
                size = 6.5 if is_driver else 5
                ax.plot(*rollout[0, agent], marker="o", markersize=size, markerfacecolor="white",
                        markeredgecolor=colour, markeredgewidth=1.3, zorder=4)
                ax.plot(*rollout[-1, agent], marker="o", markersize=size, color=colour, zorder=4)
            _repulsion_axes(ax, limits, titles[index] if titles else None)
            if index:
                ax.set_ylabel("")
        figure.legend(handles=_legend_handles(), loc="outside lower center", ncol=5, frameon=False)
        if title:
            figure.suptitle(title)
        return render(figure, Path(path), dpi=DPI)


def repulsion_frames(positions: np.ndarray, duration: float, panel: tuple[int, int] = (360, 360),
                     titles: Sequence[str] | None = None, physics: repulsion.Physics = repulsion.Physics()) -> np.ndarray:
    """An animation of some rollouts side by side: agents with the trail they leave.

    Args:
      positions: [N, T+1, agents, 2], drivers first.
      duration: simulated time of the rollout (the title shows the time).
      panel: (width, height) in pixels of one rollout's panel.
      titles: one panel title per rollout.
      physics: tells how many agents are drivers.

    Returns:
      uint8 [T+1, H, W, 3].
    """
    positions = np.asarray(positions, dtype=float)
    count, steps = positions.shape[0], positions.shape[1]
    limits = _repulsion_view(positions, physics.drivers)
    colours = [DRIVER_COLOUR if agent < physics.drivers else EVADER_COLOUR for agent in range(positions.shape[2])]
    with matplotlib.rc_context(STYLE):
        figure = _figure(count * panel[0] / 100, panel[1] / 100)
        axes = figure.subplots(1, count, squeeze=False)[0]
        trails, heads = [], []
        for index, (ax, rollout) in enumerate(zip(axes, positions)):
            _repulsion_axes(ax, limits, titles[index] if titles else None, fill=True)
            if index:
                ax.set_ylabel("")
            for agent, colour in enumerate(colours):
                is_driver = agent < physics.drivers
                ax.plot(*rollout[0, agent], marker="o", markersize=4, markerfacecolor="white",
                        markeredgecolor=colour, markeredgewidth=1.0, alpha=0.8)
                trails.append(ax.plot([], [], color=colour, linewidth=1.6 if is_driver else 1.2, alpha=0.55)[0])
                heads.append(ax.plot([], [], marker="o", markersize=7 if is_driver else 5.5, color=colour,
                                     markeredgecolor="white", markeredgewidth=0.6, zorder=6)[0])
        clock = figure.suptitle("t = 0.00")
        _fill_axes(figure, axes, limits)
        frames = []
        for step in range(steps):
            for index, rollout in enumerate(positions):
                for agent in range(len(colours)):
                    artist = index * len(colours) + agent
                    trails[artist].set_data(rollout[: step + 1, agent, 0], rollout[: step + 1, agent, 1])
                    heads[artist].set_data([rollout[step, agent, 0]], [rollout[step, agent, 1]])
            clock.set_text(f"t = {duration * step / max(steps - 1, 1):.2f}")
            frames.append(figure_pixels(figure))
        return np.stack(frames)


def _densities(states: np.ndarray, physics: quantum.Physics) -> tuple[np.ndarray, np.ndarray]:
    """(x with the walls, probability density |psi|^2 / dx with zeros on the walls) from states [..., nx, 2]."""
    density = np.sum(np.asarray(states, dtype=float) ** 2, axis=-1) / physics.dx
    walls = np.zeros(density.shape[:-1] + (1,))
    x = np.concatenate([[0.0], physics.grid, [physics.length]])
    return x, np.concatenate([walls, density, walls], axis=-1)


def quantum_density(states: np.ndarray, controls: np.ndarray, dt: float, target: int, path: str | Path,
                    titles: Sequence[str] | None = None, title: str | None = None,
                    physics: quantum.Physics = quantum.Physics()) -> Path:
    """The probability density |psi(x, t)|^2 over time and space, with the fidelity and the control below.

    Args:
      states: [N, T+1, nx, 2] (re, im), the initial state first.
      controls: [N, T], the control u_t held over step t.
      dt: time step.
      target: the eigenstate the controller steers into.
      path: the PNG to write (atomically).
      titles: one column title per rollout.
      title: the figure title.
      physics: the box.

    Returns:
      ``path``.
    """
    states, controls = np.asarray(states, dtype=float), np.asarray(controls, dtype=float)
    count, steps = states.shape[0], states.shape[1]
    x, density = _densities(states, physics)
    time = dt * np.arange(steps)
    goal = quantum.eigenstate(target, physics.nx)
    overlap = np.sum(states * goal[:, None], axis=-2)  # (re, im) of <target|psi>
    fidelity = np.sum(overlap**2, axis=-1)
    top = float(np.max(density))
    with matplotlib.rc_context(STYLE):
        figure = _figure(2.5 * count + 0.9, 4.6)
        grid = figure.add_gridspec(3, count, height_ratios=(3.2, 1, 1))
        image = None
        for index in range(count):
            ax = figure.add_subplot(grid[0, index])
            image = ax.pcolormesh(time, x, density[index].T, shading="gouraud", cmap=DENSITY_MAP, vmin=0.0, vmax=top,
                                  rasterized=True)
            ax.set_xlim(time[0], time[-1])
            ax.set_title(titles[index] if titles else None)
            ax.tick_params(labelbottom=False)
            if index == 0:
                ax.set_ylabel("position x")
            else:
                ax.tick_params(labelleft=False)
            lower = figure.add_subplot(grid[1, index], sharex=ax)
            lower.plot(time, fidelity[index], color="#009E73", linewidth=1.4)
            lower.set_ylim(-0.03, 1.03)
            lower.grid(True, alpha=0.25, linewidth=0.6)
            lower.tick_params(labelbottom=False)
            control = figure.add_subplot(grid[2, index], sharex=ax)
            # u_t holds over [t dt, (t+1) dt): a step plot shows exactly what the simulator saw.
            control.stairs(controls[index], time, color="#CC79A7", linewidth=1.2, baseline=None)
            control.axhline(0.0, color="0.6", linewidth=0.6, zorder=0)
            control.grid(True, alpha=0.25, linewidth=0.6)
            control.set_xlabel("time t")
            if index == 0:
                lower.set_ylabel(f"fidelity\nto state {target}")
                control.set_ylabel("control u")
            else:
                lower.tick_params(labelleft=False)
        colourbar = figure.colorbar(image, ax=figure.axes[0::3], location="right", fraction=0.05, pad=0.02)
        colourbar.set_label(r"$|\psi(x, t)|^2$")
        if title:
            figure.suptitle(title)
        return render(figure, Path(path), dpi=DPI)


def quantum_frames(states: np.ndarray, controls: np.ndarray, dt: float, target: int,
                   panel: tuple[int, int] = (360, 270), titles: Sequence[str] | None = None,
                   physics: quantum.Physics = quantum.Physics()) -> np.ndarray:
    """An animation of |psi(x, t)|^2 against the target's density, some rollouts side by side.

    Args:
      states: [N, T+1, nx, 2] (re, im), the initial state first.
      controls: [N, T], the control u_t held over step t.
      dt: time step.
      target: the eigenstate the controller steers into.
      panel: (width, height) in pixels of one rollout's panel.
      titles: one panel title per rollout.
      physics: the box.

    Returns:
      uint8 [T+1, H, W, 3].
    """
    states, controls = np.asarray(states, dtype=float), np.asarray(controls, dtype=float)
    count, steps = states.shape[0], states.shape[1]
    x, density = _densities(states, physics)
    _, goal = _densities(quantum.eigenstate(target, physics.nx)[:, None] * np.array([1.0, 0.0]), physics)
    top = 1.05 * max(float(np.max(density)), float(np.max(goal)))
    with matplotlib.rc_context(STYLE):
        figure = _figure(count * panel[0] / 100, panel[1] / 100)
        axes = figure.subplots(1, count, squeeze=False)[0]
        curves, fills, labels = [], [], []
        for index, ax in enumerate(axes):
            ax.plot(x, goal, color="0.35", linestyle="--", linewidth=1.0, label=f"target (state {target})")
            curves.append(ax.plot(x, density[index, 0], color="#D55E00", linewidth=1.6, label=r"$|\psi|^2$")[0])
            fills.append(ax.fill_between(x, density[index, 0], color="#D55E00", alpha=0.2, linewidth=0))
            labels.append(ax.text(0.03, 0.95, "", transform=ax.transAxes, ha="left", va="top", fontsize=7, color="0.25"))
            ax.set_xlim(x[0], x[-1])
            ax.set_ylim(0.0, top)
            ax.set_xlabel("position x")
            ax.set_title(titles[index] if titles else None)
            if index == 0:
                ax.set_ylabel(r"$|\psi(x, t)|^2$")
                ax.legend(loc="upper right", frameon=False, fontsize=7)
        clock = figure.suptitle("")
        frames = []
        for step in range(steps):
            for index in range(count):
                curves[index].set_ydata(density[index, step])
                fills[index].remove()
                fills[index] = axes[index].fill_between(x, density[index, step], color="#D55E00", alpha=0.2, linewidth=0)
                u = controls[index, min(step, controls.shape[1] - 1)]
                labels[index].set_text(f"u = {u:+.2f}")
            clock.set_text(f"t = {dt * step:.2f}")
            frames.append(figure_pixels(figure))
        return np.stack(frames)


def draw_repulsion(request: DrawRequest) -> list[Path]:
    """The registry's drawer for repulsion: an animation of the agents and their paths."""
    settings, positions = request.settings, request.states.position
    written = []
    if request.video is not None:
        frames = repulsion_frames(positions, repulsion.Physics().duration, (settings.width, settings.height), request.titles)
        written.append(write_video(request.video, frames, settings.fps))
    written.append(repulsion_paths(positions, request.picture, request.titles, title=request.label))
    return written


def draw_quantum(request: DrawRequest) -> list[Path]:
    """The registry's drawer for quantum control: the density's animation and its picture over time."""
    settings, config = request.settings, request.task_config
    written = []
    if request.video is not None:
        frames = quantum_frames(request.states, request.controls, config.dt, config.target,
                                (settings.width, settings.height), request.titles)
        written.append(write_video(request.video, frames, settings.fps))
    written.append(quantum_density(request.states, request.controls, config.dt, config.target, request.picture,
                                   request.titles, title=request.label))
    return written
