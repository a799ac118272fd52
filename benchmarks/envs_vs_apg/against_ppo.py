"""Returns of `stablebptt train` run folders beside Brax PPO's on the same env, against the wall clock and
against the env steps each seed simulated: the mean over seeds and the band from the lowest seed to the
highest.

A run's wall clock is the one `--budget` counts (every start's set-up and compile, and its evaluations);
its returns are its own evaluations (`stablebptt plot RUN --x wall-clock` draws the same). Brax PPO's
are its runs in results/envs/baselines/ppo.json (`ppo_baseline.py`, 5 seeds sharing one GPU), the
campaign of the longest budget on the env, its clock compile included and its evaluations off it;
its seeds evaluate at nearby but not equal times, so each seed is interpolated onto a common grid
between the first and last times every seed evaluated at.

  python benchmarks/envs_vs_apg/against_ppo.py --runs RUNS/CheetahRun RUNS/WalkerWalk --out results/envs/suite/against_ppo_900s.png
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import suite_table  # noqa: E402

from stablebptt.reports import curves  # noqa: E402

GRID_POINTS = 200  # where each PPO seed is read between evaluations


def ours(run: curves.Run) -> dict[str, np.ndarray]:
    """A run's evaluated epochs: returns (E, seeds), wall clock (E,), env steps per seed (E,)."""
    name, sign = curves.score_of(run)
    returns = sign * run.metrics["test_loss"]
    evaluated = ~np.isnan(returns).any(axis=1)
    return {"returns": returns[evaluated], "wall-clock": curves.wall_clock(run)[evaluated],
            "env-steps": curves.x_values(run, "env-steps")[0][evaluated]}


def brax_ppo(env: str, axis: str) -> tuple[np.ndarray, np.ndarray] | None:
    """Brax PPO's returns on ``env`` on a common grid of ``axis``: (grid (G,), returns (G, seeds)); None
    without runs."""
    campaigns = suite_table._ppo_campaigns(env)
    if not campaigns:
        return None
    key = {"wall-clock": "train_wall_s", "env-steps": "env_steps"}[axis]
    seeds = [(np.array([p[key] for p in run["points"]], float), np.array([p["return"] for p in run["points"]], float))
             for run in campaigns[-1]]
    grid = np.linspace(max(x[0] for x, _ in seeds), min(x[-1] for x, _ in seeds), GRID_POINTS)
    return grid, np.stack([np.interp(grid, x, y) for x, y in seeds], axis=1)


def draw(run_dirs: list[Path], out: Path) -> Path:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from stablebptt.reports.plots import render
    runs = [curves.load_run(path) for path in run_dirs]
    figure, axes = plt.subplots(len(runs), 2, figsize=(10, 3.4 * len(runs)), squeeze=False)
    for row, run in zip(axes, runs):
        env, mine = run.config["task_config"]["env"], ours(run)
        for ax, axis, label in ((row[0], "wall-clock", "wall clock, s (set-up and compile included)"),
                                (row[1], "env-steps", "env steps per seed")):
            mean, low, high = curves.aggregate(mine["returns"])
            ax.plot(mine[axis], mean, color="C0", label=f"stablebptt ({len(run.seeds)} seeds)")
            ax.fill_between(mine[axis], low, high, color="C0", alpha=0.2)
            ppo = brax_ppo(env, axis)
            if ppo is not None:
                mean, low, high = curves.aggregate(ppo[1])
                ax.plot(ppo[0], mean, color="C3", label=f"Brax PPO ({ppo[1].shape[1]} seeds)")
                ax.fill_between(ppo[0], low, high, color="C3", alpha=0.2)
            if env in suite_table.PPO_REFERENCE:
                ax.axhline(suite_table.PPO_REFERENCE[env], color="grey", linestyle=":", label="PPO's published return")
            if axis == "env-steps":
                ax.set_xscale("log")
            ax.set_xlabel(label)
            ax.set_ylabel(f"{env} return")
            ax.legend(fontsize=8, loc="upper left")
    figure.tight_layout()
    return render(figure, out)


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", nargs="+", type=Path, required=True, help="run folders of `stablebptt train --env`")
    parser.add_argument("--out", type=Path, required=True, help="figure file (.png, .pdf or .svg)")
    args = parser.parse_args(argv)
    print(f"wrote {draw(args.runs, args.out)}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
