"""The window study and the side-by-side with Brax APG and PPO: tables with intervals and curves from the records.

Reads the records `stablebptt_half.py`, `apg_baseline.py` and `ppo_baseline.py` wrote (one JSON per
run), keeps of each what the report uses (`--raw`: trimmed, the per-update logs left out, into
`OUT/records.json`, which a later call adds to), and writes `OUT/window_study.md` (the tables) and
one figure per env, `OUT/window_study_<env>.png` (the mean return of each method with a band, against
training wall time and against env steps).

  python benchmarks/envs_vs_apg/window_study.py --raw DIR [DIR ...] --out results/envs/episodes
  python benchmarks/envs_vs_apg/window_study.py --raw DIR --sharing 5 --out ...  # seeds_together.sh's runs
  python benchmarks/envs_vs_apg/window_study.py --cut-logs LOG [LOG ...] --sharing 5 --budget 360 --out ...
  python benchmarks/envs_vs_apg/window_study.py --out results/envs/episodes     # from OUT/records.json again

`--cut-logs` takes the log of a Brax baseline's run that the call's time limit cut before it wrote
its record, and keeps what the log's lines say (its evaluations) as a record of status "cut".
`--sharing N` marks the records read by this call as runs of N seeds at once on one GPU
(`seeds_together.sh`), as stablebptt's N seeds share theirs in one program.

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
import re

import numpy as np

KEEP_STABLEBPTT = ("env", "mode", "seeds", "budget_s", "hyperparams", "device", "jax", "points", "status", "compile_s",
                   "setup_s", "update_compile_s", "setup_phases_s",
                   "nan_update_per_seed", "zeroed_updates_per_seed", "updates", "update_s", "env_steps_per_s_per_seed",
                   "final_return_per_seed", "best_return_per_seed", "argv", "machine")
KEEP_BRAX = ("env", "seed", "algo", "variant", "budget_s", "hyperparams", "device", "jax", "points", "status", "compile_s",
             "updates_per_epoch", "update_s", "env_steps_per_s", "final_return", "best_return", "argv", "sharing", "error_type", "error",
             "machine")
RESAMPLES = 10_000
DEFAULT_BATCH = 64  # stablebptt_half.py's states per seed, left out of a method's name
# The time at which the methods of an env are compared side by side: each seed's last evaluation at
# or before it, or when its budget ran out where that budget is this time. Per env, the budget of the
# study's runs there (stablebptt's longer runs on the locomotion envs were evaluated every 150 s or so).
EQUAL_TIME_S = {"CartpoleSwingup": 240.0, "AcrobotSwingup": 240.0, "CheetahRun": 320.0, "WalkerWalk": 285.0,
                "WalkerStand": 300.0}
BRAX_NAMES = {"brax_apg": "Brax APG", "brax_ppo": "Brax PPO"}


def trim(record: dict) -> dict:
    keep = KEEP_BRAX if "seed" in record else KEEP_STABLEBPTT
    kept = {key: record[key] for key in keep if key in record}
    if "error" in kept:
        kept["error"] = kept["error"][:160]
    return kept


def method(record: dict) -> str:
    if "seed" in record:
        variant = record.get("variant", "shipped")
        sharing = record.get("sharing", 1)
        return (BRAX_NAMES[record.get("algo", "brax_apg")] + (f" ({variant})" if variant != "shipped" else "")
                + (f", {sharing} seeds sharing a GPU" if sharing > 1 else ""))
    options = record["hyperparams"]
    name = ", ".join([f"stablebptt {record['mode']}, window {options['horizon']}", *option_words(options)])
    return name + (f", seeds {record['seeds'][0]}-{record['seeds'][-1]}" if record["seeds"][0] != 0 else "")


# A stablebptt run's options beyond stablebptt_half.py's defaults (its window aside): the option, its
# default, the option in words (a method's name, a suite row's setting) and its tag in a record's key.
OPTIONS = (
    ("dense_reward", False, lambda value: "dense reward", lambda value: "_dense"),
    ("critic", False, lambda value: "critic", lambda value: "_critic"),
    ("discount", 1.0, lambda value: f"discount {value:g}", lambda value: f"_d{value:g}"),
    ("action_noise", 0.0, lambda value: f"action noise {value:g}", lambda value: f"_noise{value:g}"),
    ("lr_decay", 1.0, lambda value: f"lr decay {value:g}", lambda value: f"_decay{value:g}"),
    ("normalize_observations", False, lambda value: "normalised observations", lambda value: "_norm"),
    ("nonfinite_flows", "stop", lambda value: "non-finite flows zeroed", lambda value: "_zeroed"),
    ("smoothing_scale", 1.0, lambda value: f"smoothing scale {value:g}", lambda value: f"_smoothing{value:g}"),
    ("batch", DEFAULT_BATCH, lambda value: f"{value} states per seed", lambda value: f"_b{value}"),
)


def _given(options: dict) -> list:
    """The options of ``OPTIONS`` that a run set to other than their default, with their values."""
    return [(option, options[option[0]]) for option in OPTIONS if options.get(option[0], option[1]) != option[1]]


def option_words(options: dict) -> list[str]:
    """A stablebptt run's options beyond stablebptt_half.py's defaults, in words (its window aside)."""
    return [words(value) for (_, _, words, _), value in _given(options)]


def record_name(record: dict) -> str:
    """The record's key in records.json: one per stablebptt run (its seeds inside), one per Brax seed."""
    if "seed" in record:
        algo = {"brax_apg": "apg", "brax_ppo": "ppo"}[record.get("algo", "brax_apg")]
        variant = record.get("variant", "shipped")
        return f"{record['env']}_{algo}{'' if variant == 'shipped' else '_' + variant}_s{record['seed']}"
    options = record["hyperparams"]
    return (f"{record['env']}_{record['mode']}_w{options['horizon']}"
            + "".join(tag(value) for (_, _, _, tag), value in _given(options))
            + (f"_seeds{record['seeds'][0]}" if record["seeds"][0] != 0 else ""))


