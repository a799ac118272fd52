"""stablebptt's gradient flows on MuJoCo Playground envs under a wall-clock budget.

The other half of the benchmark whose first half is `apg_baseline.py`: the same envs as shipped
(`registry.load(name, config_overrides={"impl": "jax"})`, no variant: the library differentiates
MJX's constraint solver implicitly), turned into a `Task` by `stablebptt.envs.adapter.env_task`
and trained by `stablebptt.engine.training.make_trainer`'s compiled update, ALL seeds of one flow in ONE
compiled program (TrainConfig(seeds=N), seeds vmapped). Policies are scored with the shared
`evaluation.py` at regular points of training wall time, off the training clock, exactly as
apg_baseline.py scores APG. The training clock starts before `env_task` (its reward diagnosis,
the initial states' resets, the update's compile all count), as APG's starts before `apg.train`.

  python benchmarks/envs_vs_apg/stablebptt_half.py --envs CartpoleSwingup --modes R,C \
      --seeds 3 --budget 90 --horizon 100 --batch 64 --out DIR

Training data as the library defines it (`--episodes`): on (the default, as `stablebptt train --env`),
`batch` env states carried from update to update, each update one window of `horizon` steps from where
they stand, an episode reset between windows once it is done or at its length, the episodes' clocks
spread at the start (as APG trains); off (the paper's protocol), `train_size` fixed initial states from
`env.reset`, minibatches of `batch` cycled in order, one window from each. The loss is the window's
negative return.

`--throughput` times the update alone (no evaluation, one seed unless --seeds): steady update
wall time over `--throughput-updates` updates after the compile.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys
import time
import traceback

import jax
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import evaluation  # noqa: E402

from stablebptt.engine.config import TrainConfig, seed_array  # noqa: E402
from stablebptt.engine.fitting import settled_trainer, state_shapes  # noqa: E402
from stablebptt.engine.per_update import PerUpdateEpoch
from stablebptt.engine.training import make_trainer
from stablebptt.envs import playground  # noqa: E402
from stablebptt.envs.adapter import env_task, observation_policy  # noqa: E402


def solver_info(env) -> dict:
    o = env._mj_model.opt
    return {"solver": int(o.solver), "iterations": int(o.iterations), "ls_iterations": int(o.ls_iterations),
            "disableflags": int(o.disableflags), "n_limited_joints": int(env._mj_model.jnt_limited.sum())}


def _f(x):
    x = float(np.asarray(x))
    return x if math.isfinite(x) else str(x)


def _seed_slice(tree, i):
    return jax.tree.map(lambda a: a[i], tree)


def finite_per_seed(params) -> list[bool]:
    """Whether each seed's parameters (the leading axis of every leaf) are all finite."""
    leaves = [np.asarray(leaf) for leaf in jax.tree.leaves(params)]
    return np.logical_and.reduce([np.isfinite(leaf.reshape(leaf.shape[0], -1)).all(axis=1) for leaf in leaves]).tolist()


def build(env, env_name, a, mode, seeds, horizon, batch):
    """Task and trainer for ``env``, named ``env_name`` (Playground's registry name) in its summary; returns (task, config, trainer, update) with update = the jitted per-update program."""
    PHASES.clear()
    b0 = time.perf_counter()
    # As the command line sets up: the reward's diagnosis compiles beside the trainer's set-up and the
    # update's trace, and is waited for before the update compiles (settled).
    task = env_task(env, horizon, discount=a.discount, episode_length=a.trainer_episode_length or None,
                    hidden=tuple(a.hidden), name=env_name, defer_diagnosis=True,
                    normalize_observations=a.normalize_observations, smoothing_scale=a.smoothing_scale,
                    # --dense-reward: a ...Sparse env trains on its dense variant's reward, scored on its own.
                    reward_env=evaluation.load_env(playground.dense_variant(env_name)) if a.dense_reward else None)
    PHASES["env_task_s"] = time.perf_counter() - b0
    print(f"  env_task {PHASES['env_task_s']:.1f}s", flush=True)  # a run cut during its set-up still says how far it got
    config = TrainConfig(mode=mode, clip=a.clip, clip_threshold=a.clip_threshold, lr=a.lr, batch=batch,
                         # test_size = train_size: one compile of the batched reset serves both samples.
                         train_size=batch * a.train_batches, test_size=batch * a.train_batches, seeds=seeds, seed=a.seed0,
                         epochs=1, cosine=False, unroll=a.unroll, seed_batching=a.seed_batching,
                         epoch_program="per-update", episodes=a.episodes, critic=a.critic, critic_lr=a.critic_lr,
                         action_noise=a.action_noise, lr_decay=a.lr_decay,
                         td_lambda=a.td_lambda, nonfinite_flows=a.nonfinite_flows)
    b0 = time.perf_counter()
    trainer = make_trainer(task, config)
    PHASES["make_trainer_s"] = time.perf_counter() - b0
    print(f"  make_trainer {PHASES['make_trainer_s']:.1f}s", flush=True)
    assert isinstance(trainer.epoch, PerUpdateEpoch)
    return task, config, trainer, trainer.epoch.update


