"""The suite table: MuJoCo Playground's envs trained by `stablebptt train`, read from its run folders.

The runs are the product's own commands, one env per GPU (`on_gpus.sh`), each with a wall-clock
budget that counts set-up and compile, seeds batched in one program:

  benchmarks/envs_vs_apg/on_gpus.sh LOGS \
      'stablebptt train --env CartpoleSwingup --critic --discount 0.99 --seeds 5 --budget 300 --no-progress --out RUNS/CartpoleSwingup' \
      'stablebptt train --env CheetahRun --seeds 5 --budget 300 --no-progress --out RUNS/CheetahRun' ...

A run continued by later commands goes on with `stablebptt train --resume RUNS/E --budget S`: its row names
the first command (without its budget) and its starts, and a table of its returns along the wall clock
(every start's set-up and compile counted, as `stablebptt plot --x wall-clock` draws it) follows. This script
reads each run folder (config.json, metrics.csv, startup.json), keeps what the table needs in
`OUT/records.json` (a later call adds to it, a run of the same command replaces its record) and writes
`OUT/suite.md`: per run the command that made it, the final return (the last evaluation: `--test-size`
fresh resets, the deterministic policy, the env's own reward) with a 95% bootstrap interval over
seeds, the first evaluation's, the update's and the start-up's seconds, and Brax PPO's return at its
budget where `results/envs/baselines/ppo.json` has one (Brax's own loop, `ppo_baseline.py`), with
MuJoCo Playground's published PPO return as the reference; then, per env with a reference, its best
command's return by 300 s in runs of 5 seeds or more on the reported seeds (a command run more than
once, whatever its budgets and resumes: its runs' seeds pooled), and how many envs stand at half of it or
more.

  python benchmarks/envs_vs_apg/suite_table.py --runs RUNS/* --out results/envs/suite
  python benchmarks/envs_vs_apg/suite_table.py --out results/envs/suite      # from OUT/records.json again
"""
from __future__ import annotations

import argparse
import collections
import csv
import dataclasses
import functools
import json
import os
import re
from pathlib import Path

import numpy as np

# PPO's returns on MuJoCo Playground's suite envs, read off the reward curves of Figure 7 of its report
# (Zakka et al. 2025, arXiv 2502.08844v1, Appendix A.2: Brax PPO, 60M env steps, 100M for AcrobotSwingup,
# WalkerRun and the swimmer, 5 seeds on one A100). The report gives curves, not numbers: these are
# approximate to the curves' resolution.
PPO_REFERENCE = {"CartpoleBalance": 950, "CartpoleSwingup": 800, "CheetahRun": 850, "WalkerWalk": 960,
                 "WalkerRun": 560, "WalkerStand": 1000, "FingerSpin": 600, "FingerTurnEasy": 950,
                 "FingerTurnHard": 950, "ReacherEasy": 950, "ReacherHard": 950, "PointMass": 900, "FishSwim": 650,
                 "AcrobotSwingup": 220, "HumanoidWalk": 500, "HumanoidRun": 130}
PPO_RUNS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "results", "envs", "baselines",
                        "ppo.json")


def interval(values, draws: int = 10_000, seed: int = 0) -> tuple[float, float]:
    """95% bootstrap interval of the mean of ``values``."""
    values = np.asarray(values, float)
    means = np.random.default_rng(seed).choice(values, (draws, len(values))).mean(axis=1)
    return float(np.percentile(means, 2.5)), float(np.percentile(means, 97.5))


def command_of(record: dict) -> str:
    """The `stablebptt train` command of a run folder's config.json: the options that differ from the
    env's defaults (a budget alone bounds the run: its epochs are not said)."""
    from stablebptt import tasks
    from stablebptt.cli import typed_option
    from stablebptt.commands.train import UNTIL_BUDGET
    from stablebptt.engine.config import TrainConfig
    from stablebptt.tasks.env import Config
    words = ["stablebptt train", f"--env {record['task_config']['env']}"]
    for name, default in ((f.name, f.default) for f in dataclasses.fields(Config) if f.name != "env"):
        value = record["task_config"].get(name, default)
        if value != default:
            words.append(typed_option(name, value))
    defaults = {**{f.name: f.default for f in dataclasses.fields(TrainConfig)}, **tasks.train_defaults("env")}
    for name, default in defaults.items():
        value = record["train"].get(name, default)
        if value != default and not (name == "epochs" and value == UNTIL_BUDGET):
            words.append(typed_option(name, value))
    return " ".join(words)


