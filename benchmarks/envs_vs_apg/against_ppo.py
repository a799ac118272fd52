"""Returns of `stablebptt train` run folders beside Brax PPO's on the same env, against the wall clock and
against the env steps each seed simulated: the mean over seeds and the band from the lowest seed to the
highest.

A run's wall clock is the one `--budget` counts (every start's set-up and compile, and its evaluations);
its returns are its own evaluations (`stablebptt plot RUN --x wall-clock` draws the same). Brax PPO's
are its runs in results/envs/baselines/ppo.json (`ppo_baseline.py`, 5 seeds sharing one GPU), the
campaign of the longest budget on the env and on the GPU model the run's first start ran on (of any
model where none ran there), its clock compile included and its evaluations off it;
its seeds evaluate at nearby but not equal times, so each seed is interpolated onto a common grid
between the first and last times every seed evaluated at. It also prints, env by env, the numbers
docs/performance.md reads off the figure: each side's last return and env steps, PPO's return at the
run's last env steps and at each mark of the wall clock, and where either side's mean passes the other's.

  python benchmarks/envs_vs_apg/against_ppo.py --runs RUNS/CheetahRun RUNS/WalkerWalk --out results/envs/suite/against_ppo_900s.png
  python benchmarks/envs_vs_apg/against_ppo.py --ppo WalkerStand H100     # PPO's numbers at the marks alone
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import suite_table  # noqa: E402

from stablebptt.reports import curves  # noqa: E402
from stablebptt.runs.run_folder import STARTUP_FILE  # noqa: E402
from stablebptt.storage import read_json  # noqa: E402

GRID_POINTS = 200  # where each PPO seed is read between evaluations


def ours(run: curves.Run) -> dict[str, np.ndarray]:
    """A run's evaluated epochs: returns (E, seeds), wall clock (E,), env steps per seed (E,)."""
    _, sign = curves.score_of(run)
    returns = sign * run.metrics["test_loss"]
    evaluated = ~np.isnan(returns).any(axis=1)
    return {"returns": returns[evaluated], "wall-clock": curves.wall_clock(run)[evaluated],
            "env-steps": curves.x_values(run, "env-steps")[0][evaluated]}


def card(run: curves.Run) -> str:
    """The GPU model a run's first start ran on (its ``startup.json``); "" where it names none."""
    path = run.path / STARTUP_FILE
    starts = read_json(path) if path.exists() else []
    return suite_table.card_of(starts[0].get("device", "")) if starts else ""


def campaign(env: str, on: str = "") -> list[dict]:
    """Brax PPO's runs on ``env`` of the longest budget on the GPU model ``on``, else of the longest budget
    on any; empty without runs."""
    campaigns = suite_table.ppo_campaigns(env)
    same_card = [runs for runs in campaigns if suite_table.campaign_card(runs) == on]
    return (same_card or campaigns or [[]])[-1]


def brax_ppo(env: str, axis: str, on: str = "") -> tuple[np.ndarray, np.ndarray] | None:
    """Brax PPO's returns on ``env`` (``campaign(env, on)``) on a common grid of ``axis``: (grid (G,),
    returns (G, seeds)); None without runs."""
    key = {"wall-clock": "train_wall_s", "env-steps": "env_steps"}[axis]
    seeds = [(np.array([p[key] for p in run["points"]], float), np.array([p["return"] for p in run["points"]], float))
             for run in campaign(env, on)]
    if not seeds:
        return None
    grid = np.linspace(max(x[0] for x, _ in seeds), min(x[-1] for x, _ in seeds), GRID_POINTS)
    return grid, np.stack([np.interp(grid, x, y) for x, y in seeds], axis=1)


def _mean_interval(values) -> str:
    low, high = suite_table.interval(values)
    return f"{np.mean(values):.1f} [{low:.1f}, {high:.1f}]"


def at_marks(runs: list[dict]) -> list[str]:
    """Brax PPO's ``runs`` at each mark of their budget that every seed reached (``suite_table.marks_reached``
    of its last evaluation, as a run of ours is read): each seed's evaluation nearest the mark, and each
    seed's last at or before it, with their times."""
    reached = min(run["points"][-1]["train_wall_s"] for run in runs)
    lines = []
    for mark in (mark for mark in suite_table.marks_reached(reached) if mark <= runs[0]["budget_s"]):
        before = [[point for point in run["points"] if point["train_wall_s"] <= mark] for run in runs]
        for how, points in (("nearest", suite_table.nearest_points(runs, mark)),  # however far: times printed
                            ("by", [max(seed, key=lambda point: point["train_wall_s"]) for seed in before if seed])):
            if len(points) < len(runs):
                continue  # a seed evaluated first past the mark
            times, returns = [point["train_wall_s"] for point in points], [point["return"] for point in points]
            lines.append(f"  Brax PPO's evaluations {how} {mark} s, at {min(times):.0f}-{max(times):.0f} s: "
                         f"{_mean_interval(returns)}; per seed " + " / ".join(f"{value:.0f}" for value in returns))
    return lines


