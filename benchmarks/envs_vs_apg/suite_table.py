"""The suite table: MuJoCo Playground's DeepMind Control Suite envs trained by stablebptt, in real returns.

Reads the records `stablebptt_half.py` wrote (one per env, its seeds in one program) and writes
`OUT/suite.md`: per env the initial policy's return (its evaluation before the first update), the
final and best return with a 95% bootstrap interval over seeds, MuJoCo Playground's PPO return as the
reference, the final return's share of it, env steps per second per seed and the set-up and compile
time; `OUT/records.json` keeps the records (trimmed as window_study.py trims them), and a later call
adds to it.

  python benchmarks/envs_vs_apg/suite_table.py --raw DIR [DIR ...] --out results/envs/suite
  python benchmarks/envs_vs_apg/suite_table.py --out results/envs/suite      # from OUT/records.json again

The runs, one env per GPU (`on_gpus.sh`), each for the same budget, compile included:

  python benchmarks/envs_vs_apg/stablebptt_half.py --envs E --modes C --seeds 5 --budget 300 \\
      --eval-every 60 --batch 64 --horizon 128 --min-timing-updates 2 --out DIR/E

A flat reward trains on its smooth surrogate (the record's task summary names it); every return here
is the true reward's, scored by evaluation.py. A row's notes say how its env trained where the
evaluations show it: flat since training began (which, below PPO's reference, says where it stopped),
or seeds that fell below half their best; and a row short of the goals (not trained, or below 80% of
PPO's reference) says what to try, each an option of the measured runs that answers how it ran.
"""
from __future__ import annotations

import argparse
import glob
import json
import math
import os

import numpy as np
from window_study import interval, option_words, trim

# PPO's returns on MuJoCo Playground's suite envs, read off the reward curves of Figure 7 of its report
# (Zakka et al. 2025, arXiv 2502.08844v1, Appendix A.2: Brax PPO, 60M env steps, 100M for AcrobotSwingup,
# WalkerRun and the swimmer, 5 seeds on one A100). The report gives curves, not numbers: these are
# approximate to the curves' resolution. Envs without a number here get none.
PPO_REFERENCE = {"CartpoleBalance": 950, "CartpoleSwingup": 800, "CheetahRun": 850, "WalkerWalk": 960,
                 "WalkerRun": 560, "WalkerStand": 1000, "FingerSpin": 600, "FingerTurnEasy": 950,
                 "FingerTurnHard": 950, "ReacherEasy": 950, "ReacherHard": 950, "PointMass": 900, "FishSwim": 650,
                 "AcrobotSwingup": 220, "HumanoidWalk": 500, "HumanoidRun": 130}


def course(record: dict) -> list[str]:
    """What the evaluations say of how an env trained: a plateau (the mean of every evaluation after the
    first update within 5% of the last; at any level, PointMass's 836 too) or seeds that fell (a final
    return below half the seed's best)."""
    returns = np.asarray([point["return_per_seed"] for point in record["points"]], float)  # evaluations x seeds
    means = np.nanmean(returns, axis=1)
    notes = []
    after_first = means[1:]
    if len(after_first) >= 3 and np.all(np.abs(after_first - means[-1]) <= 0.05 * abs(means[-1])):
        notes.append(f"flat from its first evaluation after training began (update {record['points'][1]['updates']})")
    final, best = returns[-1], np.nanmax(returns, axis=0)
    fell = int(np.sum(final < 0.5 * best))
    if fell:
        notes.append(f"{fell} of {returns.shape[1]} seeds ended below half their best")
    return notes


FEW_UPDATES = 200  # below this the row says how many updates the budget left (the envs that trained made 900 or more)


def few_updates(record: dict) -> bool:
    """Whether the budget left few updates after set-up and compile (a run that ended on non-finite
    gradients stopped for that instead)."""
    return record.get("updates", FEW_UPDATES) < FEW_UPDATES and record.get("status") != "nan"


def on_surrogate(record: dict) -> bool:
    """Whether the run trained on its reward's smooth surrogate (its task summary names one)."""
    summary = record.get("task_summary", "")
    return ("smoothed" in summary or "widened" in summary) and not record.get("hyperparams", {}).get("dense_reward")


def setting(record: dict) -> str:
    """How a run trained beyond the table's protocol (C at window 128 on the env's own or surrogate
    reward), in words; "" for the protocol itself. Each setting is a row of its own."""
    options = record.get("hyperparams", {})
    window = [f"window {options['horizon']}"] if options.get("horizon", 128) != 128 else []
    return ", ".join(window + option_words(options))


def labelled(record: dict) -> str:
    """The env, and its run's setting where it has one: a row's label and its key in records.json."""
    return record["env"] + (f" ({setting(record)})" if setting(record) else "")


