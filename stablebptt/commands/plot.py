#!/usr/bin/env python3
"""Plot the learning curves of run directories: test loss, update norm and cos(g_M, g_R) per epoch.

    python scripts/plot.py runs/repulsion-20261122-101500            # -> that run's learning_curves.png
    python scripts/plot.py runs/r runs/m runs/c runs/s --out compare.png --smooth 30
    python scripts/plot.py runs/c --band std --out c.pdf

One run directory: the figure goes to learning_curves.png inside it (the file
stablebptt.reports.plots.plot_run writes at the end of a run) unless --out says otherwise. Several run directories: the
comparison needs --out, so that it never lands in one run's directory. The
figure is derived from config.json and metrics.csv, so it is replaced
(atomically) whenever it is drawn again. A metrics.csv that is missing, empty or
cut mid-line is read from the run's checkpoint.npz instead (one line on stderr
says so; --resume writes it back); without a checkpoint a cut last line is left out. Smoothing defaults to the paper's
30 epochs for runs of at least 90 epochs and none for shorter ones.
"""
from __future__ import annotations

import argparse
import sys

from stablebptt.cli import Parser, fail, path_named
from stablebptt.errors import InputError
from stablebptt.reports.choices import BANDS, X_AXES


def parse(argv: list[str]) -> argparse.Namespace:
    parser = Parser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run_dirs", nargs="+", type=path_named, metavar="RUN_DIR", help="run directories written by scripts/train.py")
    parser.add_argument("--out", type=path_named, default=None,
                        help="figure file (.png, .pdf or .svg); default with one RUN_DIR: RUN_DIR/learning_curves.png")
    parser.add_argument("--smooth", type=int, default=None, metavar="N",
                        help="centred moving average over N epochs, 0 = raw (default: 30 for runs of >= 90 epochs, else 0)")
    parser.add_argument("--band", choices=BANDS, default="minmax",
                        help="band around the mean over seeds: min to max, or +- one standard deviation (default: minmax)")
    parser.add_argument("--x", choices=X_AXES, default="epoch", dest="x_axis",
                        help="draw against epochs, the env steps each seed simulated in training, the training "
                             "wall time (compiling excluded), or the wall clock from the command's start as --budget "
                             "counts it (set-up, compile and evaluations of every start included) (default: epoch)")
    args = parser.parse_args(argv)
    if args.smooth is not None and args.smooth < 0:
        fail(f"--smooth must be zero or positive, got {args.smooth}")
    if args.out is None and len(args.run_dirs) > 1:
        fail(f"{len(args.run_dirs)} run directories: say where the comparison goes with --out FILE.png")
    return args


def main(argv: list[str]) -> int:
    args = parse(argv)
    from stablebptt.reports import plots  # after parsing: matplotlib is slow to import, --help should not wait for it

    out = args.out if args.out is not None else args.run_dirs[0] / plots.FIGURE_FILE
    if out.is_dir():
        out = out / plots.FIGURE_FILE
    try:
        path = plots.learning_curves(args.run_dirs, out, smooth=args.smooth, band=args.band,
                                     note=lambda line: print(line, file=sys.stderr), x_axis=args.x_axis)
    except InputError as error:
        fail(str(error))
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    from stablebptt.cli import stop_at_once_on_signals
    stop_at_once_on_signals()
    sys.exit(main(sys.argv[1:]))