def lower_update(trainer, update, seed_ids):
    """The update traced and lowered for the states ``trainer.init`` gives, from their shapes alone
    (the reward's diagnosis need not have answered); and the minibatches."""
    shapes = state_shapes(trainer, seed_ids)
    batches = trainer.batches
    take = jax.jit(_seed_slice)  # one program for every minibatch, not one eager slice per leaf
    batch_list = [take(batches, i) for i in range(len(jax.tree.leaves(batches)[0]))]
    return update.lower(shapes, batch_list[0]), batch_list


_EVALUATORS: dict = {}
PHASES: dict = {}  # set-up and compile phases of the last run, seconds


def phase_clock(start: float):
    """A lap timer over PHASES from ``start`` (a perf_counter time): ``lap(name)`` records the seconds
    since the previous lap (the first: since ``start``) as ``name``."""
    last = [start]

    def lap(name: str) -> None:
        now = time.perf_counter()
        PHASES[name] = now - last[0]
        last[0] = now
    return lap


def run_one(env_name, mode, a, log):
    seeds = a.seeds
    horizon, batch = a.horizon, a.batch
    eval_env = evaluation.load_env(env_name)
    train_env = evaluation.load_env(env_name)
    episode_length = int(eval_env._config.episode_length)
    rec = {
        "env": env_name, "variant": "shipped", "mode": mode, "algo": f"stablebptt_{mode}",
        "seeds": list(range(a.seed0, a.seed0 + seeds)), "budget_s": a.budget, "episode_length": episode_length,
        "hyperparams": {"horizon": horizon, "batch": batch, "train_size": batch * a.train_batches, "lr": a.lr,
                        "optimizer": "adam", "clip": a.clip, "clip_threshold": a.clip_threshold,
                        "discount": a.discount, "hidden": list(a.hidden), "unroll": a.unroll,
                        "seed_batching": a.seed_batching, "policy": "tanh(mlp), output layer starts at zero "
                        "(small where the reward's gradient is NaN at zero action)",
                        "initial_states": ("batch env states carried across updates, reset when an episode ends"
                                           if a.episodes == "on" else
                                           "train_size env.reset states (data_seed 42), fixed, minibatches cycled"),
                        "episodes": a.episodes, "trainer_episode_length": a.trainer_episode_length,
                        "critic": a.critic, "critic_lr": a.critic_lr, "td_lambda": a.td_lambda,
                        "action_noise": a.action_noise, "lr_decay": a.lr_decay,
                        "normalize_observations": a.normalize_observations, "dense_reward": a.dense_reward,
                        "nonfinite_flows": a.nonfinite_flows, "smoothing_scale": a.smoothing_scale},
        "solver_train_env": solver_info(train_env), "solver_eval_env": solver_info(eval_env),
        "eval": {"num_envs": a.eval_envs, "seed": evaluation.EVAL_SEED, "deterministic": True,
                 "seeds_in_one_program": True},
        "device": str(jax.devices()[0]), "jax": jax.__version__,
        "points": [], "status": "running",
    }
    if (env_name, a.eval_envs) not in _EVALUATORS:  # one compiled evaluator per env, shared by the modes
        # All seeds in one program, each with evaluation.py's protocol (same resets, same rollout).
        _EVALUATORS[(env_name, a.eval_envs)] = evaluation.make_seed_evaluator(eval_env, observation_policy, num_envs=a.eval_envs)
    evaluate = _EVALUATORS[(env_name, a.eval_envs)]
    clock = {"eval_s": 0.0, "last_eval_train_s": -1e9, "updates": 0}
    t0 = time.perf_counter()

    def train_s():
        return time.perf_counter() - t0 - clock["eval_s"]

    def record_point(params):
        t = train_s()
        e0 = time.perf_counter()
        per_seed = evaluate(params)
        # A seed whose parameters went non-finite has no policy: its return is NaN, whatever the env's
        # reward makes of the states a NaN action leads to (some rewards map them to a finite number).
        rets = [p["mean_return"] if ok else float("nan") for p, ok in zip(per_seed, finite_per_seed(params))]
        pt = {"train_wall_s": t, "updates": clock["updates"],
              "env_steps_per_seed": clock["updates"] * batch * horizon,
              "return_per_seed": rets, "return_std_per_seed": [p["std_return"] for p in per_seed],
              "num_done_early_per_seed": [p["num_done_early"] for p in per_seed]}
        fin = [r for r in rets if math.isfinite(r)]
        pt["return"] = statistics.mean(fin) if fin else float("nan")
        pt["eval_s"] = time.perf_counter() - e0
        rec["points"].append(pt)
        clock["eval_s"] += pt["eval_s"]
        clock["last_eval_train_s"] = t
        log(f"  [{env_name}/{mode}] t={t:7.1f}s updates={clock['updates']} returns="
            + ",".join(f"{r:.1f}" for r in rets) + f" (eval {pt['eval_s']:.1f}s)")

    try:
        task, config, trainer, update = build(train_env, env_name, a, mode, seeds, horizon, batch)
        seed_ids = seed_array(config)
        rec["setup_s"] = time.perf_counter() - t0  # env_task (the diagnosis started), resets, trainer set-up
        c0 = time.perf_counter()
        # As `stablebptt train` starts: the update is traced while the reward's diagnosis compiles beside,
        # and compiled once the diagnosis has answered, so a flat reward's surrogate is the only update
        # compiled (it has a trainer of its own).
        lowered, batch_list = lower_update(trainer, update, seed_ids)
        lap = phase_clock(c0)
        lap("update_trace_s")
        task, settled = settled_trainer(task, trainer, config)
        lap("diagnosis_wait_s")
        if settled is not trainer:
            trainer, update = settled, settled.epoch.update
            lowered, batch_list = lower_update(trainer, update, seed_ids)
            lap("surrogate_trace_s")
        task = task.settled_fully()  # the surrogate's own check, compiled beside that trace
        lap("surrogate_check_wait_s")
        compiled = lowered.compile()
        lap("update_xla_compile_s")
        state = trainer.init(seed_ids)
        jax.block_until_ready(state)
        lap("init_s")
        rec["update_compile_s"] = time.perf_counter() - c0  # the update's compile, the diagnosis's wait, init
        rec["task_summary"] = task.summary
        rec["task_resolved"] = task.resolved
        rec["flows"] = list(trainer.flows)
        rec["compile_s"] = rec["setup_s"] + rec["update_compile_s"]
        rec["setup_phases_s"] = dict(PHASES)
        log(f"  [{env_name}/{mode}] phases {PHASES}")
        log(f"  [{env_name}/{mode}] setup {rec['setup_s']:.1f}s, update compile {rec['update_compile_s']:.1f}s; "
            f"{task.summary}")
        record_point(state.params)
        update_times, losses, norms = [], [], []
        nan_update = [None] * seeds
        zeroed = np.zeros(seeds, int)
        while True:
            u0 = time.perf_counter()
            state, (loss, norm, _cos, finite) = compiled(state, batch_list[clock["updates"] % len(batch_list)])
            loss = np.asarray(loss)  # blocks: the update is timed whole
            update_times.append(time.perf_counter() - u0)
            clock["updates"] += 1
            losses.append(loss.tolist())
            norms.append(np.asarray(norm).tolist())
            # A seed stops counting as training where its loss or update is non-finite, or (nonfinite_flows
            # "stop", the default) any flow's gradient is; with "zero" such a gradient is counted and C goes on.
            flows_ok = np.asarray(finite).all(axis=-1)
            update_ok = np.isfinite(loss) & np.isfinite(np.asarray(norm))
            ok = update_ok & flows_ok if a.nonfinite_flows == "stop" else update_ok
            zeroed += ~flows_ok & update_ok
            for i in range(seeds):
                if nan_update[i] is None and not ok[i]:
                    nan_update[i] = clock["updates"]
                    log(f"  [{env_name}/{mode}] seed {a.seed0 + i}: non-finite loss or gradient at update {clock['updates']}")
            t = train_s()
            if t >= a.budget or t - clock["last_eval_train_s"] >= a.eval_every:
                record_point(state.params)
            if t >= a.budget or (a.max_updates and clock["updates"] >= a.max_updates):
                break
            if all(n is not None for n in nan_update):
                record_point(state.params)
                break
        # Timing only, after the last evaluation (not training): enough updates for a steady update time.
        timing_only = 0
        while len(update_times) < a.min_timing_updates:
            u0 = time.perf_counter()
            state, (loss, *_rest) = compiled(state, batch_list[(clock["updates"] + timing_only) % len(batch_list)])
            np.asarray(loss)
            update_times.append(time.perf_counter() - u0)
            timing_only += 1
        rec["timing_only_updates"] = timing_only
        rec["status"] = "nan" if all(n is not None for n in nan_update) else "budget"
        rec["nan_update_per_seed"] = nan_update
        rec["zeroed_updates_per_seed"] = zeroed.tolist()  # updates whose flow gradient was non-finite, the update finite
        rec["updates"] = clock["updates"]
        steady = update_times[1:] or update_times
        rec["first_update_s"] = update_times[0]
        rec["update_s"] = statistics.median(steady)
        rec["steps_per_update_per_seed"] = batch * horizon
        rec["env_steps_per_s_per_seed"] = batch * horizon / rec["update_s"]
        rec["env_steps_per_s_all_seeds"] = seeds * batch * horizon / rec["update_s"]
        # Thin the per-update log to at most ~400 rows.
        stride = max(1, len(losses) // 400)
        rec["batch_loss"] = [[i + 1, l] for i, l in enumerate(losses)][::stride]
        rec["update_norm"] = [[i + 1, n] for i, n in enumerate(norms)][::stride]
    except Exception as e:  # noqa: BLE001 - the failure itself is the measurement
        rec["status"] = "error"
        rec["error_type"] = type(e).__name__
        rec["error"] = str(e)[:3000]
        rec["traceback_tail"] = traceback.format_exc()[-3000:]
        log(f"  [{env_name}/{mode}] ERROR {type(e).__name__}: {str(e)[:500]}")
    rec["total_wall_s"] = time.perf_counter() - t0
    rec["eval_wall_s"] = clock["eval_s"]
    finals = rec["points"][-1]["return_per_seed"] if rec["points"] else []
    bests = []
    for i in range(seeds):
        vals = [p["return_per_seed"][i] for p in rec["points"] if math.isfinite(p["return_per_seed"][i])]
        bests.append(max(vals) if vals else None)
    rec["final_return_per_seed"] = finals
    rec["best_return_per_seed"] = bests
    return rec


def throughput(env_name, mode, a, log):
    """Steady update time at (horizon, batch), no evaluation."""
    env = evaluation.load_env(env_name)
    rec = {"env": env_name, "mode": mode, "method": f"stablebptt {mode}", "algo": f"stablebptt_{mode}",
           "horizon": a.horizon, "batch": a.batch, "argv": sys.argv,
           "seeds": a.seeds, "seed_batching": a.seed_batching, "unroll": a.unroll, "device": str(jax.devices()[0]),
           "jax": jax.__version__}
    try:
        t0 = time.perf_counter()
        task, config, trainer, update = build(env, env_name, a, mode, a.seeds, a.horizon, a.batch)
        task, trainer = settled_trainer(task, trainer, config)  # timed as trained: a flat reward's surrogate
        task = task.settled_fully()
        update = trainer.epoch.update
        state = trainer.init(seed_array(config))
        jax.block_until_ready(state)
        rec["setup_s"] = time.perf_counter() - t0
        b = _seed_slice(trainer.batches, 0)
        c0 = time.perf_counter()
        compiled = update.lower(state, b).compile()
        rec["update_compile_s"] = time.perf_counter() - c0
        rec["compile_s"] = rec["setup_s"] + rec["update_compile_s"]
        times = []
        for _ in range(a.throughput_updates):
            u0 = time.perf_counter()
            state, out = compiled(state, b)
            jax.block_until_ready((state, out))
            times.append(time.perf_counter() - u0)
        rec["update_times_s"] = times
        rec["update_s"] = statistics.median(times[2:] or times)
        rec["env_steps_per_s"] = a.seeds * a.batch * a.horizon / rec["update_s"]
        rec["status"] = "ok"
        log(f"  throughput {env_name}/{mode} H={a.horizon} B={a.batch} seeds={a.seeds}: update "
            f"{1e3 * rec['update_s']:.2f} ms, {rec['env_steps_per_s']:.0f} env steps/s, compile {rec['update_compile_s']:.1f}s")
    except Exception as e:  # noqa: BLE001
        rec["status"] = "error"
        rec["error_type"] = type(e).__name__
        rec["error"] = str(e)[:3000]
        log(f"  throughput {env_name}/{mode} ERROR {type(e).__name__}: {str(e)[:500]}")
    return rec


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--envs", default="CartpoleSwingup,AcrobotSwingup,CheetahRun")
    p.add_argument("--modes", default="R,C")
    p.add_argument("--seeds", type=int, default=3, help="seeds seed0..seed0+N-1, all in one program")
    p.add_argument("--seed0", type=int, default=0)
    p.add_argument("--budget", type=float, default=90.0, help="training wall seconds, compile included")
    p.add_argument("--eval-every", type=float, default=None, help="training wall seconds; default budget/10")
    p.add_argument("--eval-envs", type=int, default=evaluation.NUM_EVAL_ENVS)
    p.add_argument("--horizon", type=int, default=100)
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--train-batches", type=int, default=8, help="train_size = batch x this")
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--clip", default="norm")
    p.add_argument("--clip-threshold", type=float, default=1.0)
    p.add_argument("--discount", type=float, default=1.0)
    p.add_argument("--hidden", type=lambda s: [int(x) for x in s.split(",")], default=[64, 64])
    p.add_argument("--unroll", type=int, default=1)
    p.add_argument("--seed-batching", default="vmap", choices=("vmap", "map"))
    p.add_argument("--episodes", default="on", choices=("on", "off"),
                   help="train on carried episodes (on) or from fixed starts, one window from each (off)")
    p.add_argument("--action-noise", type=float, default=0.0, help="std of Gaussian noise on training actions")
    p.add_argument("--lr-decay", type=float, default=1.0, help="the learning rate's factor per update")
    p.add_argument("--normalize-observations", action="store_true",
                   help="the policy sees observations standardised by running statistics")
    p.add_argument("--dense-reward", action="store_true", help="a ...Sparse env trains on its dense variant's reward "
                   "(as `stablebptt train --dense-reward`); every return reported stays the sparse one's")
    p.add_argument("--smoothing-scale", type=float, default=1.0,
                   help="a flat reward's surrogate temperatures: this times the sampled differences' median")
    p.add_argument("--nonfinite-flows", choices=("stop", "zero"), default="stop",
                   help="as `stablebptt train --nonfinite-flows`: zero (mode C) counts a flow's non-finite gradient, "
                   "left at zero by C's sign agreement, and trains the seed on")
    p.add_argument("--critic", action="store_true", help="bootstrap each window by a learned value of its last state")
    p.add_argument("--critic-lr", type=float, default=1e-3)
    p.add_argument("--td-lambda", type=float, default=0.95)
    p.add_argument("--trainer-episode-length", type=int, default=0,
                   help="env_task's episode_length: the length of the carried episodes (0: the env's own)")
    p.add_argument("--max-updates", type=int, default=0, help="stop after this many updates (0: budget only)")
    p.add_argument("--min-timing-updates", type=int, default=6,
                   help="after the budget, run updates (not counted as training) until this many are timed")
    p.add_argument("--throughput", action="store_true", help="time the update alone, no training record")
    p.add_argument("--throughput-updates", type=int, default=12)
    p.add_argument("--out", required=True)
    a = p.parse_args(argv)
    a.eval_every = a.eval_every or a.budget / 10
    os.makedirs(a.out, exist_ok=True)
    logf = open(os.path.join(a.out, "log_stablebptt.txt"), "a")

    def log(msg):
        print(msg, flush=True)
        logf.write(msg + "\n")
        logf.flush()

    log(f"jax {jax.__version__} devices {jax.devices()} args {vars(a)}")
    if a.throughput:
        out = []
        for env_name in a.envs.split(","):
            for mode in a.modes.split(","):
                out.append(throughput(env_name, mode, a, log))
                with open(os.path.join(a.out, f"throughput_stablebptt_H{a.horizon}_B{a.batch}.json"), "w") as f:
                    json.dump(out, f, indent=1)
        return
    summary = []
    for env_name in a.envs.split(","):
        for mode in a.modes.split(","):
            log(f"== {env_name} mode={mode} seeds={a.seeds} budget={a.budget}s")
            rec = run_one(env_name, mode, a, log)
            rec["argv"] = sys.argv
            with open(os.path.join(a.out, f"{env_name}_stablebptt_{mode}.json"), "w") as f:
                json.dump(rec, f, indent=1)
            keys = ("env", "mode", "status", "final_return_per_seed", "best_return_per_seed", "compile_s",
                    "update_s", "env_steps_per_s_per_seed", "updates", "nan_update_per_seed", "error_type")
            summary.append({k: rec.get(k) for k in keys})
            log(f"   -> {summary[-1]}")
            with open(os.path.join(a.out, "summary_stablebptt.json"), "w") as f:
                json.dump(summary, f, indent=1)


if __name__ == "__main__":
    main()
