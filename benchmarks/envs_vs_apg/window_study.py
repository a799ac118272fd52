"""The window study and the side-by-side with Brax APG: tables with intervals and curves from the records.

Reads the records `stablebptt_half.py` and `apg_baseline.py` wrote (one JSON per run), keeps of each
what the report uses (`--raw`: trimmed, the per-update logs left out, into `OUT/records.json`, which
a later call adds to), and writes
`OUT/window_study.md` (the tables) and one figure per env, `OUT/window_study_<env>.png` (the return
against training wall time and against env steps).

  python benchmarks/envs_vs_apg/window_study.py --raw DIR [DIR ...] --out results/envs/episodes
  python benchmarks/envs_vs_apg/window_study.py --out results/envs/episodes     # from OUT/records.json again

Every return is `evaluation.py`'s: 64 fixed resets, 1000 steps, the deterministic policy, off the
training clock. "Final" is the policy when the budget ran out, "best" each seed's best evaluation.
Intervals: 95% percentile bootstrap over seeds (10,000 resamples); for C - R the seeds of each side
are resampled apart.
"""
from __future__ import annotations

import argparse
import glob
import json
import math
import os

import numpy as np

KEEP_STABLEBPTT = ("env", "mode", "seeds", "budget_s", "hyperparams", "device", "jax", "points", "status", "compile_s",
                   "nan_update_per_seed", "updates", "update_s", "env_steps_per_s_per_seed",
                   "final_return_per_seed", "best_return_per_seed", "argv")
KEEP_APG = ("env", "seed", "budget_s", "hyperparams", "device", "jax", "points", "status", "compile_s", "updates_per_epoch",
            "update_s", "env_steps_per_s", "final_return", "best_return", "argv")
RESAMPLES = 10_000


def trim(record: dict) -> dict:
    keep = KEEP_APG if "seed" in record else KEEP_STABLEBPTT
    return {key: record[key] for key in keep if key in record}


def method(record: dict) -> str:
    if "seed" in record:
        return "Brax APG"
    critic = ", critic" if record["hyperparams"].get("critic") else ""
    discount = record["hyperparams"].get("discount", 1.0)
    return f"stablebptt {record['mode']}, window {record['hyperparams']['horizon']}{critic}" + \
        (f", discount {discount:g}" if discount != 1.0 else "")


def runs(records: list[dict]) -> dict:
    """(env, method) -> one entry: final and best returns per seed, the curve, throughput and compile time.
    APG's seeds, one run each, are joined into one entry."""
    joined: dict = {}
    for record in records:
        key = (record["env"], method(record))
        entry = joined.setdefault(key, {"final": [], "best": [], "curves": [], "compile_s": [], "update_ms": [],
                                        "steps_per_s": [], "diverged": 0, "updates": [], "argv": [], "device": set()})
        entry["device"].add(record["device"])
        entry["budget_s"] = record["budget_s"]
        entry["argv"].append(" ".join(record["argv"]).replace("/tmp/", "DIR/"))
        entry["compile_s"].append(record["compile_s"])
        entry["update_ms"].append(1e3 * record["update_s"])
        if "seed" in record:
            entry["final"].append(record["final_return"])
            entry["best"].append(record["best_return"])
            entry["steps_per_s"].append(record["env_steps_per_s"])
            entry["updates"].append(record["points"][-1]["updates"])
            entry["curves"].append([(p["train_wall_s"], p["env_steps"], p["return"]) for p in record["points"]])
        else:
            entry["final"] += record["final_return_per_seed"]
            entry["best"] += record["best_return_per_seed"]
            entry["steps_per_s"].append(record["env_steps_per_s_per_seed"])
            entry["updates"].append(record["updates"])
            entry["diverged"] += sum(n is not None for n in record["nan_update_per_seed"])
            for seed in range(len(record["seeds"])):
                entry["curves"].append([(p["train_wall_s"], p["env_steps_per_seed"], p["return_per_seed"][seed])
                                        for p in record["points"]])
    return joined


