"""The installed command: ``stablebptt SUBCOMMAND [options]``, one subcommand per script."""
from __future__ import annotations

import importlib
import sys

from stablebptt.cli import stop_at_once_on_signals

SUBCOMMANDS = {
    "train": "train a controller (one run)",
    "sweep": "train a grid of tasks, flows, clippings and seeds",
    "render": "render a run's rollouts, or a model at rest",
    "plot": "plot learning curves of runs and sweeps",
    "bench": "time updates per flow and per step",
    "accuracy": "what accuracy costs in time: integrators, time steps, precision",
    "toy": "the paper's two-parameter toy problem",
}


def usage() -> str:
    width = max(map(len, SUBCOMMANDS))
    rows = "\n".join(f"  {name:<{width}}  {text}" for name, text in SUBCOMMANDS.items())
    return f"usage: stablebptt SUBCOMMAND [options]   (stablebptt SUBCOMMAND --help)\n\n{rows}"


def main(argv: list[str] | None = None) -> int:
    stop_at_once_on_signals()  # first: a stop signal ends it in one line in every phase
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] in ("-h", "--help"):
        print(usage())
        return 0
    if not argv:
        print(f"error: give a subcommand: one of {', '.join(SUBCOMMANDS)} (stablebptt --help)", file=sys.stderr)
        return 2
    if argv[0] not in SUBCOMMANDS:
        print(f"error: unknown subcommand {argv[0]!r}; one of {', '.join(SUBCOMMANDS)}", file=sys.stderr)
        return 2
    module = importlib.import_module(f"stablebptt.commands.{argv[0]}")
    sys.argv[0] = f"stablebptt {argv[0]}"  # what argparse shows in usage lines
    return module.main(argv[1:]) or 0


if __name__ == "__main__":
    sys.exit(main())
