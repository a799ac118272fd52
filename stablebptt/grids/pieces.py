"""A grid in pieces: seed ranges trained apart (one call, or one cluster job, each) and merged.

A piece trains seeds ``[start, stop)`` of a grid of ``seeds`` seeds into
``root/pieces/seeds<start>-<stop - 1>/``: its own cell folders and checkpoints,
so it resumes alone, and a manifest (``piece.json``) saying which grid it belongs
to - task and its options, the axes, epochs, data sizes and a digest of the
code. ``merge`` checks every piece against the grid being merged (one line naming
what differs), that the pieces cover each seed exactly once and have finished,
and writes the merged cells into ``root`` as the grid run whole writes them:
seeds as rows of one run folder per (value, mode, clip).

Cells of different seeds never share a number: each seed is its own vmapped
slot, and the training and test states come from ``TrainConfig.data_seed``,
the same in every piece. A merged grid equals the grid run whole up to float32
rounding (XLA may fuse a batch of 8 cells differently from one of 4).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from stablebptt import storage
from stablebptt.engine.metrics import COLUMNS
from stablebptt.errors import InputError
from stablebptt.runs import model_store, run_folder

PIECES_FOLDER = "pieces"
MANIFEST_FILE = "piece.json"


def parse_seed_range(text: str, seeds: int) -> tuple[int, int]:
    """``"A:B"`` -> (A, B): seeds A to B - 1 (counted from 0) of a grid of ``seeds`` seeds."""
    start, colon, stop = text.partition(":")
    try:
        start, stop = int(start), int(stop)
    except ValueError:
        raise InputError(f"--seed-range takes START:STOP (seeds START to STOP-1, from 0), got {text!r}") from None
    if not colon or not 0 <= start < stop <= seeds:
        raise InputError(f"--seed-range {text}: need 0 <= START < STOP <= --seeds ({seeds})")
    return start, stop


def piece_root(root: Path, start: int, stop: int) -> Path:
    return root / PIECES_FOLDER / f"seeds{start}-{stop - 1}"



def write_manifest(folder: Path, grid_description: dict, start: int, stop: int) -> None:
    """The piece's manifest; a folder holding a piece of another grid is refused (its results would mix)."""
    path = folder / MANIFEST_FILE
    manifest = {"grid": grid_description, "seed_range": [start, stop]}
    if path.exists():
        found = storage.read_json(path)
        if found != {"grid": as_recorded(grid_description, found.get("grid")), "seed_range": [start, stop]}:
            raise InputError(f"{folder} holds a piece of another grid ({_first_difference(found, manifest)}): "
                             "choose another output folder (--out) or remove it")
        return
    folder.mkdir(parents=True, exist_ok=True)
    storage.write_json(path, manifest)


def as_recorded(grid_description: dict, recorded) -> dict:
    """``grid_description`` as a piece written before grids recorded their model's contents (``inputs``)
    would have it, where ``recorded`` is such a piece's; else unchanged."""
    identity = grid_description.get("identity")
    if isinstance(recorded, dict) and isinstance(identity, dict):
        return {**grid_description, "identity": identity_as_recorded(identity, recorded.get("identity", {}))}
    return grid_description


def identity_as_recorded(identity: dict, recorded: dict) -> dict:
    """A grid's ``identity`` as one written before grids recorded their model's contents (``inputs``)
    would have it, where ``recorded`` is such an identity; else unchanged."""
    if isinstance(recorded, dict) and "inputs" not in recorded:
        return {key: value for key, value in identity.items() if key != "inputs"}
    return identity


# The fields of a grid's description in the order a reader looks for a difference: the axes and settings
# before the code and the task options every axis value repeats.
_ORDER = ("task", "name", "option", "train_option", "values", "modes", "clips", "first_seed", "seeds", "epochs",
          "train_size", "test_size", "identity", "task_configs", "code")


def _first_difference(found: dict, expected: dict) -> str:
    """The first field in which two manifests differ, as the option that sets it: '--lrs: 0.001 there, 0.01 here'."""
    def name(path: list[str], grid: dict) -> str:
        key = path[-1] if path else "the grid"
        if key == "values":
            return "--lrs" if grid.get("train_option") == "lr" \
                else f"the values of --{str(grid.get('option', '')).replace('_', '-')}"
        if path[:2] == ["grid", "task_configs"] and len(path) > 3:
            return f"--{key.replace('_', '-')}"
        if "inputs" in path:
            return "the model file's contents"
        return {"code": "the library's code", "seed_range": "--seed-range", "first_seed": "--seed",
                "modes": "--modes", "clips": "--clips"}.get(key, f"--{key.replace('_', '-')}")

    def walk(a, b, path):
        if isinstance(a, dict) and isinstance(b, dict):
            for key in sorted(set(a) | set(b), key=lambda k: (_ORDER.index(k) if k in _ORDER else len(_ORDER), k)):
                if a.get(key) != b.get(key):
                    return walk(a.get(key), b.get(key), path + [key])
        if isinstance(a, list) and isinstance(b, list) and len(a) == len(b) and path[-1] == "task_configs":
            for index, (x, y) in enumerate(zip(a, b)):
                if x != y:
                    return walk(x, y, path + [str(index)])
        grid = (expected or {}).get("grid", expected) or {}
        return f"{name(path, grid)}: {_short(a)} there, {_short(b)} here"
    return walk(found, expected, [])


