"""Merge the envs-vs-APG records into results/envs/: a JSON and CSV record, a markdown table, one figure per env.

  python benchmarks/envs_vs_apg/report.py --raw RAW --out results/envs

`--raw` holds one folder per machine run, each with the JSON records that apg_baseline.py and
stablebptt_half.py wrote and a CALL.json: {"command": the command line run, "device": ...,
"date": ...}. Every number in the markdown names the command (argv of the script) and the run.
The folders behind the committed tables are in git: `git ls-tree -r fb065bd results/envs/raw`.
"""

from __future__ import annotations

import argparse
import csv
import glob
import json
import math
import os
import statistics
import sys

import numpy as np


def _finite(xs):
    return [x for x in xs if isinstance(x, (int, float)) and math.isfinite(x)]


def _ms(xs):
    """mean ± std (population over seeds) as text."""
    given = [x for x in xs if x is not None]
    xs = _finite(xs)
    if not xs:
        return "NaN" if given else "-"
    if len(xs) == 1:
        return f"{xs[0]:.1f}"
    return f"{statistics.mean(xs):.1f} ± {statistics.pstdev(xs):.1f}"


def _cmd(argv):
    return "python " + " ".join(argv) if argv else "?"


def _apg_label(record):
    """How the call ran APG's seeds on the GPU (CALL.json's "apg_seeds"), where it says."""
    how = record["call"].get("apg_seeds")
    return f", {how}" if how else ""


def load(raw):
    runs, throughput = [], []
    for call_dir in sorted(glob.glob(os.path.join(raw, "*"))):
        if not os.path.isdir(call_dir):
            continue
        call = {}
        if os.path.exists(os.path.join(call_dir, "CALL.json")):
            call = json.load(open(os.path.join(call_dir, "CALL.json")))
        call["name"] = os.path.basename(call_dir)
        for path in sorted(glob.glob(os.path.join(call_dir, "*.json"))):
            name = os.path.basename(path)
            if name in ("CALL.json",) or name.startswith("summary"):
                continue
            data = json.load(open(path))
            if name.startswith("throughput"):
                for r in data if isinstance(data, list) else [data]:
                    r["call"] = call
                    throughput.append(r)
                continue
            data["call"] = call
            data["file"] = os.path.relpath(path, raw)
            runs.append(data)
    return runs, throughput


BUDGET_SLACK_S = 2.0  # an APG epoch (20 updates) ends the run at most about a second past the budget here


def at_budget_return(points, budget):
    """(return, initial_policy) of the policy as it stood at the budget: the last evaluation at a training
    time <= budget + BUDGET_SLACK_S; if none (compile longer than the budget), the initial policy's
    evaluation, whenever it ran (no update had finished by the budget)."""
    within = [p for p in points if p["train_wall_s"] <= budget + BUDGET_SLACK_S]
    if within:
        return within[-1]["return"], within[-1].get("updates", 0) == 0
    first = [p for p in points if p.get("updates", 0) == 0]
    return (first[0]["return"], True) if first else (None, False)