def record_from_log(path: str, budget: float) -> list[dict]:
    """The evaluations a Brax baseline's log printed, as records (one per seed) of a run cut before its end."""
    import re
    pattern = re.compile(r"\[(\w+)/(\w+)/s(\d+)\] t=\s*([\d.]+)s ep=(\d+) steps=(\d+) return=(\S+)")
    header = re.compile(r"^jax (\S+) devices .*? (\w+) hp (\{.*\})$")
    records: dict = {}
    options, version = {}, ""
    for line in open(path):
        found = header.match(line.strip())
        if found:
            import ast
            version, options = found.group(1), ast.literal_eval(found.group(3))
            continue
        found = pattern.search(line)
        if not found:
            continue
        env, label, seed = found.group(1), found.group(2), int(found.group(3))
        algo = "brax_ppo" if label == "brax_ppo" else "brax_apg"
        record = records.setdefault(seed, {"env": env, "seed": seed, "algo": algo, "variant": "shipped" if algo == "brax_ppo"
                                           else label, "budget_s": budget, "hyperparams": options, "jax": version,
                                           "device": "cuda:0", "points": [], "status": "cut", "compile_s": float("nan"),
                                           "update_s": float("nan"), "env_steps_per_s": float("nan"),
                                           "argv": [f"(from the log {os.path.basename(path)})"]})
        record["points"].append({"train_wall_s": float(found.group(4)), "epoch": int(found.group(5)),
                                 "env_steps": int(found.group(6)), "return": float(found.group(7))})
    for record in records.values():
        returns = [p["return"] for p in record["points"]]
        record["final_return"], record["best_return"] = returns[-1], max(returns)
    return list(records.values())


def at_time(curve: list, seconds: float) -> tuple[float, float, float] | None:
    """A seed's last evaluation at or before ``seconds`` of training: (time, env steps, return)."""
    before = [point for point in curve if point[0] <= seconds]
    return before[-1] if before else None


