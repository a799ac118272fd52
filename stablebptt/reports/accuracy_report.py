"""The accuracy report: tidy CSVs of the accuracy studies' rows, their tables, figures and summary.md.

Never measures: ``report(out)`` redraws everything from the CSVs and meta.json
that ``stablebptt.apps.accuracy``'s studies left in ``out``.
"""
from __future__ import annotations

import csv
import io
from pathlib import Path

META_FILE = "meta.json"
STUDIES = ("trajectory", "gradients", "training", "contact")


def write_csv(path: Path, rows: list[dict]) -> None:
    """A tidy CSV, one row per measurement; floats in full precision."""
    from stablebptt.storage import atomic_write
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=list(rows[0]), lineterminator="\n")
    writer.writeheader()
    writer.writerows([{k: repr(v) if isinstance(v, float) else v for k, v in row.items()} for row in rows])
    atomic_write(path, text.getvalue().encode())


def read_csv(path: Path) -> list[dict]:
    """Rows written by ``write_csv``, numbers and booleans parsed back."""
    def parse_value(text: str):
        if text in ("True", "False"):
            return text == "True"
        for kind in (int, float):
            try:
                return kind(text)
            except ValueError:
                pass
        return text

    with open(path, newline="") as handle:
        return [{key: parse_value(value) for key, value in row.items()} for row in csv.DictReader(handle)]


def markdown_table(header: list[str], rows: list[list[str]]) -> list[str]:
    """Markdown lines; columns whose first cell starts with a digit are right-aligned."""
    align = ["---:" if rows and rows[0][i][:1].isdigit() else "---" for i in range(len(header))]
    return ["| " + " | ".join(header) + " |", "| " + " | ".join(align) + " |"] + ["| " + " | ".join(r) + " |" for r in rows]


def sci(value: float, digits: int = 2) -> str:
    import math
    return "n/a" if not math.isfinite(value) else f"{value:.{digits - 1}e}"


def fixed(value: float, decimals: int) -> str:
    """A number with ``decimals`` decimals; empty where it was not measured (NaN)."""
    import math
    return "" if math.isnan(value) else f"{value:.{decimals}f}"


def growth_rows(rows: list[dict]) -> list[dict]:
    """Fit log ||g|| = a + lambda t over the horizons of each (task, regime, flow, precision)."""
    import numpy as np
    groups = {}
    for row in rows:
        groups.setdefault((row["task"], row["setup"], row["regime"], row["flow"], row["precision"]), []).append(row)
    fits = []
    for (task, label, regime, flow, bits), members in groups.items():
        members = [m for m in members if m["finite"] and m["norm"] > 0]
        if len(members) < 2:
            continue
        t = np.array([m["simulated_time"] for m in members])
        log_norm = np.log([m["norm"] for m in members])
        slope, intercept = np.polyfit(t, log_norm, 1)
        residual = log_norm - (intercept + slope * t)
        fits.append({"task": task, "setup": label, "regime": regime, "flow": flow, "precision": bits,
                     "exponent_per_simulated_second": float(slope), "intercept": float(intercept),
                     "rms_residual": float(np.sqrt(np.mean(residual**2))),
                     "t_min": float(t.min()), "t_max": float(t.max()), "points": len(members),
                     "norm_min": float(np.exp(log_norm.min())), "norm_max": float(np.exp(log_norm.max()))})
    return fits


# ----------------------------------------------------------------------------- figures

# Okabe-Ito colours: distinguishable with colour blindness.
INTEGRATOR_COLORS = {"euler": "#0072B2", "implicitfast": "#009E73", "rk4": "#D55E00", "crank-nicolson": "#CC79A7"}
INTEGRATOR_NAMES = {"euler": "Euler", "implicitfast": "implicitfast", "rk4": "RK4", "crank-nicolson": "Crank-Nicolson"}
PRECISION_STYLES = {"float32": ("--", "s", False), "float64": ("-", "o", True)}  # line, marker, filled
SERIES_COLORS = ("#0072B2", "#D55E00", "#009E73", "#CC79A7", "#E69F00", "#56B4E9")
FLOW_STYLES = {"R": ("-", "o", True), "M": (":", "^", False)}


def _figure(width: float, height: float):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    figure = Figure(figsize=(width, height), layout="constrained")
    FigureCanvasAgg(figure)  # headless: never touches pyplot or a display
    return figure