def rows_of(runs):
    """One row per (env, method): APG seeds merged per variant; stablebptt one record per mode."""
    groups = {}
    for r in runs:
        if r.get("throughput_run"):
            continue
        if r.get("algo") == "brax_apg":
            key = (r["env"], f"Brax APG ({r['variant']}{_apg_label(r)})")
        else:
            key = (r["env"], f"stablebptt {r['mode']}")
        groups.setdefault(key, []).append(r)
    rows = []
    for (env, method), recs in sorted(groups.items(), key=lambda kv: (kv[0][0], not kv[0][1].startswith("Brax"), kv[0][1])):
        recs.sort(key=lambda r: (r.get("seed", 0), r["call"]["name"]))
        call_name = ", ".join(sorted({r["call"]["name"] for r in recs}))
        notes = []
        if recs[0].get("algo") == "brax_apg":
            seeds = [r["seed"] for r in recs]
            finals = [r.get("final_return") for r in recs]
            bests = [r.get("best_return") for r in recs]
            at_budget = [at_budget_return(r["points"], r["budget_s"]) for r in recs]
            initial = [r["points"][0]["return"] if r.get("points") else None for r in recs]
            statuses = [r["status"] for r in recs]
            # A run with one epoch has no steady epoch: its set-up + first epoch bounds the compile from above.
            compile_s = _finite([r.get("compile_s") for r in recs if len(r.get("epochs", [])) >= 2])
            compile_upper = _finite([r.get("setup_s", 0) + r["first_epoch_s"] for r in recs
                                     if len(r.get("epochs", [])) == 1])
            if compile_upper:
                notes.append(f"{len(compile_upper)} run(s) ended after ONE epoch: compile <= set-up + first epoch "
                             f"= {', '.join(f'{x:.0f}' for x in compile_upper)} s (20 updates included), no steady update time")
            update_s = _finite([r.get("update_s") for r in recs if len(r.get("epochs", [])) >= 2])
            sps = _finite([r.get("env_steps_per_s") for r in recs if len(r.get("epochs", [])) >= 2])
            hp = recs[0]["hyperparams"]
            setting = f"H={hp['horizon_length']}, {hp['num_envs']} envs, lr {hp['learning_rate']}, preset {recs[0].get('preset')}"
            errors = sorted({f"{r.get('error_type')}: {r.get('error', '')[:160]}" for r in recs if r["status"] == "error"})
            nan = [r.get("nan_epoch") for r in recs if r["status"] == "nan"]
            trained_on = recs[0]["variant"]
            argvs = [r.get("argv") for r in recs]
            updates = [r["epochs"][-1]["epoch"] * r["updates_per_epoch"] if r.get("epochs") else 0 for r in recs]
            compile_text = _ms(compile_s) if compile_s else ("<= " + _ms(compile_upper) if compile_upper else "-")
        else:
            r = recs[0]
            seeds = r["seeds"]
            finals = r.get("final_return_per_seed") or []
            bests = r.get("best_return_per_seed") or []
            at_budget = [at_budget_return([{**p, "return": p["return_per_seed"][i]} for p in r["points"]], r["budget_s"])
                         for i in range(len(seeds))]
            initial = r["points"][0]["return_per_seed"] if r.get("points") else []
            nan_upd = r.get("nan_update_per_seed") or [None] * len(seeds)
            statuses = [("nan" if n is not None else r["status"]) for n in nan_upd] if r["status"] != "error" else ["error"]
            compile_s = _finite([r.get("compile_s")])
            update_s = _finite([r.get("update_s")])
            sps = _finite([r.get("env_steps_per_s_all_seeds")])
            hp = r["hyperparams"]
            setting = (f"H={hp['horizon']}, batch {hp['batch']}, lr {hp['lr']}, clip {hp['clip']} {hp['clip_threshold']}, "
                       f"{len(seeds)} seeds in one program ({hp['seed_batching']})")
            errors = [f"{r.get('error_type')}: {r.get('error', '')[:160]}"] if r["status"] == "error" else []
            nan = [n for n in nan_upd if n is not None]
            trained_on = "shipped"
            argvs = [r.get("argv")]
            updates = [r.get("updates", 0)]
            compile_text = _ms(compile_s)
            if r.get("setup_phases_s"):
                ph = r["setup_phases_s"]
                notes.append(f"compile = env_task {ph.get('env_task_s', 0):.0f} s + make_trainer "
                             f"{ph.get('make_trainer_s', 0):.0f} s + init, then the update's compile "
                             f"{r.get('update_compile_s', 0):.0f} s")
            if "timing_only_updates" not in r and r.get("updates", 0) < 2:
                notes.append("update time from ONE update (the first after the compile)")
            if r.get("compile_s", 0) > r["budget_s"]:
                notes.append(f"compile ({r['compile_s']:.0f} s) longer than the budget: no update within it; "
                             f"the run then made {r.get('updates')} update(s) past the budget")
        status = ", ".join(f"{s} x{statuses.count(s)}" for s in sorted(set(statuses)))
        rows.append({
            "env": env, "method": method, "trained_on": trained_on, "seeds": seeds,
            "final_mean": statistics.mean(_finite(finals)) if _finite(finals) else None,
            "final_std": statistics.pstdev(_finite(finals)) if len(_finite(finals)) > 1 else None,
            "best_mean": statistics.mean(_finite(bests)) if _finite(bests) else None,
            "best_std": statistics.pstdev(_finite(bests)) if len(_finite(bests)) > 1 else None,
            "final_text": _ms(finals), "best_text": _ms(bests),
            "at_budget_text": _ms([x[0] for x in at_budget]),
            "at_budget_per_seed": [x[0] for x in at_budget],
            "at_budget_mean": statistics.mean(_finite([x[0] for x in at_budget])) if _finite([x[0] for x in at_budget]) else None,
            "at_budget_initial_policy": sum(1 for x in at_budget if x[1]),
            "initial_per_seed": initial,
            "compile_text": compile_text, "notes": notes,
            "final_per_seed": finals, "best_per_seed": bests,
            "compile_s": statistics.mean(compile_s) if compile_s else None,
            "update_ms": 1e3 * statistics.mean(update_s) if update_s else None,
            "env_steps_per_s": statistics.mean(sps) if sps else None,
            "updates": updates, "budget_s": recs[0].get("budget_s"), "status": status,
            "nan_at": nan, "errors": errors, "setting": setting,
            "commands": sorted({_cmd(a) for a in argvs}),
            "call": call_name, "device": recs[0].get("device"), "eval_episode_length": recs[0].get("episode_length"),
            "eval_envs": recs[0].get("eval", {}).get("num_envs"),
        })
    return rows