# The wall-clock marks at which a resumed run's returns are read (its last evaluation by each).
WALL_CLOCK_MARKS = (300, 600, 900)
MARK_WITHIN_S = 15  # how near a mark a run or Brax PPO's evaluation counts as at it


def marks_reached(reached_s: float) -> list[int]:
    """The marks a run (ours or Brax PPO's) that trained until ``reached_s`` s of its clock is read at: those it
    reached within MARK_WITHIN_S. Past them its last evaluation would stand for a time it never trained."""
    return [mark for mark in WALL_CLOCK_MARKS if mark <= reached_s + MARK_WITHIN_S]


def read_run(folder: str) -> dict:
    """What the table keeps of one run folder."""
    from stablebptt.engine.divergence import retired_in
    from stablebptt.engine.metrics import COLUMNS
    from stablebptt.reports.curves import load_run, wall_clock, x_values

    with open(os.path.join(folder, "config.json")) as handle:
        config = json.load(handle)
    with open(os.path.join(folder, "metrics.csv")) as handle:
        rows = [{key: float(value) for key, value in row.items()} for row in csv.DictReader(handle)]
    with open(os.path.join(folder, "startup.json")) as handle:
        starts = json.load(handle)
    seeds = sorted({int(row["seed"]) for row in rows})
    evaluated = sorted({int(row["epoch"]) for row in rows if np.isfinite(row["test_loss"])})
    # A seed stopped apart (a non-finite epoch of its own) has no numbers from then on: it is scored by
    # its last evaluation, not left out (leaving it out would score the seeds that survived).
    returns, last = {}, {}
    for epoch in evaluated:
        for row in rows:
            if row["epoch"] == epoch and np.isfinite(row["test_loss"]):
                last[int(row["seed"])] = -row["test_loss"]
        returns[epoch] = [last[seed] for seed in seeds if seed in last]
    stopped = int(retired_in(np.array([[row[name] for name in COLUMNS] for row in rows]), np.array(seeds)).sum())
    per_seed = [row for row in rows if int(row["seed"]) == seeds[0]]
    train = config["train"]
    steps_per_update = train["batch"] * config["resolved_task"]["horizon_steps"]
    run = load_run(folder)
    # Each epoch's updates from the env steps it trained (a budget's last epoch may be cut short); an epoch
    # whose count did not grow is read as whole.
    whole = config["steps_per_epoch"] // steps_per_update
    updates = [round(steps / steps_per_update) if steps > 0 else whole
               for steps in np.diff(x_values(run, "env-steps")[0], prepend=0.0)]
    clock = dict(zip(run.epochs.tolist(), wall_clock(run).tolist()))
    command = command_of(config)
    last_epoch = int(per_seed[-1]["epoch"])
    budgets = [start.get("budget") for start in starts]
    if len(starts) > 1:  # resumed: the record holds the last start's budget, its starts each one's where recorded
        command = without_budget(command) + (
            f" --budget {budgets[0]:g}, then " + ", then ".join(f"--resume RUN --budget {b:g}" for b in budgets[1:])
            if all(budgets) else f" (resumed: {len(starts)} starts)")
    # Reached as budgeted (its starts' budgets summed; else its wall clock).
    reached = sum(budgets) if all(budgets) else clock[last_epoch]
    along = {str(mark): returns[max(e for e in evaluated if clock[e] <= mark)]
             for mark in marks_reached(reached) if any(clock[e] <= mark for e in evaluated)}
    return {"env": config["task_config"]["env"], "command": command, "started": starts[0].get("started", ""),
            "budget": train.get("budget", 0.0),
            "wall_s": clock[last_epoch], "starts": len(starts), "returns_by_wall_clock": along,
            "seeds": seeds, "epochs": len(per_seed), "updates": int(sum(updates)),
            "update_s": float(np.median([row["seconds"] / count for row, count in zip(per_seed, updates)][1:]
                                        or [per_seed[0]["seconds"] / updates[0]])),
            "train_s": float(sum(row["seconds"] for row in per_seed)),
            "eval_s": float(sum(row["eval_seconds"] for row in per_seed)),
            "first_return": returns[evaluated[0]], "final_return": returns[evaluated[-1]],
            "best_return": float(max(np.mean(values) for values in returns.values())),
            "device": starts[0]["device"],
            "ended": _ended(starts[-1], train.get("budget", 0.0), starts[-1]["seconds_to_training"] + sum(
                row["seconds"] + row["eval_seconds"] for row in per_seed))
            + (f", {stopped} of {len(seeds)} seeds stopped apart (non-finite), each scored by its last evaluation" if stopped else ""),
            "seconds_to_training": starts[0]["seconds_to_training"], "phases": starts[0]["phases"],
            **_from_cache(starts[0]),
            "resumes": [{"seconds_to_training": start["seconds_to_training"], "phases": start["phases"],
                         **_from_cache(start)} for start in starts[1:]]}