def interval(values, resamples: int = RESAMPLES, seed: int = 0) -> tuple[float, float]:
    values = np.asarray(values, float)
    if len(values) < 2:
        return float("nan"), float("nan")
    means = np.random.default_rng(seed).choice(values, (resamples, len(values))).mean(axis=1)
    return tuple(np.percentile(means, [2.5, 97.5]))


def difference_interval(a, b, resamples: int = RESAMPLES, seed: int = 0) -> tuple[float, float, float]:
    """Mean of a - mean of b, with a 95% bootstrap interval, each side's seeds resampled apart."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    rng = np.random.default_rng(seed)
    diffs = rng.choice(a, (resamples, len(a))).mean(axis=1) - rng.choice(b, (resamples, len(b))).mean(axis=1)
    low, high = np.percentile(diffs, [2.5, 97.5])
    return float(a.mean() - b.mean()), float(low), float(high)


def _number(value: float, digits: int = 1) -> str:
    return "-" if value is None or not math.isfinite(value) else f"{value:.{digits}f}"


def tables(joined: dict) -> list[str]:
    lines = ["| env | method | budget s | seeds | final return | 95% interval | best return | updates | compile s | update ms "
             "| env steps/s per seed | diverged seeds |", "|---|---|---:|---:|---:|---|---:|---:|---:|---:|---:|---:|"]
    order = lambda key: (key[0], key[1].startswith("stablebptt"), key[1])  # noqa: E731
    for key in sorted(joined, key=order):
        e = joined[key]
        low, high = interval(e["final"])
        lines.append(f"| {key[0]} | {key[1]} | {e['budget_s']:.0f} | {len(e['final'])} | {_number(np.mean(e['final']))} | "
                     f"[{_number(low)}, {_number(high)}] | {_number(np.mean(e['best']))} | "
                     f"{int(np.mean(e['updates']))} | {_number(np.mean(e['compile_s']), 0)} | "
                     f"{_number(np.median(e['update_ms']), 1)} | {_number(np.mean(e['steps_per_s']), 0)} | "
                     f"{e['diverged']} |")
    lines += ["", "C - R, final return, per env and window (95% bootstrap interval; the sign is the verdict only where "
              "the interval excludes 0):", "", "| env | window | C - R | 95% interval | verdict |", "|---|---:|---:|---|---|"]
    for env, name in sorted(joined):
        if not name.startswith("stablebptt C"):
            continue
        other = (env, name.replace("stablebptt C", "stablebptt R"))
        if other not in joined:
            continue
        mean, low, high = difference_interval(joined[(env, name)]["final"], joined[other]["final"])
        verdict = "C higher" if low > 0 else "R higher" if high < 0 else "no separation"
        lines.append(f"| {env} | {name.rsplit(' ', 1)[1]} | {_number(mean)} | [{_number(low)}, {_number(high)}] | "
                     f"{verdict} |")
    return lines


def throughput(timed: list[dict], records: list[dict]) -> list[str]:
    """The update at APG's window and env count: stablebptt's throughput-only runs beside APG's training runs."""
    if not timed:
        return []
    lines = ["One update at Brax APG's defaults (window 32, one env, one seed), forward and backward, on the same "
             "machine:", "", "| env | method | update ms | env steps/s | command |", "|---|---|---:|---:|---|"]
    for record in records:
        if "seed" in record:
            lines.append(f"| {record['env']} | Brax APG (seed {record['seed']}, timed while training) | "
                         f"{1e3 * record['update_s']:.1f} | {record['env_steps_per_s']:.0f} | apg_baseline.py |")
    for record in timed:
        command = " ".join(record["argv"]).replace("/tmp/", "DIR/")
        lines.append(f"| {record['env']} | stablebptt {record['mode']} | {1e3 * record['update_s']:.1f} | "
                     f"{record['env_steps_per_s']:.0f} | `{command}` |")
    return lines


