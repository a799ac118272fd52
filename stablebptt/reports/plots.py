"""Learning curves drawn from run directories: they read ``config.json`` and ``metrics.csv``, never train.

    from stablebptt.reports.plots import learning_curves, plot_run
    plot_run("runs/repulsion-20261122-101500")            # -> .../learning_curves.png
    learning_curves(["runs/r", "runs/c"], "compare.png", smooth=30)

One figure, three panels sharing the epoch axis: test loss (log scale),
update norm (log scale) and the cosine of the gradients g_M and g_R. Each run
is one line (the mean over its seeds) with a band (min-max or +-std over its
seeds). Colour says the gradient flow, line style the clipping. The numbers
drawn (a run's tables, smoothing, the band) come from ``stablebptt.reports.curves``.
"""
from __future__ import annotations

import functools
import io
import warnings
from collections import Counter
from pathlib import Path
from typing import Callable, Iterable, Sequence

import matplotlib
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import to_rgb
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.ticker import LogFormatter, MaxNLocator

from stablebptt.cli import typed_option
from stablebptt.errors import InputError, StorageError, real_number, whole_number
from stablebptt.flows.modes import MODE_ORDER, MODES
from stablebptt.reports.choices import BANDS, format_problem
from stablebptt.reports.curves import (
    LOSS,
    Run,
    aggregate,
    default_smooth,
    effective_window,
    load_run,
    moving_average,
    score_of,
    x_values,
)
from stablebptt.storage import atomic_write

FIGURE_FILE = "learning_curves.png"
MAX_DPI = 1200  # a print's resolution; far more makes an image past matplotlib's 65,536 pixels a side

# Okabe-Ito colours (distinguishable with colour blindness), given to the modes in MODE_TABLE's order.
PALETTE = ("#0072B2", "#E69F00", "#CC79A7", "#009E73", "#D55E00", "#56B4E9", "#F0E442", "#000000")
MODE_COLORS = dict(zip(MODES, PALETTE))
CLIP_STYLES = {"value": "-", "norm": "--", "none": ":"}

# Train options that do not change what a curve means (or show on the axes anyway): never in a label.
# A budget is how long the run's last start ran, which its curve's length shows.
_UNLABELLED_TRAIN_KEYS = {"mode", "clip", "epochs", "seeds", "seed", "checkpoint_every", "seed_batching", "cosine",
                          "budget"}

# (metrics.csv column, panel title, y label, log scale)
PANELS = (
    ("test_loss", "Test loss", "test loss", True),
    ("update_norm", "Update norm", r"$\|\Delta\theta\|_2$ per update", True),
    ("cosine", r"Cosine similarity of $g_M$ and $g_R$", r"$\cos(g_M, g_R)$", False),
)


def run_labels(runs: Sequence[Run]) -> list[str]:
    """Legend labels: flow and clipping, plus whatever else differs between the runs.

    Args:
      runs: the runs of one figure.

    Returns:
      One label per run, e.g. ``"C, clip value, rc=0.01"``; the directory name is
      appended where two labels would otherwise be equal.
    """
    labels = [f"{run.mode}, " + ("no clip" if run.clip == "none" else f"clip {run.clip}") for run in runs]
    extras = [[] for _ in runs]
    task_names = [str(run.config.get("task", "?")) for run in runs]
    if len(set(task_names)) > 1:
        for extra, task_name in zip(extras, task_names):
            extra.append(task_name)
    # Task options are compared within each task only: another task's options say nothing here.
    for task_name in dict.fromkeys(task_names):
        members = [i for i, name in enumerate(task_names) if name == task_name]
        _append_differences(extras, members, [runs[i].config.get("task_config") or {} for i in members], set())
    _append_differences(extras, range(len(runs)), _as_trained([run.config.get("train") or {} for run in runs]),
                        _UNLABELLED_TRAIN_KEYS)
    labels = [", ".join([label] + extra) for label, extra in zip(labels, extras)]
    repeated = Counter(labels)
    return [f"{label} ({run.path.name})" if repeated[label] > 1 else label for label, run in zip(labels, runs)]


def _as_trained(settings: list[dict]) -> list[dict]:
    """Train settings with the options a record predates filled in as that run trained (the option's
    default, or the value it had before it was recorded), so that an older run is not labelled None."""
    keys = set().union(*settings)
    if all(len(setting) == len(keys) for setting in settings):
        return settings
    from dataclasses import fields

    from stablebptt.engine.config import RECORDED_BEFORE, TrainConfig  # imports JAX: only where a record is older
    trained = {field.name: field.default for field in fields(TrainConfig)} | RECORDED_BEFORE
    return [{**{key: trained.get(key) for key in keys}, **setting} for setting in settings]