def _from_cache(start: dict) -> dict:
    """A start's compile seconds that JAX's persistent cache saved it, where its record measured them."""
    seconds = start.get("compile_seconds_from_cache")
    return {} if seconds is None else {"compile_seconds_from_cache": seconds}


def fresh_start(record: dict) -> bool:
    """Whether a run's first start compiled its programs itself, as on a fresh machine: it loaded at most
    WARM_S seconds of compile from the cache, or its record predates the measure."""
    return record.get("compile_seconds_from_cache", 0.0) <= WARM_S


def without_budget(command: str) -> str:
    words = command.split(" ")
    return " ".join(word for i, word in enumerate(words) if word != "--budget" and (i == 0 or words[i - 1] != "--budget"))


def what_trains(command: str) -> str:
    """A record's command without its budgets and resumes: runs of one recipe given other budgets, or
    resumed past the mark, are reruns of one command (pooled by the mark, not the best of them taken)."""
    return without_budget(command.split(", then ")[0].split(" (resumed: ")[0])


def _ended(start: dict, budget: float, elapsed: float) -> str:
    """How a run's last start ended (``startup.json``); for a record from before it said so, "budget"
    where its start-up, training and evaluations filled 90% of the budget, else "stopped early"; a run
    without a budget that never said how it ended was killed before it could."""
    if "ended" in start:
        ended = start["ended"]
        return ended["status"] + (f" ({ended['message']})" if ended["status"] == "diverged" else "")
    if not budget:
        return "killed"
    return "budget" if elapsed >= 0.9 * budget else f"stopped early, after {elapsed:.0f} s"


@functools.cache  # one read for every row of the table
def _ppo_runs() -> tuple[dict, ...]:
    with open(PPO_RUNS) as handle:
        return tuple(json.load(handle))


def card_of(text: str) -> str:
    """The GPU's model a run's device or a Brax PPO record's machine names ("H100", "H200"); "" where none."""
    match = re.search(r"\b[A-Z]{1,2}\d{3}\b", text or "")  # H100, H200, A100; GH200, GB200
    return match.group(0) if match else ""


def campaign_card(runs: list[dict]) -> str:
    """The GPU model a Brax PPO campaign ran on (its seeds shared one)."""
    return card_of(runs[0].get("machine", ""))


def ppo_campaigns(env: str, card: str = "") -> list[list[dict]]:
    """Brax PPO's runs on ``env`` grouped by the budget they were started with and the GPU they ran on, the
    shortest budget first and, of one budget, the campaign on ``card`` first: each group one campaign of
    seeds that shared a GPU under the same protocol."""
    campaigns = collections.defaultdict(list)
    for run in _ppo_runs():
        if run["env"] == env:
            campaigns[run["budget_s"], card_of(run.get("machine", ""))].append(run)
    return [campaigns[key] for key in sorted(campaigns, key=lambda key: (key[0], key[1] != card, key[1]))]


def ppo_at_budget(env: str, card: str = "") -> str:
    """Brax PPO's final return on ``env`` with its interval over seeds, at each budget its runs reached
    ("; " between campaigns, each named by its GPU where the env's campaigns ran on more than one model);
    "-" without runs. Runs stopped before their budget are left out here."""
    campaigns = ppo_campaigns(env, card)
    several_cards = len({campaign_card(runs) for runs in campaigns}) > 1
    cells = []
    for runs in campaigns:
        finals = [run["final_return"] for run in runs if run["status"] == "budget"]
        if len(finals) == len(runs):
            low, high = interval(finals)
            on = f" on an {campaign_card(runs)}" if several_cards else ""
            cells.append(f"{np.mean(finals):.1f} [{low:.1f}, {high:.1f}] at {runs[0]['budget_s']:.0f} s{on}")
    return "; ".join(cells) or "-"


