"""A grid's report, rebuilt from its cell folders: tables, tidy CSV, paired bootstrap intervals of
C - R and C - M, learning-curve figures, and a one-screen verdict per clip mode.

Every function reads run folders of the single-run schema (``stablebptt.runs.run_folder``), so a report
covers whatever cells a root holds: one call's, several calls', or merged pieces'.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from stablebptt import storage
from stablebptt.flows.modes import MODE_TABLE
from stablebptt.runs import run_folder

COMPARED = MODE_TABLE["C"].flows  # C is judged against each flow it combines (R and M)


def cell_name(task_name, option, value, mode, clip) -> str:
    return f"{task_name}-{option}{value}-{mode}-{clip}"


def write_summary(root: Path, directories: list[Path]) -> list[str]:
    """Write summary.csv and return it as a Markdown table: final test loss, mean +- std over seeds, per cell."""
    lines = ["| cell | epochs | final test loss (mean +- std over seeds) | diverged seeds |", "|---|---:|---:|---:|"]
    csv_lines = ["cell,epochs,test_loss_mean,test_loss_std,diverged_seeds"]
    for directory in sorted(directories):
        rows = run_folder.read_metrics(directory / run_folder.METRICS_FILE)
        last = max(row["epoch"] for row in rows)
        final = np.array([row["test_loss"] for row in rows if row["epoch"] == last])
        diverged = int(np.sum(~np.isfinite(final)))
        finite = final[np.isfinite(final)]
        mean, std = (float(finite.mean()), float(finite.std())) if len(finite) else (float("nan"), float("nan"))
        lines.append(f"| {directory.name} | {int(last)} | {mean:.4g} +- {std:.2g} | {diverged} |")
        csv_lines.append(f"{directory.name},{int(last)},{mean!r},{std!r},{diverged}")
    storage.atomic_write(root / "summary.csv", ("\n".join(csv_lines) + "\n").encode())
    return lines


def mode_table(directories: list[Path], task_name: str, option: str, complexities, modes, clips) -> list[str]:
    """Final test loss, mean +- std over seeds: one row per complexity and clip mode, one column per mode."""
    lines = [f"| {option} | clip | epochs | " + " | ".join(modes) + " |", "|---|---|---:|" + "---:|" * len(modes)]
    for value in complexities:
        for clip in clips:
            cells, epochs = [], ""
            for mode in modes:
                directory = next((d for d in directories if d.name == cell_name(task_name, option, value, mode, clip)), None)
                if directory is None:
                    cells.append("-")
                    continue
                rows = run_folder.read_metrics(directory / run_folder.METRICS_FILE)
                last = max(r["epoch"] for r in rows)
                final = np.array([r["test_loss"] for r in rows if r["epoch"] == last])
                epochs = str(int(last))
                cells.append(f"{np.nanmean(final):.3g} +- {np.nanstd(final):.2g}" if np.isfinite(final).any() else "diverged")
            lines.append(f"| {value} | {clip} | {epochs} | " + " | ".join(cells) + " |")
    return lines


def tidy_test_loss(root: Path, directories: list[Path], option: str, every: int = 10) -> None:
    """test_loss.csv: one row per cell, seed and every tenth epoch (and the last), small enough for git."""
    lines = [f"{option},mode,clip,seed,epoch,test_loss"]
    for directory in sorted(directories):
        config = storage.read_json(directory / run_folder.CONFIG_FILE)
        train = config["train"]
        value = config["task_config"][option] if option in config["task_config"] else train[option]  # a task or a training option
        rows = run_folder.read_metrics(directory / run_folder.METRICS_FILE)
        last = max(row["epoch"] for row in rows)
        lines += [f"{value},{train['mode']},{train['clip']},{int(row['seed'])},{int(row['epoch'])},{row['test_loss']:.7g}"
                  for row in rows if row["epoch"] % every == 0 or row["epoch"] == last]
    storage.atomic_write(root / "test_loss.csv", ("\n".join(lines) + "\n").encode())


BOOTSTRAP_RESAMPLES = 10_000
BOOTSTRAP_SEED = 0  # the intervals are reproducible to the digit


def paired_bootstrap(differences: np.ndarray, level: float = 0.95) -> tuple[float, float, float]:
    """Mean of per-seed ``differences`` and its ``level`` percentile-bootstrap interval (seeds resampled)."""
    rng = np.random.default_rng(BOOTSTRAP_SEED)
    means = differences[rng.integers(0, len(differences), (BOOTSTRAP_RESAMPLES, len(differences)))].mean(axis=1)
    tail = 100 * (1 - level) / 2
    return float(differences.mean()), float(np.percentile(means, tail)), float(np.percentile(means, 100 - tail))


def _final_losses(test_loss_csv: Path, option: str) -> dict[tuple, float]:
    """(value, clip, mode, seed) -> test loss at the last epoch, from a grid's tidy CSV."""
    import csv
    with open(test_loss_csv, newline="") as handle:
        rows = list(csv.DictReader(handle))
    last = max(int(r["epoch"]) for r in rows)
    return {(r[option], r["clip"], r["mode"], r["seed"]): float(r["test_loss"]) for r in rows if int(r["epoch"]) == last}


def _verdict(low: float, high: float) -> str:
    return "C better" if high < 0 else ("C worse" if low > 0 else "not resolved")