def _append_differences(extras: list[list[str]], members: Sequence[int], settings: list[dict], skip: set) -> None:
    """Append ``key=value`` to the labels of ``members`` for every key whose value is not the same for all."""
    for key in sorted(set().union(*settings) - skip):
        values = [setting.get(key) for setting in settings]
        if any(value != values[0] for value in values):
            for member, value in zip(members, values):
                extras[member].append(f"{key}={_short(value)}")


def _short(value) -> str:
    return f"{value:g}" if isinstance(value, float) else str(value)


# Task options a title leaves out: the run's name says them (the model file, the environment).
_NAMED_BY_THE_RUN = {"model", "env"}


def _common_settings(runs: Sequence[Run]) -> str:
    """What all runs share, in the words of the command that trained them: the run's name (a model's,
    an environment's) and the options set, as flags: 'cartpole_3: --steps 80 --no-zero-output'."""
    tasks = {run.config.get("task") for run in runs}
    if len(tasks) != 1 or None in tasks:
        return ""
    names = {str((run.config.get("resolved_task") or {}).get("name") or run.config.get("task")) for run in runs}
    settings = [run.config.get("task_config") or {} for run in runs]
    # The options the runs' records say were set (a title names only values all runs share, so a record
    # that says speaks for one that predates it); without any, the values alone: 0 and "" mean the
    # task's own value, True the usual one.
    recorded = [options for options in (run.config.get("task_options_set") for run in runs) if isinstance(options, list)]
    flags = []
    for key, value in sorted(settings[0].items()):
        usual = (all(key not in options for options in recorded) if recorded else
                 value is True or value is None or value == "" or (not isinstance(value, bool) and value == 0))
        if key in _NAMED_BY_THE_RUN or usual or any(s.get(key) != value for s in settings):
            continue
        flags.append(typed_option(key, value))
    name = names.pop() if len(names) == 1 else str(tasks.pop())
    return name + (f": {' '.join(flags)}" if flags else "")