def standing(record: dict) -> str | None:
    """Where the final return's interval over seeds lies against the initial policy's return: "above",
    "includes" or "below"; None with fewer than two finite seeds."""
    final = np.asarray(record["final_return_per_seed"], float)
    initial = np.asarray(record["points"][0]["return_per_seed"], float)  # the evaluation before the first update
    finite = final[np.isfinite(final)]
    if finite.size < 2:
        return None
    low, high = interval(finite)
    return "above" if low > initial.mean() else "below" if high < initial.mean() else "includes"


def share_of_reference(record: dict) -> float | None:
    """The mean final return over finite seeds as a share of PPO's reference; None without one."""
    final = np.asarray(record["final_return_per_seed"], float)
    reference = PPO_REFERENCE.get(record["env"])
    return float(np.mean(final[np.isfinite(final)])) / reference if reference and np.isfinite(final).any() else None


def goals(records: list[dict]) -> list[str]:
    """The suite's goals, env by env over every row of an env: which envs trained (a row whose final
    interval lies above its initial return) and which reached half and 80% of PPO's reference."""
    envs = sorted({record["env"] for record in records})
    rows_of = {env: [record for record in records if record["env"] == env] for env in envs}
    trained = [env for env in envs if any(standing(record) == "above" for record in rows_of[env])]
    at_protocol = [env for env in envs if any(standing(record) == "above" and not setting(record) for record in rows_of[env])]
    best_share = {env: max((share_of_reference(record) or 0.0) for record in rows_of[env]) for env in envs}
    named = lambda group: ", ".join(group) or "none"  # noqa: E731
    return [f"Trained (a row whose final interval lies above its initial return): {len(trained)} of {len(envs)} envs, "
            f"{len(at_protocol)} of them at the table's own setting (C, window 128). Not trained in any row: "
            f"{named([env for env in envs if env not in trained])}.", "",
            f"At half of PPO's reference or more (any row): {named([env for env in envs if best_share[env] >= 0.5])}; "
            f"within 80% of it: {named([env for env in envs if best_share[env] >= 0.8])}. Without a reference: "
            f"{named([env for env in envs if env not in PPO_REFERENCE])}."]


def levers(record: dict) -> list[str]:
    """What would change a row that is short of the goals (not trained, or below 80% of PPO's reference
    or without one), read from how it ran: each the option of the measured runs that answers it."""
    options = record.get("hyperparams", {})
    share = share_of_reference(record)
    if standing(record) == "above" and share is not None and share >= 0.8:
        return []
    final, best = np.asarray(record["final_return_per_seed"], float), np.asarray(record["best_return_per_seed"], float)
    surrogate, few = on_surrogate(record), few_updates(record)
    updates, ran = record.get("updates", 0), record.get("status") != "nan"
    return [lever for lever, holds in (
        ("a longer budget", few),
        # Slow updates: WalkerStand and WalkerWalk trained further at window 32 than at 128 (the window study).
        ("windows of 32 (a quarter of each update's steps)", ran and updates < 500 and options.get("horizon", 128) > 32),
        # Many updates: the critic lifted CartpoleSwingup and AcrobotSwingup (1100-1200 updates), not the
        # cheetah or the walkers (160-230).
        ("the critic (--critic --discount 0.99)", ran and updates >= 500 and not options.get("critic")),
        ("its dense variant's reward (--dense-reward)", surrogate and record["env"].endswith("Sparse")),
        ("a sharper surrogate (--smoothing-scale below 1)", surrogate and not record["env"].endswith("Sparse") and not few
         and options.get("smoothing_scale", 1.0) == 1.0 and any(note.startswith("flat") for note in course(record))),
        ("--nonfinite-flows zero", any(update is not None for update in record.get("nan_update_per_seed") or [])
         and options.get("nonfinite_flows", "stop") == "stop"),
        # Seeds that fall back from their best: the measured decay kept CartpoleBalance's seeds higher.
        ("a learning-rate decay (--lr-decay)", options.get("lr_decay", 1.0) == 1.0 and not few
         and np.nanmean(final) < 0.85 * np.nanmean(best))) if holds]


