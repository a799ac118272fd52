"""What the Brax baselines (`apg_baseline.py`, `ppo_baseline.py`) share: a Brax training run under a
wall-clock budget, scored with the shared `evaluation.py` off the training clock.

Brax's trainers call `acting.Evaluator.run_evaluation` before the first epoch and after every epoch;
`timed_run` puts a subclass in its place for the run, which times the epochs, scores the current
policy with the shared protocol when a point is due, and stops the run (an exception out of Brax's
loop) at the budget or at the first non-finite update. Evaluation time, Brax's own included, is kept
off the training clock.
"""

from __future__ import annotations

import math
import statistics
import time
import traceback
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np


def add_common_arguments(parser, budget: float, eval_envs: int, brax_eval: str) -> None:
    """The options both Brax baselines take: the first seed, the training budget and the evaluation
    schedule, Brax's own evaluator, and the output folder."""
    parser.add_argument("--seed0", type=int, default=0)
    parser.add_argument("--budget", type=float, default=budget, help="training wall seconds, compile included")
    parser.add_argument("--eval-every", type=float, default=None, help="training wall seconds; default budget/10")
    parser.add_argument("--eval-envs", type=int, default=eval_envs)
    parser.add_argument("--brax-eval", choices=("all", "none"), default=brax_eval,
                        help="also run Brax's own evaluator at each point (none: only the shared evaluation.py)")
    parser.add_argument("--evaluate-after", action="store_true",
                        help="keep each point's policy and score them all once the run ends, in one program: the "
                             "same episodes and clock, the episodes' steps run once for all points where a GPU "
                             "runs them one after another (a killed process keeps no points)")
    parser.add_argument("--out", required=True)


def install_jax_shims():
    """Brax 0.14.2 calls jax.device_put_replicated, which current JAX no longer has."""
    if hasattr(jax, "device_put_replicated"):
        return

    def device_put_replicated(x, devices):
        devices = list(devices)
        mesh = jax.sharding.Mesh(np.array(devices), ("d",))
        sharding = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("d"))

        def put(a):
            a = jnp.asarray(a)
            return jax.device_put(jnp.broadcast_to(a[None], (len(devices),) + a.shape), sharding)

        return jax.tree_util.tree_map(put, x)

    jax.device_put_replicated = device_put_replicated


class BudgetReached(Exception):
    pass


class NaNReached(Exception):
    pass


def solver_info(env) -> dict:
    o = env._mj_model.opt
    return {
        "solver": int(o.solver),
        "iterations": int(o.iterations),
        "ls_iterations": int(o.ls_iterations),
        "disableflags": int(o.disableflags),
        "n_limited_joints": int(env._mj_model.jnt_limited.sum()),
    }


def finite_or_text(x):
    x = float(np.asarray(x))
    return x if math.isfinite(x) else str(x)