def runs(records: list[dict]) -> dict:
    """(env, method) -> one entry: final and best returns per seed, the curve, throughput and compile time.
    APG's seeds, one run each, are joined into one entry."""
    joined: dict = {}
    for record in records:
        key = (record["env"], method(record))
        entry = joined.setdefault(key, {"final": [], "best": [], "curves": [], "compile_s": [], "update_ms": [],
                                        "steps_per_s": [], "diverged": 0, "updates": [], "argv": [], "device": set(),
                                        "ended": [], "machine": set()})
        entry["ended"].append(record["status"] if record["status"] != "error" else
                              f"error ({record.get('error', '')[:90]})")
        entry["device"].add(record["device"])
        entry["machine"].add(record.get("machine", "-"))
        entry["budget_s"] = record["budget_s"]
        entry["argv"].append(" ".join(record["argv"]).replace("/tmp/", "DIR/"))
        entry["compile_s"].append(record["compile_s"] if record.get("compile_s") is not None else float("nan"))
        entry["update_ms"].append(1e3 * record["update_s"] if record.get("update_s") is not None else float("nan"))
        if "seed" in record:
            entry["final"].append(record["final_return"])
            entry["best"].append(record["best_return"])
            entry["steps_per_s"].append(record["env_steps_per_s"] if record.get("env_steps_per_s") is not None
                                        else float("nan"))
            entry["updates"].append(record["points"][-1].get("updates", record["points"][-1]["epoch"]))
            entry["diverged"] += record["status"] == "nan"
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


def method_order(key: tuple[str, str]) -> tuple:
    """Env, then the Brax baselines, then stablebptt's runs by window (as a number), flow and options."""
    env, name = key
    window = re.search(r"window (\d+)", name)
    return env, name.startswith("stablebptt"), int(window.group(1)) if window else 0, name


def tables(joined: dict) -> list[str]:
    lines = ["| env | method | budget s | seeds | final return | 95% interval | best return | updates | compile s | update ms "
             "| env steps/s per seed | diverged seeds | machine |", "|---|---|---:|---:|---:|---|---:|---:|---:|---:|---:|---:|---|"]
    for key in sorted(joined, key=method_order):
        e = joined[key]
        low, high = interval(e["final"])
        lines.append(f"| {key[0]} | {key[1]} | {e['budget_s']:.0f} | {len(e['final'])} | {_number(np.mean(e['final']))} | "
                     f"[{_number(low)}, {_number(high)}] | {_number(np.mean(e['best']))} | "
                     f"{int(np.mean(e['updates']))} | {_number(np.mean(e['compile_s']), 0)} | "
                     f"{_number(np.median(e['update_ms']), 1)} | {_number(np.mean(e['steps_per_s']), 0)} | "
                     f"{e['diverged']} | {'; '.join(sorted(e['machine']))} |")
    lines += ["", "C - R, final return, per env and window (95% bootstrap interval; the sign is the verdict only where "
              "the interval excludes 0):", "", "| env | window | C - R | 95% interval | verdict |", "|---|---:|---:|---|---|"]
    for env, name in sorted(joined, key=method_order):
        if not name.startswith("stablebptt C"):
            continue
        other = (env, name.replace("stablebptt C", "stablebptt R"))
        if other not in joined:
            continue
        mean, low, high = difference_interval(joined[(env, name)]["final"], joined[other]["final"])
        verdict = "C higher" if low > 0 else "R higher" if high < 0 else "no separation"
        diverged = [f"{flow} diverged in {count} of {len(joined[key]['final'])} seeds" for flow, key in
                    (("C", (env, name)), ("R", other)) if (count := int(np.sum(~np.isfinite(joined[key]["final"]))))]
        if diverged:  # a seed without a finite return has no difference: say what happened instead
            verdict = ", ".join(diverged) + (", the other finite in all" if len(diverged) == 1 else "")
        lines.append(f"| {env} | {name.split('window ', 1)[1]} | {_number(mean)} | [{_number(low)}, {_number(high)}] | "
                     f"{verdict} |")
    return lines


