"""The locomotion recipe beside Brax PPO across envs, at one mark of the wall clock, aggregated as the
field reports RL benchmarks (Agarwal et al., "Deep RL at the Edge of the Statistical Precipice", with
their library rliable).

Per env, the run of the recipe as it stands (`stablebptt train --env E --recipe locomotion --seeds 5`: the
reported seeds, a wall-clock budget, its first start from an empty compile cache; the latest such run in
OUT/records.json, as suite_table.py keeps them) and Brax PPO's runs that evaluated near the mark
(results/envs/baselines/ppo.json; of one budget, the campaign on the GPU model the run trained on first). Each
seed's return by the mark is divided by the env's largest return, 1000 (each suite env's reward lies in [0, 1]
a step, its episodes 1000 steps). Over the envs both have: the interquartile mean, the mean and the median of
those scores, each with a 95% stratified bootstrap interval (seeds drawn again within each env), and the
probability that a seed of ours scores above one of PPO's on an env drawn at random, with its interval. A run
made with other options, or before the recipe last changed, is not the recipe's: envs without its run are
named, not filled from another.

  python benchmarks/envs_vs_apg/aggregate.py --records results/envs/suite --mark 300 --out results/envs/suite/aggregate_300s
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import suite_table  # noqa: E402

from stablebptt.storage import atomic_write  # noqa: E402

RECIPE = "locomotion"
# The envs of the locomotion study (docs/performance.md, "The locomotion study, env by env").
STUDY_ENVS = ("CheetahRun", "WalkerWalk", "WalkerStand", "WalkerRun", "HopperStand", "HopperHop", "FishSwim",
              "HumanoidStand")
SEEDS = 5
MAXIMUM_RETURN = 1000.0  # the suite envs' rewards lie in [0, 1] a step over episodes of 1000 steps
BOOTSTRAP_DRAWS = 20_000
OURS, PPO = "stablebptt", "Brax PPO"


def recipe_command(env: str, recipe: str = RECIPE) -> str:
    """The command suite_table.py writes for a run of ``recipe`` on ``env`` as the recipe now stands, on
    the reported seeds, less its budget."""
    from stablebptt.commands import train as train_command
    _, task_config, train_config, _, _ = train_command.configure(*train_command.parse(
        ["--env", env, "--recipe", recipe, "--seeds", str(SEEDS)]))
    return suite_table.command_of({"task_config": dataclasses.asdict(task_config),
                                   "train": dataclasses.asdict(train_config)})


def recipe_runs(records: list[dict], mark: int, envs: tuple[str, ...] = STUDY_ENVS) -> dict[str, dict]:
    """Per env, the latest run of the recipe as it stands that trained until ``mark`` s: runs of other
    options, of fewer seeds, without a budget or from a warm compile cache are left out. A run whose budget
    ended at the mark comes before one that passed it: the longer run's last evaluation before the mark
    may lie an epoch or more back, where the shorter one's budget placed its last at the mark."""
    chosen = {}
    for env in envs:
        wanted = recipe_command(env)
        runs = [record for record in records if record["env"] == env
                and suite_table.what_trains(record["command"]) == wanted and len(record["seeds"]) >= SEEDS
                and record.get("budget", 0.0) > 0 and suite_table.fresh_start(record)
                and suite_table.by_mark(record, mark) is not None]
        if runs:
            chosen[env] = max(runs, key=lambda run: (suite_table.ended_near(run, mark), run.get("started", "")))
    return chosen


def scores(records: list[dict], mark: int, ppo_near=None) -> tuple[dict, dict[str, str]]:
    """``({"envs": [...], OURS: [seeds, envs], PPO: [seeds, envs], "returns": {OURS: ..., PPO: ...},
    "runs": {env: command}}, missing)``: the returns by ``mark`` over MAXIMUM_RETURN (under "returns", as
    they are), of the envs where both have SEEDS seeds, Brax PPO's from its campaign on the GPU model ours
    ran on where one evaluated near the mark; ``missing``: env -> why it is left out."""
    ours, ppo_near = recipe_runs(records, mark), ppo_near or suite_table.ppo_near
    envs, columns, missing = [], {OURS: [], PPO: []}, {}
    for env in STUDY_ENVS:
        if env not in ours:
            missing[env] = "no run of the recipe as it stands that trained until this mark"
            continue
        theirs = ppo_near(env, mark, card=suite_table.card_of(ours[env].get("device", "")))  # beside ours' GPU first
        if len(theirs) < SEEDS:
            missing[env] = "no Brax PPO campaign whose 5 seeds each evaluated near this mark"
        else:
            envs.append(env)
            columns[OURS].append(np.asarray(suite_table.by_mark(ours[env], mark)[:SEEDS]))
            columns[PPO].append(np.asarray(theirs[:SEEDS]))
    returns = {name: np.stack(column, axis=1) if column else np.zeros((SEEDS, 0)) for name, column in columns.items()}
    normalised = {name: table / MAXIMUM_RETURN for name, table in returns.items()}
    return {"envs": envs, **normalised, "returns": returns, "runs": {env: ours[env]["command"] for env in envs}}, missing


