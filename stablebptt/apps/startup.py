"""The start-up table: per model or environment, the time a fresh training process takes to its first update.

Each model (``train.py --model``) or environment (``train.py --env``) is trained twice, each time in a fresh process (what a user waits for): COLD, with an
empty compile cache, then WARM, the same command again with the cache the cold run filled. The
times come from the command's own progress callbacks (``stablebptt.cli.EpochProgress``): set-up
(from the process's start to the start of compiling: imports, the model, the scene analysis,
tracing), compiling (``runs.epochs.train_epochs``'s ahead-of-time compile of the epoch) and the first
epoch's share of one update. ``scripts/bench.py --startup`` runs the processes; this module names
the models and environments and writes the table and its record.
"""
from __future__ import annotations

from pathlib import Path

from stablebptt.errors import InputError

# dm_control's suite models that train (tests/physics/test_suite_models.py), smallest first.
SUITE_MODELS = ("pendulum", "acrobot", "point_mass", "hopper", "ball_in_cup", "reacher", "fish", "walker",
                "cartpole", "cheetah", "finger", "humanoid", "stacker", "manipulator")
PARTS = ("setup_s", "compile_s", "epoch_s", "first_update_s")


def resolve_models(names: list[str], suite: str) -> list[tuple[str, Path]]:
    """Each model as (name, file): an MJCF path as given, else a name of dm_control's suite in ``suite``.

    No names: the repository's cart-poles of one and three poles, then the suite's models that train
    (``SUITE_MODELS``), the quickest first.
    """
    from stablebptt import models as repository_models
    if not names:
        names = [str(repository_models.cartpole(poles)) for poles in (1, 3)] + list(SUITE_MODELS)
    models = []
    for name in names:
        path = Path(name)
        if path.suffix not in (".xml", ".mjb"):
            if not suite:
                raise InputError(f"model {name!r} is no file: give --suite, the folder of dm_control's suite/*.xml")
            path = Path(suite) / f"{name}.xml"
        if not path.is_file():
            raise InputError(f"model {name!r}: no file {path}")
        models.append((path.stem, path))
    return models


def resolve_envs(names: list[str]) -> list[str]:
    """The environments as given, a MuJoCo Playground name checked against its registry (package.module:attribute
    is imported only by the training process)."""
    from stablebptt.envs import playground
    for name in names:
        if ":" not in name:
            playground.check_name(name)
    return names


def _seconds(run: dict, part: str) -> str:
    if run.get("status") != "ok":
        return run.get("status", "not run")
    return f"{run[part]:.1f}"


def table(rows: list[dict]) -> list[str]:
    """The Markdown table of ``rows`` (one per model or environment: ``{"model", "cold", "warm", "load"}``).

    A run's entry holds the parts in seconds (``PARTS``) and ``status``: "ok", "timeout after N s",
    "failed (exit N)" or "not run". ``warm <= cold`` compares the times to the first update.
    """
    lines = ["| model or env | cold: set-up | compile | first epoch | first update | warm: set-up | compile | first epoch "
             "| first update | warm <= cold | load average (start -> end) |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|:---:|---|"]
    for row in rows:
        cold, warm = row["cold"], row["warm"]
        both = cold.get("status") == "ok" and warm.get("status") == "ok"
        verdict = ("yes" if warm["first_update_s"] <= cold["first_update_s"] else "no") if both else "-"
        load = " -> ".join(f"{row['load'][key][0]:.1f}" for key in ("start", "end"))
        lines.append(f"| {row['model']} | " + " | ".join(_seconds(cold, part) for part in PARTS) + " | "
                     + " | ".join(_seconds(warm, part) for part in PARTS) + f" | {verdict} | {load} |")
    return lines