def timed_run(
    train: Callable[[], Any],
    rec: dict,
    *,
    evaluate: Callable[[Any], dict],
    evaluate_variant: Callable[[Any], dict] | None,
    budget: float,
    eval_every: float,
    updates_per_epoch: int,
    env_steps_per_update: int,
    brax_eval: str,
    log: Callable[[str], None],
    keep: Callable[[dict], None] = lambda rec: None,
    evaluate_after: bool = False,
) -> dict:
    """Runs `train()` (a Brax trainer's call) under the budget; fills and returns `rec`.

    An epoch is what Brax runs between two calls of its evaluator: `updates_per_epoch` updates of
    `env_steps_per_update` env steps each. `keep(rec)` is called after every point scored (status
    "running") and once the run has ended, so a run stopped from outside keeps the points it scored:
    at once where a wall-clock limit's SIGINT (or Ctrl-C) stops it, which is then raised again as
    `KeyboardInterrupt` (status "interrupted"); at its last point where the process is killed.
    ``evaluate_after``: each point's policy is kept as it falls due, and all are scored once the run has
    ended or stopped, in one program per evaluator (``evaluate.many``, ``evaluate_variant.many``), after
    ``train()`` has returned and outside any context it sets: the same episodes and the same clock. Each
    point's ``eval_s`` is then an equal share of ``evaluated_after_s``, which ``total_wall_s`` leaves out;
    a process killed keeps its epochs' times and no point, and a scoring that fails leaves status "error"."""
    from brax.training import acting

    label = f"[{rec['env']}/{rec.get('variant', rec['algo'])}/s{rec['seed']}]"
    rec.update(points=[], epochs=[], status="running", brax_eval_mode=brax_eval, evaluate_after=evaluate_after)
    clock = {"t0": None, "eval_s": 0.0, "last_eval_train_s": -1e9, "epoch": 0, "last_epoch_end": None}

    def train_s():
        return time.perf_counter() - clock["t0"] - clock["eval_s"]

    pending = []  # with evaluate_after: (params, brax_metrics, t, epoch) of each point due, scored at the end

    def keep_so_far():  # the record with its returns and epochs' times summed up so far
        keep(summarised(timed(rec, updates_per_epoch, env_steps_per_update), budget))

    def add_point(scores, variant_scores, brax_metrics, t, epoch, eval_s):
        point = {
            "train_wall_s": t,
            "epoch": epoch,
            "updates": epoch * updates_per_epoch,
            "env_steps": epoch * updates_per_epoch * env_steps_per_update,
            "return": scores["mean_return"],
            "return_std": scores["std_return"],
            "num_done_early": scores["num_done_early"],
        }
        if variant_scores is not None:
            point["return_train_variant"] = variant_scores["mean_return"]
        if brax_metrics is not None:
            point["brax_eval_return"] = finite_or_text(brax_metrics.get("eval/episode_reward", float("nan")))
        point["eval_s"] = eval_s
        rec["points"].append(point)
        log(f"  {label} t={t:7.1f}s ep={epoch} steps={point['env_steps']} "
            f"return={point['return']:.2f} brax={point.get('brax_eval_return')}")

    def record_point(params, brax_metrics, t):
        # ``t``: the training seconds its call was judged due at. Read again here, it would be later
        # than the next call's (the evaluation's seconds come off the clock), and with eval_every 0
        # a quick epoch would then not be due.
        e0 = time.perf_counter()
        # Host copies: the same argument types at every call, so the evaluator compiles once (the
        # replicated training state's arrays may carry another sharding than the initial ones).
        params = jax.tree_util.tree_map(np.asarray, jax.device_get(params))
        if evaluate_after:
            pending.append((params, brax_metrics, t, clock["epoch"]))
        else:
            add_point(evaluate(params), evaluate_variant(params) if evaluate_variant is not None else None,
                      brax_metrics, t, clock["epoch"], time.perf_counter() - e0)
        clock["last_eval_train_s"] = t
        keep_so_far()  # at every point: a process killed from outside before its end keeps its compile and epochs

    def score_pending():
        """The points kept for later, scored together (their seconds shared out among them)."""
        if not pending:
            return
        e0 = time.perf_counter()
        policies = [params for params, *_ in pending]
        scores = evaluate.many(policies)
        variants = evaluate_variant.many(policies) if evaluate_variant is not None else [None] * len(policies)
        rec["evaluated_after_s"] = time.perf_counter() - e0
        for (_, brax_metrics, t, epoch), each, variant in zip(pending, scores, variants):
            add_point(each, variant, brax_metrics, t, epoch, rec["evaluated_after_s"] / len(pending))

    class TimedEvaluator(acting.Evaluator):
        def run_evaluation(self, policy_params, training_metrics, aggregate_episodes=True):
            now = time.perf_counter()
            first = clock["last_epoch_end"] is None
            if first:
                rec["setup_s"] = now - clock["t0"]  # wrapping, the jit of reset and step, init: before epoch 1
            else:
                clock["epoch"] += 1
                rec["epochs"].append({
                    "epoch": clock["epoch"],
                    "wall_s": now - clock["last_epoch_end"],
                    "sps": finite_or_text(training_metrics.get("training/sps", float("nan"))),
                    "grad_norm": finite_or_text(training_metrics.get("training/grad_norm", float("nan"))),
                    "params_norm": finite_or_text(training_metrics.get("training/params_norm", float("nan"))),
                    # Every scalar Brax reports (APG's norms, PPO's losses): one non-finite stops the run.
                    "finite": all(math.isfinite(float(np.asarray(v))) for v in training_metrics.values()
                                  if np.ndim(v) == 0),
                })
            t = train_s()
            e0 = time.perf_counter()  # after t: the evaluation's seconds then never outrun the next call's t
            nan = (not first) and not rec["epochs"][-1]["finite"]
            due = first or nan or t >= budget or t - clock["last_eval_train_s"] >= eval_every
            metrics = dict(training_metrics)
            brax_metrics = None
            if due:
                if brax_eval == "all":  # Brax's own evaluator (compiles once per run), a cross-check
                    brax_metrics = super().run_evaluation(policy_params, training_metrics, aggregate_episodes)
                    metrics = brax_metrics
                record_point(policy_params, brax_metrics, t)
            clock["eval_s"] += time.perf_counter() - e0
            clock["last_epoch_end"] = time.perf_counter()
            if nan:
                rec["nan_epoch"] = clock["epoch"]
                rec["nan_update_range"] = [(clock["epoch"] - 1) * updates_per_epoch + 1, clock["epoch"] * updates_per_epoch]
                raise NaNReached()
            if t >= budget:
                raise BudgetReached()
            return metrics

    saved = acting.Evaluator
    acting.Evaluator = TimedEvaluator
    clock["t0"] = time.perf_counter()
    try:
        train()
        rec["status"] = "finished"
    except BudgetReached:
        rec["status"] = "budget"
    except NaNReached:
        rec["status"] = "nan"
    except KeyboardInterrupt:
        rec["status"] = "interrupted"
    except Exception as e:  # noqa: BLE001 - the failure itself is the measurement
        rec["status"] = "error"
        rec["error_type"] = type(e).__name__
        rec["error"] = str(e)[:3000]
        rec["traceback_tail"] = traceback.format_exc()[-3000:]
        log(f"  {label} ERROR {type(e).__name__}: {str(e)[:300]}")
    finally:
        acting.Evaluator = saved
    rec["total_wall_s"] = time.perf_counter() - clock["t0"]
    rec["eval_wall_s"] = clock["eval_s"]
    interrupted = rec["status"] == "interrupted"
    try:
        score_pending()
    except Exception as e:  # noqa: BLE001 - the run's epochs are kept; its points are lost, and say why
        rec["status"] = "error"
        rec["error_type"] = type(e).__name__
        rec["error"] = f"scoring the points after the run: {str(e)[:3000]}"
    keep_so_far()
    if interrupted:
        raise KeyboardInterrupt
    return rec