def ppo_near(env: str, mark: float, within: float = MARK_WITHIN_S, card: str = "") -> list[float]:
    """Brax PPO's return on ``env`` per seed at its evaluation nearest ``mark`` seconds of its wall clock
    (compile included), from the first campaign in ``ppo_campaigns``'s order (``card``'s first) whose
    every seed evaluated within ``within`` s of it; empty where none did."""
    for runs in ppo_campaigns(env, card):
        returns = nearest_returns(runs, mark, within)
        if returns:
            return returns
    return []


def nearest_points(runs: list[dict], mark: float) -> list[dict]:
    """Each run's evaluation nearest ``mark`` s of its wall clock, however far."""
    return [min(run["points"], key=lambda point: abs(point["train_wall_s"] - mark)) for run in runs]


def nearest_returns(runs: list[dict], mark: float, within: float = MARK_WITHIN_S) -> list[float]:
    """Each run's return at its evaluation nearest ``mark`` s of its wall clock; empty unless every run has
    one within ``within`` s of it."""
    nearest = nearest_points(runs, mark)
    if not all(abs(point["train_wall_s"] - mark) <= within for point in nearest):
        return []
    return [point["return"] for point in nearest]


def table(records: list[dict], out: str) -> str:
    lines = ["# MuJoCo Playground's suite envs trained by `stablebptt train`", "",
             f"Written by `python benchmarks/envs_vs_apg/suite_table.py --out {out}` from "
             f"`{out}/records.json`. Each row is one command's run folder; its budget counts set-up "
             "and compile, its seeds train in one program. Returns are the run's own evaluations (fresh resets, "
             "the deterministic policy, the env's reward); Brax PPO ran in Brax's own loop "
             "(`benchmarks/envs_vs_apg/ppo_baseline.py`, 5 seeds sharing one GPU) for the budget named, its runs on "
             "record scored on 64 resets of their own (`evaluation.py` now scores a run on the 16 episodes "
             "`stablebptt train` evaluates on).", "",
             "| command | device | final return [95% interval] | first evaluation | PPO reference | share | "
             "Brax PPO | updates | s per update | s to the first epoch | evaluation's share | ended |",
             "|---|---|---|---:|---:|---:|---|---:|---:|---:|---:|---|"]
    labels = _labels(records)
    for record in _ordered(records):
        final = np.asarray(record["final_return"])
        reference = PPO_REFERENCE.get(record["env"])
        share = f"{final.mean() / reference:.0%}" if reference else "-"
        lines.append(f"| {labels[_run_of(record)]} | {record['device']} | {_with_interval(final)} | "
                     f"{np.mean(record['first_return']):.1f} | {reference or '-'} | {share} | "
                     f"{ppo_at_budget(record['env'], card_of(record['device']))} | {record['updates']} | "
                     f"{record['update_s']:.3f} | "
                     f"{record['seconds_to_training']:.0f} | "
                     f"{record['eval_s'] / (record['train_s'] + record['eval_s']):.0%} | {record['ended']} |")
    resumed = [record for record in records if record.get("starts", 1) > 1]
    if resumed:
        lines += ["", "Resumed runs: the return of the last evaluation by each mark of the wall clock (every start's "
                  "set-up and compile counted; `stablebptt plot RUN --x wall-clock` draws it):", "",
                  "| command | wall clock, s | epochs | " + " | ".join(f"by {mark} s" for mark in WALL_CLOCK_MARKS) + " |",
                  "|---|---:|---:|" + "---|" * len(WALL_CLOCK_MARKS)]
        for record in _ordered(resumed):
            along = record["returns_by_wall_clock"]
            lines.append(f"| {labels[_run_of(record)]} | {record['wall_s']:.0f} | {record['epochs']} | " + " | ".join(
                _with_interval(along[str(mark)]) if str(mark) in along else "-" for mark in WALL_CLOCK_MARKS) + " |")
        for env in sorted({record["env"] for record in resumed}):
            card = card_of(next(record["device"] for record in _ordered(resumed) if record["env"] == env))
            near = [ppo_near(env, mark, card=card) for mark in WALL_CLOCK_MARKS]
            if any(near):
                lines.append(f"| Brax PPO on {env}: each seed's evaluation nearest the mark, within {MARK_WITHIN_S} s | - | - | "
                             + " | ".join(_with_interval(returns) if returns else "-" for returns in near) + " |")
    lines += ["", *against_reference(records)]
    lines += ["", "Start-up, phase by phase (seconds; the run's first start, then each resume where the record "
              "keeps them; `startup.json` in its folder). From the cache: the seconds of compile JAX's persistent "
              "cache saved the start (the programs compiled before on the same machine; - where the record "
              "predates the measure):", "",
              "| command | start | to training | from the cache | " + " | ".join(PHASES) + " |",
              "|---|---|---:|---:|" + "---:|" * len(PHASES)]
    for record in _ordered(records):
        for number, start in enumerate([record] + record.get("resumes", []), 1):
            lines.append(f"| {labels[_run_of(record)]} | {'first' if number == 1 else f'resume {number - 1}'} | "
                         f"{start['seconds_to_training']:.0f} | "
                         + (f"{start['compile_seconds_from_cache']:.0f} | " if "compile_seconds_from_cache" in start else "- | ")
                         + " | ".join(f"{_phase(start['phases'], name):.1f}" for name in PHASES) + " |")
    return "\n".join(lines) + "\n"