def curves(recs):
    """Per seed: (times, returns) on the shipped env."""
    out = []
    for r in recs:
        if r.get("algo") == "brax_apg":
            pts = r.get("points", [])
            out.append(([p["train_wall_s"] for p in pts], [p["return"] for p in pts]))
        else:
            pts = r.get("points", [])
            for i in range(len(r["seeds"])):
                out.append(([p["train_wall_s"] for p in pts], [p["return_per_seed"][i] for p in pts]))
    return out


def figure(env, runs, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.0, 4.4))
    groups = {}
    for r in runs:
        if r["env"] != env or not r.get("points"):
            continue
        label = (f"Brax APG (trained on: {r['variant']}{_apg_label(r)})" if r.get("algo") == "brax_apg"
                 else f"stablebptt {r['mode']}")
        if r.get("status") == "error":
            label += f", {r.get('error_type', 'error')} at its first update"
        groups.setdefault(label, []).append(r)
    for label, recs in sorted(groups.items(), key=lambda kv: (not kv[0].startswith("Brax"), kv[0])):
        cs = [c for c in curves(recs) if c[0]]
        tmax = max(max(t) for t, _ in cs)
        grid = np.linspace(min(min(t) for t, _ in cs), tmax, 300)
        # Each seed's return is its last evaluation at or before t (a step function), NaN before its first.
        ys = []
        for t, y in cs:
            t, y = np.asarray(t), np.asarray(y, dtype=float)
            idx = np.searchsorted(t, grid, side="right") - 1
            ys.append(np.where(idx >= 0, y[np.clip(idx, 0, None)], np.nan))
        ys = np.asarray(ys)
        with np.errstate(all="ignore"), __import__("warnings").catch_warnings():
            __import__("warnings").simplefilter("ignore")
            mean = np.nanmean(ys, axis=0)
            lo, hi = np.nanmin(ys, axis=0), np.nanmax(ys, axis=0)
        line, = ax.plot(grid, mean, label=f"{label}, {len(cs)} seeds", drawstyle="steps-post")
        ax.fill_between(grid, lo, hi, color=line.get_color(), alpha=0.2, step="post")
        for t, y in cs:  # every evaluation, per seed
            ax.plot(t, y, "o", ms=3, color=line.get_color(), alpha=0.7)
    if not any(r["env"] == env and r.get("mode") for r in runs):
        ax.text(0.02, 0.55, "stablebptt: no record on this env\n(see 'Not in the table')", transform=ax.transAxes,
                fontsize=8, color="gray")
    budget = max((r.get("budget_s") or 0) for r in runs if r["env"] == env)
    ax.axvline(budget, color="k", ls="--", lw=1, label=f"budget {budget:g} s")
    ax.set_xlabel("training wall time, s (set-up and compile included, evaluation excluded)")
    ax.set_ylabel("episode return (1000 steps, env as shipped)")
    ax.set_title(f"{env}, one H100: mean over seeds (line), min-max (band), evaluations (dots)", fontsize=9)
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--raw", required=True, help="the folder of one folder per machine run")
    p.add_argument("--out", default="results/envs")
    p.add_argument("--name", default="apg_vs_stablebptt", help="stem of the files written into --out")
    p.add_argument("--notes", default=None, help="a markdown file appended as the section 'Not in the table'")
    p.add_argument("--apg-seeds", choices=("sequential", "concurrent"), default="sequential",
                   help="how the calls ran APG's seeds: one after another, or all at once on the one GPU")
    a = p.parse_args(argv)
    runs, throughput = load(a.raw)
    rows = rows_of(runs)
    os.makedirs(a.out, exist_ok=True)
    stem = os.path.join(a.out, a.name)
    json.dump({"rows": rows, "throughput": throughput}, open(stem + ".json", "w"), indent=1)
    cols = ["env", "method", "trained_on", "seeds", "at_budget_per_seed", "at_budget_mean", "final_per_seed",
            "final_mean", "best_per_seed", "best_mean", "compile_s", "compile_text", "update_ms", "env_steps_per_s",
            "updates", "budget_s", "status", "setting", "notes", "commands", "call", "device"]
    with open(stem + ".csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=cols, extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow({k: (json.dumps(v) if isinstance(v, list) else v) for k, v in r.items()})

    calls = {}
    for r in runs:
        calls.setdefault(r["call"]["name"], r["call"])
    for t in throughput:
        calls.setdefault(t["call"]["name"], t["call"])
    commands = []  # distinct script command lines, numbered

    def refs(cmds):
        out = []
        for c in cmds:
            if c not in commands:
                commands.append(c)
            out.append(f"[c{commands.index(c) + 1}]")
        return " ".join(out)

    f1 = lambda x, d=1: "-" if x is None else f"{x:.{d}f}"
    lines = [
        "# Brax APG against stablebptt's flows R and C on MuJoCo Playground (one H100, same wall-clock budget)",
        "",
        f"Written by `python benchmarks/envs_vs_apg/report.py {' '.join(argv if argv is not None else sys.argv[1:])}` from the "
        f"records in `{a.raw}/<call>/` (one folder per device call; `CALL.json` there holds the call's command).",
        "",
        "Protocol. Every policy is scored by `benchmarks/envs_vs_apg/evaluation.py`: the env as shipped "
        "(`registry.load(name, config_overrides={\"impl\": \"jax\"})`), 64 fixed resets (seed 1234), 1000 steps, "
        "deterministic policy, rewards summed until the first `done`; evaluation runs off the training clock. "
        "The training clock starts before the method's own set-up (APG: `apg.train`, its env wrapping and jits; "
        "stablebptt: `env_task` with its reward diagnosis, `make_trainer`, `init`, the update's compile) and "
        "counts compile. Brax APG: `apg.train`'s own defaults (horizon 32, 1 env, lr 1e-4, Adam b=(0.7, 0.95), "
        "lr decay 0.997, value clip 1.0, policy 4x32 MLP), " + (
            "seeds one after another, each in its own `apg.train`; " if a.apg_seeds == "sequential" else
            "the three seeds of an env at the same time, each in its own process and `apg.train` on the one GPU "
            "(as stablebptt's three seeds share it in one program); ") + (
        "scored at the end of an epoch of 20 updates once 30 s of training time passed. stablebptt: horizon "
        "100, batch 64 of 512 fixed `env.reset` states, Adam lr 1e-3, clip by global norm 1.0, tanh(MLP 64-64) "
        "policy starting at zero output, seeds 0-2 vmapped in ONE compiled update program per flow, no "
        "persistent compilation cache."),
        "",
        "Columns. *at budget*: the return of the policy as it stood when the budget ran out (the last "
        f"evaluation at a training time <= budget + {BUDGET_SLACK_S:g} s; where the compile outlasted the budget, "
        "the initial policy's evaluation; \u2020: the policy at the budget is the initial one, no update having finished by then); *last*: the last evaluation the run made, possibly past the budget "
        "(an APG epoch, or stablebptt's first update after its compile); *best*: each seed's best evaluation. "
        "Returns are mean \u00b1 std over seeds. *compile s*: set-up and compile (APG: set-up + first epoch "
        "minus a steady epoch; stablebptt: everything before the first update). *update ms*: one training "
        "update of the run's program, forward and backward (APG: one seed, horizon 32 x 1 env; stablebptt: "
        "three seeds x 64 states x horizon 100 in one program); *env steps/s*: env steps that program "
        "simulates per second of updates.",
        "",
        "| env | method | trained on | seeds | return at budget | last return | best return | compile s | update ms | env steps/s | status | command |",
        "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---|---|"]
    for r in rows:
        status = r["status"] + (f" (NaN at {r['nan_at']})" if r["nan_at"] else "")
        dagger = " \u2020" if r["at_budget_initial_policy"] else ""
        lines.append(f"| {r['env']} | {r['method']} | {r['trained_on']} | {len(r['seeds'])} | "
                     f"{r['at_budget_text']}{dagger} | {r['final_text']} | {r['best_text']} | {r['compile_text']} | "
                     f"{f1(r['update_ms'], 2)} | "
                     f"{'-' if r['env_steps_per_s'] is None else format(r['env_steps_per_s'], '.0f')} | {status} | "
                     f"{refs(r['commands'])} in `{r['call']}` |")
    lines += ["", "Notes per row:", ""]
    for r in rows:
        extra = r["notes"] + [f"setting: {r['setting']}", f"budget {r['budget_s']:g} s; updates made: {r['updates']}",
                              f"per seed: initial policy {[round(x, 2) if isinstance(x, float) else x for x in r['initial_per_seed']]}, "
                              f"at budget {[round(x, 2) if isinstance(x, float) else x for x in r['at_budget_per_seed']]}, "
                              f"last {[round(x, 2) if isinstance(x, float) else x for x in r['final_per_seed']]}"]
        extra += [f"error: `{e}`" for e in r["errors"]]
        lines.append(f"- {r['env']}, {r['method']}: " + "; ".join(extra))

    lines += ["", "## Same budget: who is higher when the budget runs out", ""]
    for env in sorted({r["env"] for r in rows}):
        er = [r for r in rows if r["env"] == env and r["at_budget_mean"] is not None and not r["errors"]]
        er.sort(key=lambda r: -r["at_budget_mean"])
        if not er:
            continue
        lines.append(f"- {env}: " + "; ".join(
            f"{r['method']} (trained on {r['trained_on']}) {r['at_budget_text']}"
            + (" \u2020" if r["at_budget_initial_policy"] else "") for r in er))

    lines += ["", "## Throughput of one training update (forward and backward)", "",
              "Rows 'from training run': the update times of the runs above (stablebptt: median of the updates after "
              "the first; '1 update' where only the first was timed); 'throughput run': a run made to time the update.", "",
              "| env | method | horizon | rollouts per update | update ms | env steps/s | source | command |",
              "|---|---|---:|---:|---:|---:|---|---|"]
    for r in rows:
        if r["update_ms"] is None:
            continue
        rec = next(x for x in runs if x["env"] == r["env"] and (
            (x.get("algo") == "brax_apg" and r["method"] == f"Brax APG ({x['variant']}{_apg_label(x)})")
            or (x.get("mode") and r["method"] == f"stablebptt {x['mode']}")))
        if rec.get("algo") == "brax_apg":
            hp = rec["hyperparams"]
            h, n, src = hp["horizon_length"], hp["num_envs"], "from training run (steady epochs / 20; mean over seeds)"
        else:
            hp = rec["hyperparams"]
            h, n = hp["horizon"], hp["batch"] * len(rec["seeds"])
            src = "from training run, " + ("median of the updates after the first" if "timing_only_updates" in rec
                                           else "1 update (the first after the compile)")
            src += f"; {len(rec['seeds'])} seeds x {hp['batch']} in one program"
        lines.append(f"| {r['env']} | {r['method']} | {h} | {n} | {f1(r['update_ms'], 2)} | "
                     f"{format(r['env_steps_per_s'], '.0f')} | {src} | {refs(r['commands'])} |")
    if throughput:
        for t in throughput:
            ok = t.get("status") == "ok"
            lines.append(f"| {t['env']} | {t.get('method', t.get('algo'))} | {t.get('horizon')} | {t.get('batch')} | "
                         f"{f1(1e3 * t['update_s'], 2) if ok else '-'} | {format(t['env_steps_per_s'], '.0f') if ok else '-'} | "
                         f"throughput run: {t.get('status')}"
                         f"{'' if ok else ', ' + str(t.get('epochs')) + ' epoch(s) before it stopped: no steady update time'} | "
                         f"{refs([_cmd(t.get('argv'))])} in `{t['call']['name']}` |")

    if a.notes:
        lines += ["", "## Not in the table", "", open(a.notes).read().strip()]
    lines += ["", "## Commands", "", "Script command lines (`$OUT/...` is the device call's output folder):", ""]
    lines += [f"- [c{i + 1}] `{c}`" for i, c in enumerate(commands)]
    lines += ["", "Device calls (each ran its scripts one after another on one GPU):", ""]
    for name, call in sorted(calls.items()):
        lines.append(f"- `{name}`: `{call.get('command', '?')}` on {call.get('device', '?')}; "
                     f"stablebptt/*.py sha1 {call.get('stablebptt_sha1_of_py_files', '?')[:12]}; {call.get('what', '')}")
    for env in sorted({r["env"] for r in runs}):
        png = f"{a.name}_{env}.png"
        figure(env, runs, os.path.join(a.out, png))
        lines += ["", f"![{env}]({png})"]
    open(stem + ".md", "w").write("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