def figure(joined: dict, env: str, path: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    names = sorted(name for e, name in joined if e == env)
    colors = plt.get_cmap("tab10")
    for index, name in enumerate(names):
        curves = joined[(env, name)]["curves"]
        for axis, column in zip(axes, (0, 1)):
            for number, curve in enumerate(curves):
                points = np.array(curve, float)
                if column == 1:  # a log axis: the initial policy (no env step yet) is the left panel's first point
                    points = points[points[:, 1] > 0]
                axis.plot(points[:, column], points[:, 2], color=colors(index), alpha=0.35 if len(curves) > 1 else 1,
                          label=name if number == 0 else None, linewidth=1.2)
    axes[0].set_xlabel("training wall time, s (compile included, evaluation off the clock)")
    axes[1].set_xlabel("env steps per seed")
    axes[1].set_xscale("log")
    for axis in axes:
        axis.set_ylabel("episode return (64 resets, deterministic policy)")
        axis.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    others = " and Brax APG" if any(name == "Brax APG" for name in names) else ""
    fig.suptitle(f"{env}: episode return of every seed, stablebptt's windows along carried episodes{others}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--raw", nargs="*", default=[], help="folders holding the runs' records (searched below)")
    parser.add_argument("--out", required=True)
    parser.add_argument("--machine", default="", help="the GPUs the records came from, in words (the records say cuda:N)")
    args = parser.parse_args(argv)
    kept = os.path.join(args.out, "records.json")
    os.makedirs(args.out, exist_ok=True)
    stored = json.load(open(kept)) if os.path.exists(kept) else {}  # name -> trimmed record
    for folder in args.raw:
        for path in glob.glob(os.path.join(folder, "**", "*.json"), recursive=True):
            record = json.load(open(path))
            if isinstance(record, list) and record and "update_times_s" in record[0]:  # throughput-only records
                first = record[0]
                stored[f"throughput_{first['env']}_{first['mode']}_w{first['horizon']}_b{first['batch']}"] = first
                continue
            if not isinstance(record, dict) or "points" not in record:
                continue  # summaries
            name = (f"{record['env']}_apg_s{record['seed']}" if "seed" in record else
                    f"{record['env']}_{record['mode']}_w{record['hyperparams']['horizon']}"
                    + ("_critic" if record["hyperparams"].get("critic") else "")
                    + (f"_d{record['hyperparams']['discount']:g}" if record["hyperparams"].get("discount", 1.0) != 1.0 else ""))
            stored[name] = trim(record)
    with open(kept, "w") as handle:
        json.dump(dict(sorted(stored.items())), handle, indent=0)
    records = [record for name, record in stored.items() if not name.startswith("throughput_")]
    timed = [record for name, record in stored.items() if name.startswith("throughput_")]
    joined = runs(records)
    machine = f" --machine '{args.machine}'" if args.machine else ""
    lines = ["# Windows along carried episodes: stablebptt R and C against Brax APG", "",
             f"Written by `python benchmarks/envs_vs_apg/window_study.py --out {args.out}{machine}` from the records in "
             f"`{kept}`{' (' + args.machine + ')' if args.machine else ''}.", "", *tables(joined), "",
             *throughput(timed, records), "", "Commands (DIR: the call's folder):", ""]
    for key in sorted(joined):
        lines += [f"- {key[0]}, {key[1]}: " + "; ".join(f"`{command}`" for command in sorted(set(joined[key]['argv'])))]
    for env in sorted({env for env, _ in joined}):
        path = os.path.join(args.out, f"window_study_{env}.png")
        figure(joined, env, path)
        lines += ["", f"![{env}](window_study_{env}.png)"]
    with open(os.path.join(args.out, "window_study.md"), "w") as handle:
        handle.write("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