HALF = 0.5  # the mark: an env counts where a run stands at half of PPO's reference or more
AT_S = 300  # ... by this mark of the wall clock, set-up and compile counted
MIN_SEEDS = 5  # ... in a run of this many seeds or more
WARM_S = 10.0  # ... whose first start loaded at most this much compile from the cache: PPO's compiles


def reported_seeds(record: dict) -> bool:
    """Whether a run trained the reported seeds (``stablebptt train``'s default ``--seed`` on): a run of
    the tuning seeds (``--seed 100``) chose an option, and its return is not reported against PPO's."""
    from stablebptt.engine.config import TrainConfig
    return bool(record["seeds"]) and record["seeds"][0] == TrainConfig().seed


def by_mark(record: dict, mark: int = AT_S) -> list[float] | None:
    """A run's returns by ``mark`` seconds of its wall clock: read at the mark where the run passed it,
    its final returns where it ended within MARK_WITHIN_S of it in one start; None where it did neither.
    A budget's first epoch runs whatever the start took, so a run's end is its last evaluation's clock
    (``wall_s``), and its budget only in records older than that field."""
    along = record.get("returns_by_wall_clock", {})
    if str(mark) in along:
        return along[str(mark)]
    ended_at_mark = record.get("starts", 1) == 1 and ended_near(record, mark)
    return record["final_return"] if ended_at_mark else None


def ended_near(record: dict, mark: float) -> bool:
    """Whether a run's end (its last evaluation's clock; its budget in records older than that field) lies
    within MARK_WITHIN_S of ``mark`` seconds."""
    return abs(record.get("wall_s", record.get("budget", 0.0)) - mark) <= MARK_WITHIN_S


def first_start(record: dict) -> tuple:
    """What tells a run folder's first start apart: a folder recorded again after a later resume is one run,
    counted once. What that start measured, which every record holds (its start time only the newer ones)."""
    return (record["env"], what_trains(record["command"]), record.get("seconds_to_training"),
            tuple(record.get("first_return") or ()), tuple(record["seeds"]))