def passings(grid: np.ndarray, gap: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where ``gap`` (PPO's mean less the run's along ``grid``; NaN where the run has not evaluated) turns
    positive, PPO passing the run, and where it turns negative, the run passing PPO: the first point past each."""
    rises = (gap[1:] > 0) & (gap[:-1] <= 0)  # NaN compares false: no passing where either side is missing
    falls = (gap[1:] < 0) & (gap[:-1] >= 0)
    return grid[1:][rises], grid[1:][falls]


def summary(run: curves.Run) -> list[str]:
    """What the figure shows of ``run`` beside Brax PPO, in numbers."""
    env, mine, on = run.config["task_config"]["env"], ours(run), card(run)
    runs = campaign(env, on)
    lines = [f"{env}: the run's last evaluation {_mean_interval(mine['returns'][-1])} at {mine['wall-clock'][-1]:.0f} s, "
             f"{mine['env-steps'][-1] / 1e6:.1f}M env steps a seed"]
    if not runs:
        return lines
    last_steps = [run["points"][-1]["env_steps"] for run in runs]
    at_steps = [np.interp(mine["env-steps"][-1], [p["env_steps"] for p in run["points"]],
                          [p["return"] for p in run["points"]]) for run in runs]
    lines.append(f"  Brax PPO ({runs[0]['budget_s']:.0f} s campaign, {runs[0].get('machine', 'a GPU')}): "
                 "last evaluations at "
                 f"{min(r['points'][-1]['train_wall_s'] for r in runs):.0f}-{max(r['points'][-1]['train_wall_s'] for r in runs):.0f} s "
                 f"{_mean_interval([r['points'][-1]['return'] for r in runs])}, "
                 f"{min(last_steps) / 1e6:.1f}M-{max(last_steps) / 1e6:.1f}M env steps a seed "
                 f"({min(last_steps) / mine['env-steps'][-1]:.1f}-{max(last_steps) / mine['env-steps'][-1]:.1f}x the run's); "
                 f"at the run's last env steps {_mean_interval(at_steps)}")
    lines += at_marks(runs)
    grid, returns = brax_ppo(env, "wall-clock", on)
    gap = returns.mean(axis=1) - np.interp(grid, mine["wall-clock"], mine["returns"].mean(axis=1), left=np.nan,
                                           right=np.nan)
    ppo_passes, run_passes = passings(grid, gap)
    for who, times in (("Brax PPO's mean passes the run's", ppo_passes), ("the run's mean passes Brax PPO's", run_passes)):
        lines.append(f"  {who} at " + (", ".join(f"{t:.0f} s" for t in times) or "no time"))
    return lines


def draw(run_dirs: list[Path], out: Path) -> Path:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from stablebptt.reports.plots import render
    runs = [curves.load_run(path) for path in run_dirs]
    # Laid out as render saves it, once matplotlib's own fonts are listed (a layout before warned font by font).
    figure, axes = plt.subplots(len(runs), 2, figsize=(10, 3.4 * len(runs)), squeeze=False, layout="tight")
    for row, run in zip(axes, runs):
        env, mine = run.config["task_config"]["env"], ours(run)
        mine_mean, mine_low, mine_high = curves.aggregate(mine["returns"])
        for ax, axis, label in ((row[0], "wall-clock", "wall clock, s (set-up and compile included)"),
                                (row[1], "env-steps", "env steps per seed")):
            ax.plot(mine[axis], mine_mean, color="C0", marker=".", label=f"stablebptt ({len(run.seeds)} seeds)")
            ax.fill_between(mine[axis], mine_low, mine_high, color="C0", alpha=0.2)
            ax.vlines(mine[axis], mine_low, mine_high, color="C0", alpha=0.4)  # a run of one evaluation has no band
            ppo = brax_ppo(env, axis, card(run))
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
    return render(figure, out)


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", nargs="+", type=Path, help="run folders of `stablebptt train --env`")
    parser.add_argument("--out", type=Path, help="figure file (.png, .pdf or .svg)")
    parser.add_argument("--ppo", nargs=2, metavar=("ENV", "GPU"),
                        help="Brax PPO's campaign on ENV at the marks, alone: its longest on the GPU model named "
                             "(H100, H200), else its longest on any (its machine is printed)")
    args = parser.parse_args(argv)
    if args.ppo and (args.runs or args.out):
        parser.error("--ppo prints Brax PPO's campaign alone: give it without --runs and --out")
    if args.ppo:
        env, runs = args.ppo[0], campaign(args.ppo[0], args.ppo[1].upper())  # the model as machines name it
        if not runs:
            print(f"{env}: no Brax PPO campaign on record")
            return 0
        print("\n".join([f"{env}: Brax PPO's {runs[0]['budget_s']:.0f} s campaign, {runs[0].get('machine', 'a GPU')}",
                         *at_marks(runs)]))
        return 0
    if not (args.runs and args.out):
        parser.error("give --runs and --out, or --ppo")
    for path in args.runs:
        print("\n".join(summary(curves.load_run(path))))
    print(f"wrote {draw(args.runs, args.out)}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