def _log_axes(ax, x: bool = True) -> None:
    from matplotlib.ticker import NullFormatter
    if x:
        ax.set_xscale("log")
    ax.set_yscale("log")
    ax.yaxis.set_minor_formatter(NullFormatter())  # no 4x10^-1 clutter on short axes
    ax.grid(True, which="major", alpha=0.35)
    ax.grid(True, which="minor", alpha=0.1)


def _plain_log_ticks(axis, values) -> None:
    """Ticks at ``values`` written as plain numbers (100, 0.5) on a log axis."""
    from matplotlib.ticker import FixedLocator, FuncFormatter, NullFormatter, NullLocator
    axis.set_major_locator(FixedLocator(list(values)))
    axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    axis.set_minor_locator(NullLocator())
    axis.set_minor_formatter(NullFormatter())


def _marker_style(colour: str, filled: bool) -> dict:
    return dict(marker=None, color=colour, markerfacecolor=colour if filled else "white", markeredgecolor=colour,
                markeredgewidth=1.4, markersize=7)


def _pareto(points: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """The points no other point beats in both time and error, sorted by time."""
    front, best = [], float("inf")
    for seconds, error in sorted(points):
        if error < best:
            front.append((seconds, error))
            best = error
    return front


def trajectory_figure(rows: list[dict]):
    """Error at the final time against ms per simulated second, one log-log panel per task, dt labelled."""
    import math

    from matplotlib.lines import Line2D

    setups = list(dict.fromkeys(row["setup"] for row in rows))
    figure = _figure(5.4 * len(setups), 5.2)
    axes = figure.subplots(1, len(setups), squeeze=False)[0]
    for ax, setup in zip(axes, setups):
        task_rows = [r for r in rows if r["setup"] == setup and math.isfinite(r["error"]) and r["error"] > 0]
        front = _pareto([(r["ms_per_simulated_second"], r["error"]) for r in task_rows])
        if front:
            xs, ys = zip(*front)
            ax.step(xs, ys, where="post", color="0.6", linewidth=6, alpha=0.22, zorder=0, solid_capstyle="round")
        labelled = []  # (log x, log y, text) of the dt labels drawn: Euler and implicitfast coincide on the cart-pole
        for integrator, bits in dict.fromkeys((r["integrator"], r["precision"]) for r in task_rows):
            series = sorted((r for r in task_rows if (r["integrator"], r["precision"]) == (integrator, bits)), key=lambda r: -r["dt"])
            linestyle, marker, filled = PRECISION_STYLES[bits]
            colour = INTEGRATOR_COLORS[integrator]
            ax.plot([r["ms_per_simulated_second"] for r in series], [r["error"] for r in series], linestyle=linestyle,
                    linewidth=1.4, **{**_marker_style(colour, filled), "marker": marker})
            for r in series if bits == "float64" else ():  # float32 shares the time steps
                x, y, text = math.log10(r["ms_per_simulated_second"]), math.log10(r["error"]), f"{r['dt']:.3g}"
                # Skip a label that would overlap one drawn, or repeat its dt at about the same error.
                if not any(abs(y - y0) < 0.25 and (abs(x - x0) < 0.25 or text == text0) for x0, y0, text0 in labelled):
                    labelled.append((x, y, text))
                    ax.annotate(text, (r["ms_per_simulated_second"], r["error"]), textcoords="offset points",
                                xytext=(6, 4), fontsize=7.5, color=colour)
        ax.set_title(f"{setup}, batch {task_rows[0]['batch']}, T = {task_rows[0]['simulated_time']:g}", fontsize=11)
        ax.set_xlabel("wall time per simulated second [ms] (forward rollout)")
        ax.set_ylabel("max |state - reference| at T")
        reference = task_rows[0]["reference"].split(";")[0]
        ax.annotate(f"reference: {reference}", xy=(0.5, 0), xycoords="axes fraction", xytext=(0, -34),
                    textcoords="offset points", ha="center", va="top", fontsize=8, color="0.35")
        _log_axes(ax)
    integrators = list(dict.fromkeys(r["integrator"] for r in rows))
    handles = [Line2D([], [], color=INTEGRATOR_COLORS[i], linewidth=2.2, label=INTEGRATOR_NAMES[i]) for i in integrators]
    for bits, (linestyle, marker, filled) in PRECISION_STYLES.items():
        handles.append(Line2D([], [], linestyle=linestyle, label=bits, **{**_marker_style("0.3", filled), "marker": marker}))
    handles.append(Line2D([], [], color="0.6", linewidth=6, alpha=0.3, label="Pareto front"))
    figure.legend(handles=handles, loc="outside lower center", ncol=len(handles), frameon=False)
    figure.suptitle("Trajectory error against cost (one constant control per trajectory); labels: time step dt", fontsize=12)
    return figure


def gradient_figure(rows: list[dict], fits: list[dict]):
    """(a) float32 error of the R and M gradients against the horizon; (b) ||g|| against simulated time."""
    from matplotlib.lines import Line2D

    figure = _figure(13, 5.6)
    left, right = figure.subplots(1, 2)
    series = list(dict.fromkeys((r["setup"], r["regime"]) for r in rows))
    exponent = {(f["setup"], f["regime"], f["flow"]): f["exponent_per_simulated_second"] for f in fits if f["precision"] == "float64"}
    handles = []
    for colour, (label, regime) in zip(SERIES_COLORS, series):
        for flow, (linestyle, marker, filled) in FLOW_STYLES.items():
            members = sorted((r for r in rows if (r["setup"], r["regime"], r["flow"]) == (label, regime, flow)), key=lambda r: r["horizon"])
            style = {**_marker_style(colour, filled), "marker": marker, "linestyle": linestyle, "linewidth": 1.5}
            f32 = [r for r in members if r["precision"] == "float32"]
            left.plot([r["horizon"] for r in f32], [max(r["relative_error_vs_float64"], 1e-17) for r in f32], **style)
            f64 = [r for r in members if r["precision"] == "float64"]
            right.plot([r["simulated_time"] for r in f64], [r["norm"] for r in f64], **style)
        rates = ", ".join(f"{flow} {exponent[label, regime, flow]:+.2f}" for flow in FLOW_STYLES if (label, regime, flow) in exponent)
        handles.append(Line2D([], [], color=colour, linewidth=2.2, label=f"{label}, {regime} (fitted growth per s: {rates})"))
    for flow, (linestyle, marker, filled) in FLOW_STYLES.items():
        handles.append(Line2D([], [], linestyle=linestyle, label=f"{flow} gradient", **{**_marker_style("0.3", filled), "marker": marker}))
    left.axhline(1.0, color="0.5", linewidth=0.8, zorder=0)
    left.set_xlabel("horizon [steps]")
    left.set_ylabel(r"$\|g_{32} - g_{64}\| \,/\, \|g_{64}\|$")
    left.set_title("(a) Float32 gradient error against float64")
    right.set_xlabel("simulated time of the horizon [s]")
    right.set_ylabel(r"$\|g\|$ (float64), mean over the batch")
    right.set_title(r"(b) Gradient norm: growth $\propto e^{\lambda t}$, $\lambda$ fitted")
    _log_axes(left)
    _plain_log_ticks(left.xaxis, sorted({r["horizon"] for r in rows}))
    _log_axes(right, x=False)
    figure.legend(handles=handles, loc="outside lower center", ncol=2, frameon=False, fontsize=9)
    figure.suptitle("Gradients w.r.t. the policy parameters (Glorot-initialised policy)", fontsize=12)
    return figure


def training_figure(rows: list[dict]):
    """Test loss against cumulative wall-clock seconds per mode (colour) and precision (line style)."""
    import numpy as np

    from stablebptt.flows.modes import MODE_ORDER
    from stablebptt.reports.plots import MODE_COLORS

    figure = _figure(7.8, 5.2)
    ax = figure.subplots()
    for mode in MODE_ORDER:
        for bits in PRECISION_STYLES:
            members = sorted((r for r in rows if r["mode"] == mode and r["precision"] == bits), key=lambda r: r["epoch"])
            if members:
                flat = " (loss never moves)" if len({r["test_loss"] for r in members}) == 1 else ""
                ax.plot([r["seconds"] for r in members], [r["test_loss"] for r in members], color=MODE_COLORS[mode],
                        linestyle=PRECISION_STYLES[bits][0], linewidth=1.6, label=f"{mode}, {bits}{flat}")
    ax.set_yscale("log")
    losses = [r["test_loss"] for r in rows if r["test_loss"] > 0]
    subs = range(1, 10) if max(losses) < 10 * min(losses) else (1, 2, 5)  # about five labels either way
    ticks = [v for v in np.outer(10.0 ** np.arange(-6, 7), subs).ravel() if min(losses) / 1.2 <= v <= max(losses) * 1.2]
    _plain_log_ticks(ax.yaxis, ticks)
    ax.grid(True, which="major", alpha=0.3)
    ax.set_xlabel("wall-clock seconds of training (compilation excluded)")
    ax.set_ylabel("test loss")
    epochs = max(r["epoch"] for r in rows)
    ax.set_title(f"{rows[0]['task']}: test loss against training time, {epochs} epochs per curve", fontsize=11)
    ax.legend(ncol=2, frameon=False, fontsize=9)
    return figure


# ----------------------------------------------------------------------------- tables

def trajectory_tables(rows: list[dict]) -> tuple[list[str], list[str]]:
    """(key table: the paper's time step plus each scheme's best, full table)."""
    import math
    key, full = [], []
    for row in rows:
        full.append([row["task"], INTEGRATOR_NAMES[row["integrator"]], row["precision"], f"{row['dt']:.4g}", str(row["steps"]),
                     sci(row["error"]), fixed(row["ms_per_simulated_second"], 2), fixed(row["cost_vs_paper"], 2),
                     fixed(row["gradient_ms_per_simulated_second"], 1)])
    groups = dict.fromkeys((r["task"], r["integrator"], r["precision"]) for r in rows)
    for task, integrator, bits in groups:
        members = [r for r in rows if (r["task"], r["integrator"], r["precision"]) == (task, integrator, bits)]
        at_paper = next((r for r in members if r["dt"] == r["paper_dt"]), None)
        finite = [r for r in members if math.isfinite(r["error"])]
        best = min(finite, key=lambda r: r["error"]) if finite else None
        if at_paper is None or best is None:
            continue
        key.append([task, INTEGRATOR_NAMES[integrator], bits, f"{at_paper['dt']:.4g}", sci(at_paper["error"]),
                    fixed(at_paper["cost_vs_paper"], 2), fixed(at_paper["gradient_ms_per_simulated_second"], 1),
                    f"{sci(best['error'])} at dt {best['dt']:.3g}", fixed(best["cost_vs_paper"], 1)])
    key_table = markdown_table(["task", "integrator", "precision", "dt", "error at T", "cost x", "R gradient ms / sim. s",
                                "smallest error", "its cost x"], key)
    full_table = markdown_table(["task", "integrator", "precision", "dt", "steps", "error at T", "ms / simulated s",
                                 "cost x", "R gradient ms / sim. s"], full)
    return key_table, full_table


def gradient_tables(rows: list[dict], fits: list[dict]) -> tuple[list[str], list[str]]:
    """(float32 error and norms per horizon, growth exponents)."""
    lines = []
    index = {(r["task"], r["regime"], r["horizon"], r["flow"], r["precision"]): r for r in rows}
    for task, label, regime, horizon in dict.fromkeys((r["task"], r["setup"], r["regime"], r["horizon"]) for r in rows):
        get = lambda flow, bits: index[task, regime, horizon, flow, bits]
        r64, m64 = get("R", "float64"), get("M", "float64")
        lines.append([label, regime, str(horizon), f"{r64['simulated_time']:.3g}", sci(r64["norm"]), sci(m64["norm"]),
                      sci(get("R", "float32")["relative_error_vs_float64"]), sci(get("M", "float32")["relative_error_vs_float64"]),
                      "yes" if all(get(f, b)["finite"] for f in "RM" for b in ("float32", "float64")) else "NO",
                      f"{get('R', 'float32')['ms_per_gradient']:.0f} / {r64['ms_per_gradient']:.0f}"])
    error_table = markdown_table(["set-up", "initial states", "steps", "simulated s", "norm R (f64)", "norm M (f64)",
                                  "rel. error R f32", "rel. error M f32", "all finite", "ms R+M f32 / f64"], lines)
    growth = [[f["setup"], f["regime"], f["flow"], f["precision"], f"{f['exponent_per_simulated_second']:+.3f}",
               f"{f['t_min']:.3g}-{f['t_max']:.3g}", f"{f['rms_residual']:.2f}", f"{sci(f['norm_min'])} - {sci(f['norm_max'])}"]
              for f in fits]
    growth_table = markdown_table(["set-up", "initial states", "flow", "precision", "exponent per simulated s",
                                   "fitted over s", "rms residual of log", "norm range"], growth)
    return error_table, growth_table


def training_table(rows: list[dict]) -> list[str]:
    """Per mode and precision: compile and epoch time, test loss at the start, the end and best."""
    lines = []
    for mode, bits in dict.fromkeys((r["mode"], r["precision"]) for r in rows):
        members = sorted((r for r in rows if r["mode"] == mode and r["precision"] == bits), key=lambda r: r["epoch"])
        last = members[-1]
        lines.append([mode, bits, f"{members[0]['compile_s']:.1f}", f"{last['seconds'] / max(last['epoch'], 1):.3f}",
                      f"{last['seconds']:.1f}", f"{members[0]['test_loss']:.4g}", f"{last['test_loss']:.4g}",
                      f"{min(r['test_loss'] for r in members):.4g}"])
    return markdown_table(["mode", "precision", "compile s", "s / epoch", "total s", "test loss at start",
                           "test loss at end", "best test loss"], lines)


def _short_setting(setting: str) -> str:
    """"own (100 it., tol 1e-08), 2 dt" -> "own, 2 dt"; "4 iterations" -> "4 it."."""
    head, _, tail = setting.partition(" (")
    return (head + ("," + tail.split("),", 1)[1] if ")," in tail else "")).replace(" iterations", " it.").replace(
        " iteration", " it.")


def contact_figure(rows: list[dict]):
    """Two log-log panels: trajectory error against rollout time, Jacobian error against Jacobian time; one colour per model."""
    import math

    from matplotlib.lines import Line2D

    figure = _figure(11.0, 5.2)
    panels = figure.subplots(1, 2)
    models = list(dict.fromkeys(r["model"] for r in rows))
    colours = {model: f"C{index}" for index, model in enumerate(models)}
    for ax, (x, y, xlabel, ylabel) in zip(panels, (
            ("ms_per_simulated_second", "trajectory_error", "MJX rollout, ms per simulated second (float32)",
             "max |state - MuJoCo C| at the end"),
            ("jacobian_ms_per_step", "jacobian_error", "forward-mode step Jacobians, ms per batch (float32)",
             "relative error against central differences"))):
        for model in models:
            members = [r for r in rows if r["model"] == model and math.isfinite(r[y]) and r[y] > 0]
            ax.plot([r[x] for r in members], [r[y] for r in members], linestyle="none",
                    **{**_marker_style(colours[model], True), "marker": "o"})
            for r in members:
                ax.annotate(_short_setting(r["setting"]), (r[x], r[y]), textcoords="offset points", xytext=(5, 3),
                            fontsize=7, color=colours[model])
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        _log_axes(ax)
    handles = [Line2D([], [], linestyle="none", label=model, **{**_marker_style(colours[model], True), "marker": "o"})
               for model in models]
    figure.legend(handles=handles, loc="outside lower center", ncol=len(handles), frameon=False)
    figure.suptitle("Contact scenes: error against time per constraint-solver setting", fontsize=12)
    return figure


def contact_table(rows: list[dict]) -> list[str]:
    lines = [[r["model"], str(r["contacts"]), r["setting"], f"{r['dt']:.4g}", sci(r["trajectory_error"]),
              sci(r["jacobian_error"]), fixed(r["ms_per_simulated_second"], 1), fixed(r["jacobian_ms_per_step"], 1)]
             for r in rows]
    return markdown_table(["model", "contacts", "solver", "dt", "trajectory error", "Jacobian rel. error",
                           "ms / simulated s", "ms / Jacobians"], lines)


def report(out: Path, draw: tuple[str, ...] = STUDIES) -> list[str]:
    """Summary.md, and the figures of the studies in ``draw``, from the CSVs and meta.json in ``out``.

    Never measures. Returns the key tables (Markdown lines).
    """
    from stablebptt.reports.plots import render
    from stablebptt.storage import atomic_write, read_json

    meta = read_json(out / META_FILE)
    summary = ["# What accuracy costs in time", "",
               f"Made by `{meta['command']}` on {meta['machine']}, jax {meta['jax']}. Times are medians of "
               f"{meta['rounds']} round-robin rounds (gradients: best of 3), comparable only within one table.", ""]
    printed, measured = [], lambda name: name in meta["studies"].split(",") and (out / f"{name}.csv").exists()
    if measured("trajectory"):
        rows = read_csv(out / "trajectory.csv")
        if "trajectory" in draw:
            render(trajectory_figure(rows), out / "trajectory.png")
        key_table, full_table = trajectory_tables(rows)
        references = {r["task"]: r["reference"] for r in rows}
        durations = ", ".join(f"{task} {next(r['simulated_time'] for r in rows if r['task'] == task):g}" for task in references)
        summary += ["## Trajectory error against time", "",
                    "Error: the largest |difference| over the state (positions and velocities) and over a batch of "
                    f"{rows[0]['batch']} trajectories at the final time ({durations}; cart-pole with {meta['poles']} "
                    f"pole{'s' if meta['poles'] > 1 else ''}), one constant control per trajectory. 'cost x': wall time of "
                    "the batched forward rollout per simulated second, relative to the paper's setting (its integrator "
                    "and dt, float32). 'R gradient': one R gradient of the task's loss through its policy at the "
                    "paper's dt (forward + backward), ms per simulated second.", ""]
        summary += [f"- reference, {task}: {text}" for task, text in references.items()] + [""]
        summary += key_table + ["", "![trajectory](trajectory.png)", "", "Every time step:", ""] + full_table + [""]
        printed += key_table + [""]
    if measured("gradients"):
        rows, fits = read_csv(out / "gradients.csv"), read_csv(out / "gradient_growth.csv")
        if "gradients" in draw:
            render(gradient_figure(rows, fits), out / "gradients.png")
        error_table, growth_table = gradient_tables(rows, fits)
        summary += ["## Gradients: float32 against float64, and growth with the horizon", "",
                    f"R and M gradients of the mean loss of {meta['batch']} trajectories w.r.t. the policy parameters "
                    "(Glorot output layer, so that R differs from M), one compiled program per horizon and precision; "
                    "float32 starts from the same parameters and (rounded) initial states. 'upright': the cart-pole "
                    "started with its poles at 0 +- 30 degrees instead of pi +- 30 (the poles fall and tumble).", ""]
        summary += error_table + ["", "Growth: least-squares fit of log ||g|| against the simulated time over every "
                                  "horizon (float64).", ""] + growth_table + ["", "![gradients](gradients.png)", ""]
        printed += error_table + [""] + growth_table + [""]
    if measured("training"):
        rows = read_csv(out / "training.csv")
        if "training" in draw:
            render(training_figure(rows), out / "training.png")
        table = training_table(rows)
        epochs = max(r["epoch"] for r in rows)
        setup = rows[0].get("setup") or rows[0]["task"]  # rows written before the set-up was recorded name the task
        summary += ["## Training: test loss against wall-clock time", "",
                    f"{setup}: {epochs} epochs of {meta['train_size']} "
                    "training states (batch 8), tested on as many, one seed; float64 starts from the float32 run's "
                    "data and parameters. Each mode computes only the flows it needs (--no-cosine); epochs are "
                    "timed round-robin, compilation excluded.", ""]
        summary += table + ["", "![training](training.png)", ""]
        printed += table + [""]
    if measured("contact"):
        rows = read_csv(out / "contact.csv")
        if "contact" in draw:
            render(contact_figure(rows), out / "contact.png")
        table = contact_table(rows)
        summary += ["## Contact scenes: what solver accuracy costs", "",
                    "DeepMind Control Suite models, from a state each reaches in MuJoCo's C simulation under random "
                    "controls ('contacts': its active contacts). Trajectory error: the "
                    "lean MJX step in float64 against MuJoCo's C step with the model's own settings, after "
                    f"{rows[0]['steps']} steps of random controls (each held for two steps, so '2 dt' sees the same "
                    "controls). Jacobian error: forward-mode step Jacobian (float64; the solver's implicit derivative "
                    "at the acceleration it reaches) against central differences of the C step with the model's own "
                    "solver at the same time step, relative Frobenius norm. Times: float32, a batch of "
                    f"{rows[0]['batch']} states. 'N iterations': exactly N Newton iterations "
                    "(`--solver-iterations N`).", ""]
        summary += table + ["", "![contact](contact.png)", ""]
        printed += table + [""]
    atomic_write(out / "summary.md", ("\n".join(summary) + "\n").encode())
    return printed