def against_reference(records: list[dict]) -> list[str]:
    """Per env with a PPO reference, its best command's mean return by AT_S seconds (runs of MIN_SEEDS seeds
    or more) and that share of the reference; and how many envs stand at HALF of it or more. A command run
    more than once counts once, every run's seeds pooled: a rerun cannot lift an env by luck."""
    pooled = collections.defaultdict(list)  # (env, command) -> each counted run's returns by AT_S
    # Each command's runs pooled in the order of their first starts (records older than that field first, by
    # command), whatever order the records came in: the bootstrap draws by position, so the interval is the
    # records' own, not their file's order. Sorted before a run recorded again after a resume is counted once:
    # the record of its most starts is kept.
    ordered = sorted(records, key=lambda run: (run.get("started", ""), run.get("starts", 1), run["command"]))
    records = list({first_start(record): record for record in ordered}.values())
    for record in records:
        returns = by_mark(record)
        # Only runs given a wall-clock budget: a screen of fixed epochs may have shared its GPU.
        if (record["env"] in PPO_REFERENCE and returns is not None and len(record["seeds"]) >= MIN_SEEDS
                and reported_seeds(record) and fresh_start(record) and record.get("budget", 0.0) > 0):
            pooled[record["env"], what_trains(record["command"])].append(list(returns))
    best = {}
    for (env, command), runs in pooled.items():
        returns = [value for run in runs for value in run]
        mean = float(np.mean(returns))
        if env not in best or mean > best[env][0]:
            best[env] = (mean, returns, runs, command)
    at_half = sorted(env for env, (mean, _, _, _) in best.items() if mean >= HALF * PPO_REFERENCE[env])
    lines = [f"Against MuJoCo Playground's published PPO return, by {AT_S} s of wall clock (set-up and compile "
             f"counted; each env's best command above in runs of {MIN_SEEDS} seeds or more, the reported ones, given a "
             f"wall-clock budget, whose first start compiled its programs, loading at most {WARM_S:g} s of compile from the "
             f"cache; a command run more than once, whatever its budgets and resumes, with its runs' seeds pooled): {len(at_half)} of the {len(PPO_REFERENCE)} "
             f"envs with a reference stand at {HALF:.0%} of it or more" + (f" ({', '.join(at_half)})" if at_half else "") +
             f"; {len(PPO_REFERENCE) - len(best)} have no such run on record.", "",
             f"| env | PPO reference | best by {AT_S} s | share | runs (each one's mean) | command (budgets left out) |",
             "|---|---:|---|---:|---|---|"]
    for env in sorted(best):
        mean, returns, runs, command = best[env]
        each = " / ".join(f"{np.mean(run):.1f}" for run in runs)
        lines.append(f"| {env} | {PPO_REFERENCE[env]} | {_with_interval(returns)} | "
                     f"{mean / PPO_REFERENCE[env]:.0%} | {len(runs)}: {each} | `{command}` |")
    return lines


def _phase(phases: dict, name: str) -> float:
    """A start-up phase's seconds, its parts' included (``trainer set-up: initial states``, ...)."""
    return sum(seconds for part, seconds in phases.items() if part == name or part.startswith(f"{name}: "))


def _with_interval(returns) -> str:
    """The mean of ``returns`` with its 95% bootstrap interval over seeds ("(1 seed)" for one)."""
    if len(returns) == 1:
        return f"{np.mean(returns):.1f} (1 seed)"
    low, high = interval(returns)
    return f"{np.mean(returns):.1f} [{low:.1f}, {high:.1f}]"


PHASES = ("task's build and checks", "trainer set-up", "trace", "compile beside the check", "check's wait",
          "surrogate's trace", "unused compile's wait", "surrogate check's wait", "compile", "evaluation's compile",
          "init")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", nargs="*", default=[], help="run folders of stablebptt train")
    parser.add_argument("--out", required=True)
    args = parser.parse_args(argv)
    os.makedirs(args.out, exist_ok=True)
    path = os.path.join(args.out, "records.json")
    records = {}
    if os.path.exists(path):
        with open(path) as handle:
            records = {_run_of(record): record for record in json.load(handle)}
    for folder in args.runs:
        record = read_run(folder)
        records[_run_of(record)] = record  # the same folder read again replaces its record
    out = os.path.normpath(args.out)
    write(path, json.dumps(sorted(records.values(), key=_run_of), indent=1))
    write(os.path.join(out, "suite.md"), table(list(records.values()), out))


def _run_of(record: dict) -> tuple[str, str]:
    """A record's key: its command and its first start's time, so that a command run again adds a row
    rather than replacing the earlier run's."""
    return record["command"], record.get("started", "")


def _ordered(records: list[dict]) -> list[dict]:
    """The records in the table's order: by env, then command, then first start."""
    return sorted(records, key=lambda record: (record["env"], *_run_of(record)))


def _labels(records: list[dict]) -> dict:
    """Each record's command cell: a command with several runs names each run's first start."""
    runs = collections.Counter(record["command"] for record in records)

    def label(record):
        if runs[record["command"]] == 1:
            return f"`{record['command']}`"
        return f"`{record['command']}` (" + (f"started {record['started']}" if record.get("started") else "an earlier run") + ")"
    return {_run_of(record): label(record) for record in records}


def write(path: str, text: str) -> None:
    """``text`` into ``path`` whole or not at all (a stopped call leaves the records as they were)."""
    from stablebptt.storage import atomic_write
    atomic_write(Path(path), text.encode())


if __name__ == "__main__":
    main()