def _short(value) -> str:
    text = ", ".join(map(str, value)) if isinstance(value, list) else str(value)
    return text if len(text) <= 80 else text[:77] + "..."


def pieces(root: Path) -> list[tuple[Path, dict]]:
    """Every piece under ``root``: (folder, manifest), by seed range."""
    found = [(path.parent, storage.read_json(path)) for path in (root / PIECES_FOLDER).glob(f"*/{MANIFEST_FILE}")]
    return sorted(found, key=lambda piece: piece[1]["seed_range"])


def _missing(covered: list[tuple[int, int]], seeds: int) -> str:
    have = np.zeros(seeds, dtype=bool)
    for start, stop in covered:
        have[start:stop] = True
    gaps, start = [], None
    for seed in range(seeds + 1):
        if seed < seeds and not have[seed] and start is None:
            start = seed
        elif (seed == seeds or have[seed]) and start is not None:
            gaps.append(f"--seed-range {start}:{seed}")
            start = None
    return ", ".join(gaps)


def check_pieces(root: Path, grid_description: dict, cell_names: list[str]) -> list[Path]:
    """The pieces that make up the grid, in seed order; InputError in one line if they do not."""
    found = pieces(root)
    if not found:
        raise InputError(f"no pieces in {root / PIECES_FOLDER}: train them first with --seed-range START:STOP")
    for folder, manifest in found:
        if manifest.get("grid") != (expected := as_recorded(grid_description, manifest.get("grid"))):
            raise InputError(f"{folder} is a piece of another grid "
                             f"({_first_difference(manifest.get('grid'), expected)}): merge it with its own "
                             f"command, or remove it")
    ranges = [tuple(manifest["seed_range"]) for _, manifest in found]
    for (folder, (start, stop)), (next_folder, (next_start, next_stop)) in zip(zip(found, ranges),
                                                                               zip(found[1:], ranges[1:])):
        if next_start < stop:
            raise InputError(f"the pieces of seeds {start}-{stop - 1} and {next_start}-{next_stop - 1} overlap in "
                             f"seeds {next_start}-{min(stop, next_stop) - 1}: remove one ({folder[0]} or "
                             f"{next_folder[0]})")
    if gaps := _missing(ranges, grid_description["seeds"]):
        raise InputError(f"seeds without a piece yet: run {gaps} (the same command otherwise), then merge")
    for folder, _ in found:
        for name in cell_names:
            metrics = folder / name / run_folder.METRICS_FILE
            done = max((row["epoch"] for row in run_folder.read_metrics(metrics)), default=0) if metrics.exists() else 0
            if done != grid_description["epochs"]:
                raise InputError(f"{folder} has trained {int(done)} of {grid_description['epochs']} epochs in {name}: "
                                 f"run its command again to resume it, then merge")
    return [folder for folder, _ in found]


def merge_cell(folders: list[Path], name: str, destination: Path, write_cell,
               shared: model_store.SharedModels | None = None) -> None:
    """One cell of every piece -> one cell of all their seeds, written by ``write_cell(directory, record,
    rows, params, model_file, shared)`` (the grid's own cell writer; ``shared``: the merged grid's models)."""
    records = [storage.read_json(folder / name / run_folder.CONFIG_FILE) for folder in folders]
    rows = np.concatenate([np.array([[row[c] for c in COLUMNS] for row in run_folder.read_metrics(folder / name / run_folder.METRICS_FILE)])
                           for folder in folders])
    rows = rows[np.lexsort((rows[:, 1], rows[:, 0]))]
    leaves = [run_folder.load_param_leaves(folder / name / run_folder.PARAMS_FILE) for folder in folders]
    params = [np.concatenate(per_leaf) for per_leaf in zip(*leaves)]
    record = records[0]
    record["train"] = {**record["train"], "seed": records[0]["train"]["seed"],
                       "seeds": sum(r["train"]["seeds"] for r in records)}
    first = folders[0] / name
    # The model the piece kept: its compiled copy, shared again in the merged grid's root.
    link = first / model_store.MODEL_LINK_FILE
    compiled = first / storage.read_json(link)["compiled"] if link.is_file() else None
    write_cell(destination / name, record, rows, params, compiled, shared)
    if (first / model_store.MODEL_COPY_FILE).is_file():
        storage.atomic_write(destination / name / model_store.MODEL_COPY_FILE, (first / model_store.MODEL_COPY_FILE).read_bytes())