def side_by_side(joined: dict) -> list[str]:
    """Every method of every env at the same training time, with the env steps each had taken by then."""
    lines = ["| env | method | seeds | at s | return then | 95% interval | evaluated at s (mean) | env steps per seed "
             "by then | how the runs ended |", "|---|---|---:|---:|---:|---|---:|---:|---|"]
    for env, name in sorted(joined, key=method_order):
        entry = joined[(env, name)]
        seconds = EQUAL_TIME_S.get(env)
        if ", seeds " in name or seconds is None:  # the sweep's seeds are kept apart from the reported ones
            continue
        # A run whose budget is the time compared at is scored by its last evaluation, made when the update
        # running at the budget ended (up to one update after it).
        reached = [curve[-1] if entry["budget_s"] == seconds else at_time(curve, seconds) for curve in entry["curves"]]
        reached = [point for point in reached if point is not None]
        returns = [point[2] for point in reached]
        finite = [value for value in returns if math.isfinite(value)]
        low, high = interval(finite)
        ended = ", ".join(f"{entry['ended'].count(status)} {status}" for status in sorted(set(entry["ended"])))
        lines.append(f"| {env} | {name} | {len(reached)} | {seconds:.0f} | {_number(np.mean(finite)) if finite else '-'} | "
                     f"[{_number(low)}, {_number(high)}] | {_number(np.mean([p[0] for p in reached]), 0)} | "
                     f"{_number(np.mean([p[1] for p in reached]), 0)} | {ended} |")
    return lines


def sweep(joined: dict) -> list[str]:
    """The options swept on seeds kept apart from the reported ones, each against the same seeds without it."""
    lines = ["| env | setting | seeds | final return | 95% interval | difference to the setting without options | "
             "95% interval |", "|---|---|---:|---:|---|---:|---|"]
    for env, name in sorted(joined):
        if ", seeds " not in name:
            continue
        base_name = name.split(",")[0] + "," + name.split(",")[1] + "," + name.rsplit(",", 1)[1]
        entry, base = joined[(env, name)], joined.get((env, base_name))
        low, high = interval(entry["final"])
        difference = "| - | - |"
        if base is not None and base_name != name:
            mean, d_low, d_high = difference_interval(entry["final"], base["final"])
            difference = f"| {_number(mean)} | [{_number(d_low)}, {_number(d_high)}] |"
        lines.append(f"| {env} | {name} | {len(entry['final'])} | {_number(np.mean(entry['final']))} | "
                     f"[{_number(low)}, {_number(high)}] {difference}")
    return lines


def throughput(timed: list[dict], records: list[dict]) -> list[str]:
    """The update at APG's window and env count: stablebptt's throughput-only runs beside APG's training runs."""
    if not timed:
        return []
    lines = ["One update at Brax APG's defaults (window 32, one env, one seed), forward and backward, on the same "
             "machine:", "", "| env | method | update ms | env steps/s | command |", "|---|---|---:|---:|---|"]
    for record in records:  # APG's own runs at its defaults, each seed alone on its GPU
        if "seed" in record and record.get("algo", "brax_apg") == "brax_apg" and record.get("sharing", 1) == 1:
            lines.append(f"| {record['env']} | Brax APG (seed {record['seed']}, timed while training) | "
                         f"{1e3 * record['update_s']:.1f} | {record['env_steps_per_s']:.0f} | apg_baseline.py |")
    for record in timed:
        command = " ".join(record["argv"]).replace("/tmp/", "DIR/")
        lines.append(f"| {record['env']} | stablebptt {record['mode']} | {1e3 * record['update_s']:.1f} | "
                     f"{record['env_steps_per_s']:.0f} | `{command}` |")
    return lines