def timed(rec: dict, updates_per_epoch: int, env_steps_per_update: int) -> dict:
    """``rec`` with its epochs' times summed up so far: the first epoch's, a steady one's (the median of the
    later ones), the compile (set-up plus the first epoch's excess over a steady epoch), an update's."""
    epochs = rec["epochs"]
    if epochs:
        rec["first_epoch_s"] = epochs[0]["wall_s"]
        steady = [e["wall_s"] for e in epochs[1:]] or [epochs[0]["wall_s"]]
        rec["steady_epoch_s"] = statistics.median(steady)
        rec["compile_s"] = rec.get("setup_s", 0.0) + epochs[0]["wall_s"] - rec["steady_epoch_s"]
        rec["steps_per_update"] = env_steps_per_update
        rec["update_s"] = rec["steady_epoch_s"] / updates_per_epoch
        rec["env_steps_per_s"] = env_steps_per_update / rec["update_s"]
        sps = [e["sps"] for e in epochs[1:] if not isinstance(e["sps"], str)]
        rec["brax_sps_median"] = statistics.median(sps) if sps else None
    return rec


def summarised(rec: dict, budget: float) -> dict:
    """``rec`` with its returns summed up from its points so far: the last, the best, and the last
    scored within the budget."""
    finite = [p["return"] for p in rec["points"] if math.isfinite(p["return"])]
    rec["final_return"] = rec["points"][-1]["return"] if rec["points"] else None
    rec["best_return"] = max(finite) if finite else None
    # A trainer whose epochs are long (PPO's) may pass the budget by most of an epoch: the return at
    # equal time is the last one scored within it.
    within = [p for p in rec["points"] if p["train_wall_s"] <= budget]
    rec["return_within_budget"] = within[-1]["return"] if within else None
    return rec