def _styles(runs: Sequence[Run]) -> list[tuple[tuple, str]]:
    """(colour, line style) per run: colour = flow, style = clipping; runs sharing both get darker or lighter shades."""
    seen = Counter()
    styles = []
    for run in runs:
        key = (run.mode, run.clip)
        variant = seen[key]
        seen[key] += 1
        base = np.array(to_rgb(MODE_COLORS.get(run.mode, "#555555")))
        # 0: base colour; then alternately darker and lighter, so variants stay within the flow's hue.
        amount = 0.35 * ((variant + 1) // 2)
        target = np.zeros(3) if variant % 2 else np.ones(3)
        colour = tuple(base + (target - base) * min(amount, 0.7))
        styles.append((colour, CLIP_STYLES.get(run.clip, "-.")))
    return styles


def _sort_key(run: Run) -> tuple:
    mode = MODE_ORDER.index(run.mode) if run.mode in MODE_ORDER else len(MODE_ORDER)
    clip = list(CLIP_STYLES).index(run.clip) if run.clip in CLIP_STYLES else len(CLIP_STYLES)
    return mode, clip


class _PlainLogFormatter(LogFormatter):
    """Log-axis labels where matplotlib would put them, written 0.05 rather than 5e-02."""

    def __call__(self, x, pos=None):
        return f"{x:g}" if super().__call__(x, pos) else ""


# Text falls back, character by character, to installed fonts of wide coverage, and last to matplotlib's
# own Last Resort font (a box naming the character's block): run paths and model names may be in any script.
FALLBACK_FONTS = ("Noto Sans", "Noto Sans CJK JP", "Noto Sans CJK SC", "WenQuanYi Zen Hei", "Droid Sans Fallback",
                  "Arial Unicode MS", "Last Resort High-Efficiency")


def _font_families() -> list[str]:
    from matplotlib import font_manager
    installed = {font.name for font in font_manager.fontManager.ttflist}
    return ["DejaVu Sans"] + [name for name in FALLBACK_FONTS if name in installed]


def draw(runs: Sequence[Run], smooth: int = 0, band: str = "minmax", title: str | None = None,
         x_axis: str = "epoch") -> Figure:
    """The learning-curve figure of some runs (not yet saved).

    Args:
      runs: loaded runs; drawn in the paper's order of flows R, M, C, S.
      smooth: moving-average window in epochs (``moving_average``); 0 = raw curves.
      band: ``"minmax"`` or ``"std"`` over seeds (``aggregate``).
      title: the figure title; by default the task, the shared options and what line and band show.
      x_axis: what the curves are drawn against (``choices.X_AXES``): epochs, env steps per seed, or
        training wall time.

    Returns:
      A matplotlib ``Figure`` on the Agg canvas (no display needed).
    """
    with matplotlib.rc_context({"font.family": _font_families()}):  # fonts are chosen as texts are made
        return _draw(runs, smooth, band, title, x_axis)


def _draw(runs: Sequence[Run], smooth: int, band: str, title: str | None, x_axis: str = "epoch") -> Figure:
    if not runs:
        raise InputError("no run to draw: give at least one run directory")
    if not (whole_number(smooth) and smooth >= 0):  # the command checks its --smooth before this
        raise InputError(f"smooth must be a whole number of epochs, zero or more, got {smooth!r}")
    if band not in BANDS:
        raise InputError(f"unknown band {band!r}: choose one of {', '.join(BANDS)}")
    runs = sorted(runs, key=_sort_key)  # stable: runs of one flow and clip keep the caller's order
    labels, styles = run_labels(runs), _styles(runs)
    figure = Figure(figsize=(15, 4.8), layout="constrained")
    FigureCanvasAgg(figure)  # explicit headless canvas: never touches pyplot or a display
    axes = figure.subplots(1, len(PANELS), sharex=True)
    few_epochs = max(len(run.epochs) for run in runs) <= 15  # markers make short curves readable
    xs = [x_values(run, x_axis) for run in runs]
    # An environment's test loss is its negative episode return: drawn as the return, on a linear axis.
    scores = {score_of(run) for run in runs}
    score = scores.pop() if len(scores) == 1 else LOSS
    for ax, (column, panel_title, ylabel, log) in zip(axes, PANELS):
        if column == "test_loss" and score != LOSS:
            panel_title, ylabel, log = score[0].capitalize(), score[0], False
        absent, drawn = [], 0
        for run, label, (colour, linestyle), (x, x_label) in zip(runs, labels, styles, xs):
            values = run.metrics.get(column, np.full((len(run.epochs), len(run.seeds)), np.nan))
            # Epochs not evaluated (an environment's cadence, --eval-every) are left out, not drawn as gaps;
            # a zero a log axis cannot show stays a gap.
            evaluated = np.any(np.isfinite(values), axis=1)
            if column == "test_loss":
                values = score[1] * values
            if log:
                values = np.where(values > 0, values, np.nan)  # a log axis cannot show 0 (e.g. S at a zero gradient)
            if not np.any(np.isfinite(values)):
                absent.append(run.mode)
                continue
            drawn += 1
            # The smoothing window stays a span of epochs: over evaluations as many as fall within it.
            x, values = x[evaluated], values[evaluated]
            window = effective_window(round(smooth * len(values) / len(evaluated)), len(values))
            if log:  # smooth log values: stays positive, and an exponential decay passes unchanged
                with np.errstate(invalid="ignore"):
                    smoothed = np.exp(moving_average(np.log(values), window))
            else:
                smoothed = moving_average(values, window)
            mean, low, high = aggregate(smoothed, band)
            ax.plot(x, mean, color=colour, linestyle=linestyle, linewidth=1.8, label=label,
                    marker="o" if few_epochs else None, markersize=3.5)
            if len(run.seeds) > 1:
                ax.fill_between(x, low, high, color=colour, alpha=0.18, linewidth=0)
        if log and drawn:
            ax.set_yscale("log")
            # Plain numbers (0.03, 2) read better than 3x10^-2; minor ticks get labels on short axes.
            ax.yaxis.set_major_formatter(_PlainLogFormatter())
            ax.yaxis.set_minor_formatter(_PlainLogFormatter(labelOnlyBase=False))
        if column == "cosine" and drawn:
            ax.axhline(0.0, color="0.6", linewidth=0.8, zorder=0)
            ax.set_ylim(-1.05, 1.05)
        ax.set_title(panel_title)
        ax.set_ylabel(ylabel)
        ax.set_xlabel(xs[0][1])
        if x_axis == "epoch":
            ax.xaxis.set_major_locator(MaxNLocator(integer=True, steps=[1, 2, 2.5, 5, 10]))
        ax.grid(True, which="major", alpha=0.3)
        if absent:
            reason = "not logged (trained with --no-cosine)" if column == "cosine" else "zero throughout: no log scale"
            if drawn:  # say who is missing under the axis, where it cannot hide a curve
                ax.annotate(f"not shown: {', '.join(dict.fromkeys(absent))}, {reason}", xy=(0.5, 0), xycoords="axes fraction",
                            xytext=(0, -34), textcoords="offset points", ha="center", va="top", fontsize=9, color="0.35")
            else:
                ax.text(0.5, 0.5, reason, transform=ax.transAxes, ha="center", va="center", fontsize=10, color="0.35")
                ax.set_yticks([])
    handles = [Line2D([], [], color=colour, linestyle=linestyle, linewidth=2.2, label=label)
               for label, (colour, linestyle) in zip(labels, styles)]
    columns = max(1, min(len(handles), 150 // max(len(label) + 8 for label in labels)))  # one row if it fits the width
    figure.legend(handles=handles, loc="outside lower center", ncol=columns, frameon=False)
    figure.suptitle(title if title is not None else _default_title(runs, smooth, band), fontsize=12)
    return figure


def _default_title(runs: Sequence[Run], smooth: int, band: str) -> str:
    seed_counts = sorted({len(run.seeds) for run in runs})
    seeds = f"{seed_counts[0]} seeds" if len(seed_counts) == 1 else "seeds"
    shown = f"line: mean over {seeds}"
    if max(seed_counts) > 1:
        shown += ", band: " + ("min to max over seeds" if band == "minmax" else "mean \u00b1 1 std over seeds")
    if smooth // 2:
        shown += f"; moving average over {2 * (smooth // 2) + 1} epochs"
        if any(effective_window(smooth, len(run.epochs)) < smooth for run in runs):
            shown += f" (a third of the run for runs under {3 * smooth} epochs)"
    setting = _common_settings(runs)
    return f"{setting}\n{shown}" if setting else shown


@functools.cache
def _shipped_fonts_listed() -> None:
    """Matplotlib's own fonts in its font list, added where its font cache left them out.

    Its mathematics (the panels' labels) draws with them; a cache written without them (seen on a fresh
    machine) makes every formula warn on stderr, font by font, that it fell back.
    """
    from matplotlib import font_manager
    listed = {Path(font.fname).resolve() for font in font_manager.fontManager.ttflist}
    for path in sorted(Path(matplotlib.get_data_path(), "fonts", "ttf").glob("*.ttf")):
        if path.resolve() not in listed:
            font_manager.fontManager.addfont(str(path))


def render(figure: Figure, out_path: Path, dpi: int = 150) -> Path:
    """Save ``figure`` atomically (rendered into memory first); the format follows the suffix."""
    if problem := format_problem(out_path):
        raise InputError(f"{out_path}: {problem}")
    if not out_path.parent.is_dir():
        raise InputError(f"cannot write {out_path}: the directory {out_path.parent} does not exist")
    _shipped_fonts_listed()
    buffer = io.BytesIO()
    with warnings.catch_warnings():
        # A character no installed font has is drawn as a box; matplotlib's warning of it says no more.
        warnings.filterwarnings("ignore", message="Glyph .* missing from font")
        figure.savefig(buffer, format=out_path.suffix.lower()[1:], dpi=dpi)
    try:
        atomic_write(out_path, buffer.getvalue())
    except StorageError as error:  # its words already name the file
        raise InputError(error.strerror) from None
    return out_path


def learning_curves(run_dirs: Iterable[str | Path], out_path: str | Path, smooth: int | None = 0, band: str = "minmax",
                    title: str | None = None, dpi: int = 150,
                    note: Callable[[str], None] = lambda line: None, x_axis: str = "epoch") -> Path:
    """Draw the learning curves of some run directories into one figure file.

    Args:
      run_dirs: run directories written by ``scripts/train.py`` (repeats are drawn once).
      out_path: the figure file (.png, .pdf or .svg); replaced atomically.
      smooth: moving-average window in epochs; 0 = raw curves (the paper uses 30);
        None = ``default_smooth`` of the longest run.
      band: ``"minmax"`` (band spans all seeds) or ``"std"`` (mean +- one standard deviation).
      title: figure title; by default the shared task settings and what line and band show.
      dpi: resolution of a PNG, 1 to ``MAX_DPI``.
      note: told where a run's metrics were read from elsewhere than its ``metrics.csv``.
      x_axis: what the curves are drawn against (``choices.X_AXES``).

    Returns:
      The path written.

    Raises:
      InputError: a run directory is missing or unreadable, or an argument is out of range.
    """
    if isinstance(run_dirs, (str, Path)):  # one run directory, not a list of its name's characters
        run_dirs = [run_dirs]
    if not (real_number(dpi) and 1 <= dpi <= MAX_DPI):
        raise InputError(f"dpi must be a number from 1 to {MAX_DPI}, got {dpi!r}")
    unique = {}
    for run_dir in map(Path, run_dirs):
        unique.setdefault(run_dir.resolve(), run_dir)  # keep the caller's spelling for messages
    if not unique:
        raise InputError("no run directory given")
    runs = [load_run(run_dir) for run_dir in unique.values()]
    for run in runs:
        if run.note:
            note(run.note)
    if smooth is None:
        smooth = default_smooth(max(len(run.epochs) for run in runs))
    figure = draw(runs, smooth=smooth, band=band, title=title, x_axis=x_axis)
    return render(figure, Path(out_path), dpi=dpi)


def plot_run(run_dir: str | Path) -> Path:
    """Write ``learning_curves.png`` into a run directory, smoothed as ``default_smooth`` chooses.

    Args:
      run_dir: a run directory with at least one finished epoch.

    Returns:
      The path of the PNG.
    """
    return learning_curves([run_dir], Path(run_dir) / FIGURE_FILE, smooth=None)