def band(curves: list, column: int, grid: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean over seeds of each seed's last evaluation at or before every grid value of ``column`` (time or env
    steps), where every seed has one, with the 95% bootstrap interval of the mean."""
    values = []
    for curve in curves:
        points = np.array(curve, float)
        order = np.searchsorted(points[:, column], grid, side="right") - 1
        seed = np.where((order >= 0) & (grid <= points[-1, column]), points[np.clip(order, 0, None), 2], np.nan)
        values.append(seed)
    values = np.array(values)
    defined = np.all(np.isfinite(values), axis=0)
    means = np.full(grid.shape, np.nan)
    low, high = means.copy(), means.copy()
    rng = np.random.default_rng(0)
    for index in np.flatnonzero(defined):
        column_values = values[:, index]
        means[index] = column_values.mean()
        if len(column_values) > 1:
            resampled = rng.choice(column_values, (1000, len(column_values))).mean(axis=1)
            low[index], high[index] = np.percentile(resampled, [2.5, 97.5])
    return means, low, high


def figure(joined: dict, env: str, path: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(13, 5))
    names = sorted((name for e, name in joined if e == env and ", seeds " not in name),
                   key=lambda name: method_order((env, name)))
    colors = plt.get_cmap("tab10")
    for index, name in enumerate(names):
        curves = [curve for curve in joined[(env, name)]["curves"] if len(curve) > 1]
        if not curves:  # runs that never finished an update (an error) draw nothing
            continue
        for axis, column in zip(axes, (0, 1)):
            ends = [np.array(curve, float)[:, column] for curve in curves]
            start = max(e[e > 0].min() if column == 1 else e.min() for e in ends)
            stop = max(e.max() for e in ends)
            grid = np.geomspace(start, stop, 200) if column == 1 else np.linspace(start, stop, 200)
            means, low, high = band(curves, column, grid)
            style = "--" if name.startswith("Brax") else "-"
            axis.plot(grid, means, style, color=colors(index % 10), label=f"{name} ({len(curves)} seeds)", linewidth=1.4)
            axis.fill_between(grid, low, high, color=colors(index % 10), alpha=0.15)
    axes[0].set_xlabel("training wall time, s (compile included, evaluation off the clock)")
    axes[1].set_xlabel("env steps per seed")
    axes[1].set_xscale("log")
    for axis in axes:
        axis.set_ylabel("episode return (64 resets, deterministic policy)")
        axis.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.suptitle(f"{env}: mean episode return over seeds with its 95% bootstrap band")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--raw", nargs="*", default=[], help="folders holding the runs' records (searched below)")
    parser.add_argument("--out", required=True)
    parser.add_argument("--machine", default="", help="the machine the records read now came from, in words (a record "
                        "says only cuda:N); kept with each record")
    parser.add_argument("--sharing", type=int, default=1, help="seeds run at once on one GPU in the runs read now")
    parser.add_argument("--cut-logs", nargs="*", default=[], help="logs of Brax runs cut before they wrote a record")
    parser.add_argument("--budget", type=float, default=0.0, help="the budget the cut runs were given, s")
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
            if "seed" in record:
                record["sharing"] = args.sharing
            stored[record_name(record)] = trim(record) | ({"machine": args.machine} if args.machine else {})
    for path in args.cut_logs:
        for record in record_from_log(path, args.budget):
            record["sharing"] = args.sharing
            stored[record_name(record)] = trim(record) | ({"machine": args.machine} if args.machine else {})
    with open(kept, "w") as handle:
        json.dump(dict(sorted(stored.items())), handle, indent=0)
    records = [record for name, record in stored.items() if not name.startswith("throughput_")]
    timed = [record for name, record in stored.items() if name.startswith("throughput_")]
    joined = runs(records)
    lines = ["# Windows along carried episodes: stablebptt R and C against Brax APG and Brax PPO", "",
             f"Written by `python benchmarks/envs_vs_apg/window_study.py --out {args.out}` from the records in `{kept}`; "
             "each run's machine is in the table of every run at its budget.", "",
             "## Side by side at equal training time (compile included)", "",
             *side_by_side(joined), "", "## Every run at its budget", "", *tables(joined), "",
             "## Options swept on seeds kept apart from the reported ones", "", *sweep(joined), "",
             *throughput(timed, records), "", "Commands (DIR: the call's folder; a Brax method marked \"N seeds sharing a GPU\" ran its seeds' commands at "
             "once through `benchmarks/envs_vs_apg/seeds_together.sh N LOGS 'COMMAND'`, each env's on a GPU of its own "
             "through `benchmarks/envs_vs_apg/on_gpus.sh`):", ""]
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