def aggregates(scored: dict, draws: int = BOOTSTRAP_DRAWS, seed: int = 0) -> dict:
    """rliable's point estimates and 95% stratified bootstrap intervals: per method the IQM, mean and
    median of the normalised scores; and P(ours > PPO)."""
    from rliable import library, metrics
    named = {"IQM": metrics.aggregate_iqm, "mean": metrics.aggregate_mean, "median": metrics.aggregate_median}
    all_three = lambda x: np.array([function(x) for function in named.values()])
    pair = {(OURS, PPO): (scored[OURS], scored[PPO])}
    # rliable draws its resamples from NumPy's global generator (its random_state reaches arch alone):
    # seeded here, and given back as it was, so the same records give the same intervals.
    state = np.random.get_state()
    np.random.seed(seed)
    try:
        points, intervals = library.get_interval_estimates({name: scored[name] for name in (OURS, PPO)}, all_three,
                                                           reps=draws)
        improvement, improvement_interval = library.get_interval_estimates(pair, metrics.probability_of_improvement,
                                                                           reps=draws)
    finally:
        np.random.set_state(state)
    result = {name: {metric: (float(points[name][i]), float(intervals[name][0][i]), float(intervals[name][1][i]))
                     for i, metric in enumerate(named)} for name in (OURS, PPO)}
    result["P(ours > PPO)"] = (float(improvement[(OURS, PPO)]), *map(float, np.ravel(improvement_interval[(OURS, PPO)])))
    return result


def report(scored: dict, missing: dict[str, str], summary: dict | None, mark: int, out: str) -> str:
    lines = [f"# The locomotion recipe beside Brax PPO by {mark} s, across envs", "",
             f"Written by `python benchmarks/envs_vs_apg/aggregate.py --mark {mark} --out {out}` (its docstring says how "
             "runs are chosen and scored; Brax PPO's is its campaign on the GPU model the run trained on where one "
             "evaluated near the mark). Returns by the mark, mean over seeds [95% bootstrap interval]; "
             f"scores: returns over {MAXIMUM_RETURN:g}, with 95% stratified bootstrap intervals (rliable).", "",
             "| env | stablebptt | Brax PPO | published PPO | the run |", "|---|---|---|---:|---|"]
    for i, env in enumerate(scored["envs"]):
        ours, theirs = scored["returns"][OURS][:, i], scored["returns"][PPO][:, i]
        lines.append(f"| {env} | {_mean_interval(ours)} | {_mean_interval(theirs)} | {_published(env)} | "
                     f"`{scored['runs'][env]}` |")
    lines += [f"| {env} | - | - | {_published(env)} | {why} |" for env, why in missing.items()]
    if summary is None:
        return "\n".join(lines + ["", "No env has both methods' runs by this mark: nothing to aggregate.", ""])
    lines += ["", f"Over {len(scored['envs'])} envs ({', '.join(scored['envs'])}), {SEEDS} seeds each:", "",
              "| method | IQM | mean | median |", "|---|---|---|---|"]
    for name in (OURS, PPO):
        lines.append(f"| {name} | " + " | ".join(f"{point:.3f} [{low:.3f}, {high:.3f}]"
                                                  for point, low, high in summary[name].values()) + " |")
    point, low, high = summary["P(ours > PPO)"]
    lines += ["", f"P(a seed of stablebptt scores above one of Brax PPO's, on an env drawn at random): "
                  f"{point:.3f} [{low:.3f}, {high:.3f}]", ""]
    return "\n".join(lines)


def draw(summary: dict, envs: list[str], mark: int, out: Path) -> Path:
    """The aggregates as intervals, a panel each, the methods one above the other; and the probability of
    improvement with 0.5 marked."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from stablebptt.reports.plots import render
    metrics = list(summary[OURS])
    # Laid out as render saves it, once matplotlib's own fonts are listed (a layout before warned font by font).
    figure, axes = plt.subplots(1, len(metrics) + 1, figsize=(3.0 * (len(metrics) + 1), 2.2), layout="tight")
    for ax, metric in zip(axes, metrics):
        for row, (name, colour) in enumerate(((PPO, "tab:gray"), (OURS, "tab:blue"))):
            point, low, high = summary[name][metric]
            ax.barh(row, high - low, left=low, height=0.5, color=colour, alpha=0.6)
            ax.plot([point, point], [row - 0.25, row + 0.25], color="black")
        ax.set_yticks([0, 1], [PPO, OURS] if ax is axes[0] else ["", ""])
        ax.set_title(metric)
        ax.set_xlabel("return / 1000")
    point, low, high = summary["P(ours > PPO)"]
    axes[-1].barh(0, high - low, left=low, height=0.5, color="tab:blue", alpha=0.6)
    axes[-1].plot([point, point], [-0.25, 0.25], color="black")
    axes[-1].axvline(0.5, color="tab:gray", linestyle="--")
    axes[-1].set(xlim=(0, 1), yticks=[], title="P(ours > PPO)")
    figure.suptitle(f"By {mark} s over {', '.join(envs)} (95% stratified bootstrap intervals)", fontsize=9)
    return render(figure, out)


def _published(env: str) -> str:
    return str(suite_table.PPO_REFERENCE.get(env, "-"))


def _mean_interval(values) -> str:
    low, high = suite_table.interval(values)
    return f"{np.mean(values):.1f} [{low:.1f}, {high:.1f}]"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--records", default="results/envs/suite", help="the folder of suite_table.py's records.json")
    parser.add_argument("--mark", type=int, default=suite_table.AT_S, choices=suite_table.WALL_CLOCK_MARKS,
                        help="seconds of the wall clock, set-up and compile counted")
    parser.add_argument("--out", required=True, help="OUT.md is written, and OUT.png where there is an aggregate")
    args = parser.parse_args(argv)
    with open(Path(args.records) / "records.json") as handle:
        records = json.load(handle)
    scored, missing = scores(records, args.mark)
    summary = aggregates(scored, BOOTSTRAP_DRAWS) if scored["envs"] else None
    text = report(scored, missing, summary, args.mark, args.out)
    atomic_write(Path(f"{args.out}.md"), text.encode())
    if summary is not None:
        draw(summary, scored["envs"], args.mark, Path(f"{args.out}.png"))
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
