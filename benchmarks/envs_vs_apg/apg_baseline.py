"""Brax APG baseline on MuJoCo Playground envs under a wall-clock budget.

Runs `brax.training.agents.apg.train` with its own defaults (Playground ships no APG config),
wrapped with `mujoco_playground.wrapper.wrap_for_brax_training` as Brax's Playground launcher
does, and scores the current policy with the shared `evaluation.py` at regular points of training
wall time. Evaluation time (ours and Brax's own) is kept off the training clock.

  python benchmarks/envs_vs_apg/apg_baseline.py --envs CartpoleSwingup,AcrobotSwingup,CheetahRun \
      --seeds 3 --budget 180 --out DIR

Variants (`--variants`, tried in order per env; later ones only if an earlier one fails or goes
NaN, unless --all-variants): shipped | iter1 (solver iterations = 1; skipped where the shipped model
already has 1) | noconstraint (constraint solver disabled) | saferew (Playground's reward tolerance
with a finite derivative, stablebptt.envs.playground.safe_tolerance, values unchanged), combined with '+',
e.g. iter1+saferew. Every variant is scored on the shipped env.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import jax

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import brax_runs  # noqa: E402
import evaluation  # noqa: E402

brax_runs.install_jax_shims()

from brax.training.agents.apg import networks as apg_networks  # noqa: E402
from brax.training.agents.apg import train as apg_train  # noqa: E402
from mujoco_playground import wrapper as mjp_wrapper  # noqa: E402
from stablebptt.storage import write_json  # noqa: E402

# apg.train's own defaults, spelled out so the record says what ran.
APG_DEFAULTS = dict(
    horizon_length=32,
    num_envs=1,
    learning_rate=1e-4,
    adam_b=(0.7, 0.95),
    use_schedule=True,
    schedule_decay=0.997,
    max_gradient_norm=1e9,
    normalize_observations=False,
    deterministic_eval=False,
    num_eval_envs=128,
    action_repeat=1,
)
# Defaults of Brax's own launcher (brax/training/learner.py --learner=apg) where they differ.
LEARNER_CLI = dict(APG_DEFAULTS, num_envs=4, learning_rate=5e-4, normalize_observations=True)
PRESETS = {"train_defaults": APG_DEFAULTS, "learner_cli": LEARNER_CLI}


def apply_variant(env, variant: str):
    import mujoco
    from mujoco import mjx

    m = env._mj_model
    parts = variant.split("+")
    model_changed = False
    for part in parts:
        if part in ("shipped", "saferew"):  # saferew changes the reward's derivative only (see run_one)
            continue
        if part == "iter1":
            m.opt.iterations = 1
        elif part == "noconstraint":
            m.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONSTRAINT)
        else:
            raise ValueError(variant)
        model_changed = True
    if model_changed:
        env._mjx_model = mjx.put_model(m, impl="jax")
    return env


def reward_context(variant: str):
    """saferew: Playground's reward tolerance with the same values and a finite derivative
    (stablebptt.envs.playground.repaired_rewards, what stablebptt's env_task uses), while APG traces."""
    import contextlib

    if "saferew" in variant.split("+"):
        from stablebptt.envs import playground

        return playground.repaired_rewards()
    return contextlib.nullcontext()


_EVALUATORS: dict = {}


def run_one(env_name, variant, seed, budget, eval_every, updates_per_epoch, hp, eval_envs, log, brax_eval="all",
            keep=lambda rec: None, evaluate_after=False):
    """One APG training run; returns its JSON record."""
    shipped = evaluation.load_env(env_name)
    episode_length = int(shipped._config.episode_length)
    train_env = apply_variant(evaluation.load_env(env_name), variant)

    hp = dict(hp)
    num_envs, horizon = hp["num_envs"], hp["horizon_length"]
    nets = apg_networks.make_apg_networks
    rec = {
        "env": env_name,
        "variant": variant,
        "seed": seed,
        "algo": "brax_apg",
        "budget_s": budget,
        "episode_length": episode_length,
        "hyperparams": {k: (list(v) if isinstance(v, tuple) else v) for k, v in hp.items()},
        "updates_per_epoch": updates_per_epoch,
        "solver_train_env": brax_runs.solver_info(train_env),
        "solver_eval_env": brax_runs.solver_info(shipped),
        "eval": {"num_envs": eval_envs, "seed": evaluation.EVAL_SEED, "deterministic": True},
        "device": str(jax.devices()[0]),
        "jax": jax.__version__,
    }

    # Our deterministic policy from APG's params (normalizer, policy): tanh of the Gaussian mean.
    obs_size, act_size = train_env.observation_size, train_env.action_size
    from brax.training.acme import running_statistics

    normalize = running_statistics.normalize if hp["normalize_observations"] else (lambda x, y: x)
    net = nets(obs_size, act_size, preprocess_observations_fn=normalize)
    make_policy = apg_networks.make_inference_fn(net)

    def apply(params, obs):
        return make_policy(params, deterministic=True)(obs, jax.random.PRNGKey(0))[0]

    # One compiled evaluator per (env, variant, policy family), shared by the seeds: the policy's
    # structure is the same for every seed, and params are an argument.
    key = (env_name, variant, bool(hp["normalize_observations"]), eval_envs)
    if key not in _EVALUATORS:
        _EVALUATORS[key] = (
            evaluation.make_evaluator(shipped, apply, num_envs=eval_envs),
            evaluation.make_evaluator(train_env, apply, num_envs=eval_envs) if variant != "shipped" else None,
        )
    eval_shipped, eval_variant = _EVALUATORS[key]

    def train():
        max_epochs = 1_000_000
        with reward_context(variant):
            apg_train.train(
                environment=train_env,
                eval_env=train_env,
                wrap_env_fn=mjp_wrapper.wrap_for_brax_training,
                episode_length=episode_length,
                policy_updates=updates_per_epoch * max_epochs,
                num_evals=max_epochs + 1,
                seed=seed,
                network_factory=nets,
                **hp,
            )

    return brax_runs.timed_run(train, rec, evaluate=eval_shipped, evaluate_variant=eval_variant, budget=budget,
                               eval_every=eval_every, updates_per_epoch=updates_per_epoch,
                               env_steps_per_update=num_envs * horizon, brax_eval=brax_eval, log=log, keep=keep,
                               evaluate_after=evaluate_after)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--envs", default="CartpoleSwingup,AcrobotSwingup,CheetahRun")
    p.add_argument("--seeds", type=int, default=3, help="seeds 0..N-1, one after another")
    p.add_argument("--updates-per-epoch", type=int, default=20, help="APG updates between callbacks")
    p.add_argument("--preset", choices=sorted(PRESETS), default="train_defaults")
    p.add_argument("--set", action="append", default=[], help="override a hyperparameter: key=value")
    p.add_argument("--variants", default="shipped,iter1,noconstraint")
    p.add_argument("--all-variants", action="store_true", help="run every variant, not only fallbacks")
    p.add_argument("--sticky-variant", action="store_true",
                   help="seeds after the first start from the variant the first seed trained on")
    p.add_argument("--throughput", action="store_true",
                   help="write throughput_apg_*.json (update time at the given horizon/num_envs) instead of run records")
    brax_runs.add_common_arguments(p, budget=180.0, eval_envs=evaluation.NUM_EVAL_ENVS, brax_eval="all")
    a = p.parse_args(argv)

    hp = dict(PRESETS[a.preset])
    for kv in a.set:
        k, v = kv.split("=", 1)
        hp[k] = type(hp[k])(json.loads(v)) if k in hp and not isinstance(hp[k], bool) else json.loads(v)
    eval_every = a.eval_every or a.budget / 10
    os.makedirs(a.out, exist_ok=True)
    logf = open(os.path.join(a.out, "log.txt"), "a")

    def log(msg):
        print(msg, flush=True)
        logf.write(msg + "\n")
        logf.flush()

    log(f"jax {jax.__version__} devices {jax.devices()} preset {a.preset} hp {hp}")
    summary = []
    throughput_records = []
    for env_name in a.envs.split(","):
        variants = a.variants.split(",")
        if evaluation.load_env(env_name)._mj_model.opt.iterations == 1 and "iter1" in variants:
            variants.remove("iter1")  # the shipped model already runs one solver iteration
            log(f"== {env_name}: shipped solver iterations = 1, variant iter1 skipped (same model)")
        for seed in range(a.seed0, a.seed0 + a.seeds):
            for variant in variants:
                log(f"== {env_name} variant={variant} seed={seed} budget={a.budget}s")
                # A run's record is written at every point scored: a run stopped by a wall-clock limit keeps them.
                path = Path(a.out) / f"{env_name}_{variant}_s{seed}.json"
                keep = (lambda rec: None) if a.throughput else (
                    lambda rec, path=path: write_json(path, {**rec, "preset": a.preset, "argv": sys.argv}))
                rec = run_one(env_name, variant, seed, a.budget, eval_every, a.updates_per_epoch, hp, a.eval_envs, log,
                              a.brax_eval, keep=keep, evaluate_after=a.evaluate_after)
                rec["preset"] = a.preset
                rec["argv"] = sys.argv
                if a.throughput:
                    tp = {"env": env_name, "method": f"Brax APG ({variant})", "algo": "brax_apg", "variant": variant,
                          "horizon": hp["horizon_length"], "batch": hp["num_envs"], "seeds": 1, "seed": seed,
                          "update_s": rec.get("update_s"), "env_steps_per_s": rec.get("env_steps_per_s"),
                          "compile_s": rec.get("compile_s"), "epochs": len(rec.get("epochs", [])),
                          "updates_per_epoch": a.updates_per_epoch, "device": rec["device"], "jax": rec["jax"],
                          "status": "ok" if rec.get("update_s") and rec["status"] in ("budget", "finished") else rec["status"],
                          "error_type": rec.get("error_type"), "error": rec.get("error"), "argv": sys.argv}
                    throughput_records.append(tp)
                    with open(os.path.join(a.out, f"throughput_apg_H{hp['horizon_length']}_B{hp['num_envs']}.json"), "w") as f:
                        json.dump(throughput_records, f, indent=1)
                    log(f"   -> throughput {tp}")
                    if rec["status"] in ("budget", "finished") and not a.all_variants:
                        break
                    continue
                keys = ("env", "variant", "seed", "status", "final_return", "best_return", "compile_s",
                        "env_steps_per_s", "update_s", "nan_epoch", "error_type")
                summary.append({k: rec.get(k) for k in keys})
                log(f"   -> {summary[-1]}")
                with open(os.path.join(a.out, "summary.json"), "w") as f:
                    json.dump(summary, f, indent=1)
                if rec["status"] in ("budget", "finished") and not a.all_variants:
                    if a.sticky_variant and seed == a.seed0:
                        # Later seeds start from the variant that trained seed0 (earlier ones failed there).
                        variants = variants[variants.index(variant):]
                        log(f"== {env_name}: later seeds run variants {variants} (sticky)")
                    break


if __name__ == "__main__":
    try:
        main()
    except KeyboardInterrupt:  # a wall-clock limit's SIGINT: the records keep the points scored
        print("stopped: each run's record keeps the points it scored", file=sys.stderr)
        sys.exit(130)