def row(record: dict) -> str:
    """One env's line of the table."""
    seeds = record["seeds"]
    final, best = np.asarray(record["final_return_per_seed"], float), np.asarray(record["best_return_per_seed"], float)
    initial = np.asarray(record["points"][0]["return_per_seed"], float)  # the evaluation before the first update
    finite = final[np.isfinite(final)]
    low, high = interval(finite)
    reference = PPO_REFERENCE.get(record["env"])
    share, place, to_try = share_of_reference(record), standing(record), levers(record)
    dense = record.get("hyperparams", {}).get("dense_reward")
    stopped = [update for update in record.get("nan_update_per_seed") or [] if update is not None]
    notes = [note for note, holds in (("trained on its dense variant's reward", dense),
                                      ("trained on its reward's surrogate", on_surrogate(record)),
                                      (f"a non-finite loss or flow gradient on {len(stopped)} of {len(final)} seeds (first at updates "
                                       f"{min(stopped or [0])}-{max(stopped or [0])})"
                                       + ("; the run ended once every seed had met one" if record.get("status") == "nan" else ""),
                                       bool(stopped)),
                                      (f"{len(final) - finite.size} of {len(final)} seeds non-finite", finite.size < len(final)),
                                      (f"final interval {place} the initial return", place is not None),
                                      # Why an env may not have trained: the budget left few updates after set-up and compile.
                                      (f"{record.get('updates')} update{'' if record.get('updates') == 1 else 's'}, after {_number(record.get('compile_s'), 0)} s of the "
                                       f"{record['budget_s']:.0f} s set up and compiling", few_updates(record)))
             if holds] + course(record) + ([f"to try: {', '.join(to_try)}"] if to_try else [])
    steps = record.get("env_steps_per_s_per_seed")
    return (f"| {labelled(record)} | {len(seeds)} | {record['budget_s']:.0f} | {_number(initial.mean())} | "
            f"{_number(finite.mean() if finite.size else float('nan'))} [{_number(low)}, {_number(high)}] | "
            f"{_number(np.nanmean(best))} | {reference or '-'} | {'-' if share is None else f'{100 * share:.0f}%'} | {_number(steps, 0)} | "
            f"{_number(record.get('compile_s'), 0)} | {'; '.join(notes)} |")


def _number(value, digits: int = 1) -> str:
    return "-" if value is None or not math.isfinite(value) else f"{value:.{digits}f}"


def table(records: list[dict]) -> list[str]:
    lines = ["| env | seeds | budget s | initial return | final return [95% interval] | best return | PPO reference | "
             "final / reference | env steps/s per seed | set-up and compile s | notes |",
             "|---|---:|---:|---:|---|---:|---:|---:|---:|---:|---|"]
    return lines + [row(record) for record in sorted(records, key=lambda r: (r["env"], setting(r)))]


PHASES = (("env_task_s", "env checks"), ("make_trainer_s", "trainer set-up"), ("update_trace_s", "update traced"),
          ("diagnosis_wait_s", "diagnosis waited for"), ("surrogate_trace_s", "surrogate's update traced"),
          ("surrogate_check_wait_s", "surrogate's check waited for"), ("update_xla_compile_s", "XLA compile"),
          ("init_s", "init"))


def phases(records: list[dict]) -> list[str]:
    """Where each run's set-up and compile went, phase by phase (stablebptt_half.py's ``setup_phases_s``),
    for the runs that recorded every phase."""
    timed = sorted((record for record in records if "update_xla_compile_s" in record.get("setup_phases_s", {})),
                   key=lambda r: -r["compile_s"])
    if not timed:
        return []
    lines = ["Set-up and compile phase by phase, seconds (the runs that recorded every phase; a dash: a phase the run had no need of):", "",
             "| env | " + " | ".join(name for _, name in PHASES) + " | total |",
             "|---|" + "---:|" * (len(PHASES) + 1)]
    for record in timed:
        spent = record["setup_phases_s"]
        lines.append(f"| {labelled(record)} | " + " | ".join(_number(spent.get(key)) for key, _ in PHASES)
                     + f" | {_number(record['compile_s'])} |")
    return lines + [""]


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--raw", nargs="*", default=[], help="folders holding stablebptt_half.py's records (searched below)")
    parser.add_argument("--out", required=True)
    args = parser.parse_args(argv)
    kept = os.path.join(args.out, "records.json")
    records = json.load(open(kept)) if os.path.exists(kept) else {}
    for folder in args.raw:
        for path in sorted(glob.glob(os.path.join(folder, "**", "*_stablebptt_*.json"), recursive=True)):
            record = json.load(open(path))
            if record.get("status") != "error" and record.get("points"):
                # Another way to train an env is a row of its own.
                records[labelled(record)] = {**trim(record), "task_summary": record.get("task_summary", "")}
    os.makedirs(args.out, exist_ok=True)
    with open(kept, "w") as file:
        json.dump(records, file, indent=1)
    lines = ["# MuJoCo Playground's suite envs trained by stablebptt", "",
             f"Written by `python benchmarks/envs_vs_apg/suite_table.py --out {args.out}` from `{kept}`; every return "
             "is evaluation.py's (64 fixed resets, 1000 steps, the deterministic policy, the true reward). PPO's "
             "references are read from MuJoCo Playground's published learning curves (approximate).", "",
             *table(list(records.values())), "", *goals(list(records.values())), "", *phases(list(records.values()))]
    with open(os.path.join(args.out, "suite.md"), "w") as file:
        file.write("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