def _comparisons(final: dict[tuple, float]) -> dict[tuple, dict[str, tuple | None]]:
    """Per (value, clip): "R" and "M" -> (mean, low, high) of C minus that mode over paired seeds
    (None where fewer than two seeds pair, or a difference is not finite)."""
    seeds = sorted({key[3] for key in final}, key=int)
    result = {}
    for value, clip in dict.fromkeys((key[0], key[1]) for key in final):
        result[(value, clip)] = {}
        for other in COMPARED:
            pairs = [(final.get((value, clip, "C", s)), final.get((value, clip, other, s))) for s in seeds]
            differences = np.array([c - o for c, o in pairs if c is not None and o is not None])
            ok = len(differences) >= 2 and np.all(np.isfinite(differences))
            result[(value, clip)][other] = paired_bootstrap(differences) if ok else None
    return result


def claim_intervals(test_loss_csv: Path, option: str) -> list[str]:
    """Per complexity and clip mode: final test loss of C minus R and of C minus M, mean over seeds with its
    95% paired bootstrap interval, and whether the interval supports "C is better" (it lies below 0).

    Seeds pair the runs: a seed gives every mode the same data and initial parameters.
    """
    final = _final_losses(test_loss_csv, option)
    seeds = {key[3] for key in final}
    lines = [f"| {option} | clip | seeds | C - R: mean [95% interval] | verdict | C - M: mean [95% interval] | verdict |",
             "|---|---|---:|---:|---|---:|---|"]
    for (value, clip), against in _comparisons(final).items():
        cells = []
        for other in COMPARED:
            if against[other] is None:
                cells += ["-", "-"]
                continue
            mean, low, high = against[other]
            cells += [f"{mean:+.3g} [{low:+.3g}, {high:+.3g}]", _verdict(low, high)]
        lines.append(f"| {value} | {clip} | {len(seeds)} | " + " | ".join(cells) + " |")
    return lines


# Below this many seeds a percentile bootstrap has few distinct resamples (2 seeds: 3 means) and
# its interval is too narrow to trust; the verdicts say so.
ROUGH_BELOW = 5


def verdicts(test_loss_csv: Path, option: str, score: tuple[str, float] = ("test loss", 1.0)) -> list[str]:
    """One line per value and clip mode: the flow with the lowest mean final test loss, and whether the
    intervals of C - R and C - M say C is better. ``score``: how the line shows that loss (its name, and
    +1 or -1 times the test loss), e.g. ("episode return", -1.0) for an environment, whose loss is the
    negative return."""
    name, sign = score
    final = _final_losses(test_loss_csv, option)
    seeds = len({key[3] for key in final})
    lines = [f"which flow wins ({name} at the last epoch, mean over {seeds} seed(s); C - X: 95% paired bootstrap interval of the test loss)"]
    if seeds < ROUGH_BELOW:
        lines[0] += f"; with fewer than {ROUGH_BELOW} seeds an interval is rough: give --seeds {ROUGH_BELOW} or more before relying on it"
    for (value, clip), against in _comparisons(final).items():
        means = {mode: np.mean([loss for (v, c, m, _), loss in final.items() if (v, c, m) == (value, clip, mode)])
                 for mode in dict.fromkeys(key[2] for key in final if key[:2] == (value, clip))}
        finite = {mode: mean for mode, mean in means.items() if np.isfinite(mean)}
        best = min(finite, key=finite.get) if finite else None
        said = [f"C - {other}: {_verdict(*against[other][1:])}" if against[other] else f"C - {other}: -"
                for other in COMPARED]
        lead = f"{option}={value}, clip {clip}: " + (f"best {best} ({name} {sign * finite[best]:.4g})" if best else "every mode diverged")
        lines.append(f"{lead}; " + "; ".join(said))
    return lines


def write_intervals(root: Path, option: str) -> list[str]:
    """intervals.md from the preset's test_loss.csv (kept with the tables, so it needs no run directories)."""
    table = claim_intervals(root / "test_loss.csv", option)
    storage.atomic_write(root / "intervals.md", ("\n".join(table) + "\n").encode())
    return table


def write_report(root: Path, directories: list[Path], task_name, option, complexities, modes, clips,
                 score: tuple[str, float] = ("test loss", 1.0)) -> list[str]:
    """summary.csv, test_loss.csv, table.md, intervals.md, verdicts.txt and one learning-curve figure per
    complexity, from the run directories; returns the table (Markdown lines) and the verdicts (``verdicts``)."""
    from stablebptt.reports.plots import learning_curves
    write_summary(root, directories)
    tidy_test_loss(root, directories, option)
    table = mode_table(directories, task_name, option, complexities, modes, clips)
    storage.atomic_write(root / "table.md", ("\n".join(table) + "\n").encode())
    write_intervals(root, option)
    said = verdicts(root / "test_loss.csv", option, score)
    storage.atomic_write(root / "verdicts.txt", ("\n".join(said) + "\n").encode())
    for value in complexities:
        members = [d for d in directories if d.name.startswith(f"{task_name}-{option}{value}-")]
        if members:
            learning_curves(members, root / f"{task_name}-{option}{value}.png", smooth=None)
    return table + [""] + said


def run_directories(root: Path, task_name: str, option: str) -> list[Path]:
    return sorted(d for d in root.glob(f"{task_name}-{option}*") if (d / run_folder.METRICS_FILE).exists())


