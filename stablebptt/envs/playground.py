"""MuJoCo Playground's environments, loaded for the gradient flows (the optional extra ``playground``).

``load(name)`` takes an environment from Playground's registry with MJX's JAX
implementation (``impl="jax"``; Warp has no gradients) and refuses, in one
line, a name the registry lacks, a missing extra, an environment that runs
on Warp only, and a robot whose MuJoCo Menagerie models cannot be fetched. ``repaired_rewards()`` is the context ``environments.env_task``
enters while the step traces: Playground's reward ``tolerance`` computed in a
form whose values are the same and whose derivative is never NaN; ``repaired_rewards(sloped_tails=True)``
also gives the derivative a slope past where a tolerance's sigmoid ends at zero.
"""
from __future__ import annotations

import contextlib
import functools
import importlib
import io
import subprocess
import sys
import threading
from typing import Any, Iterable, Iterator

import jax
import jax.numpy as jnp

from stablebptt.errors import InputError, first_line
from stablebptt.physics import mujoco_log
from stablebptt.imports import imported_without

EXTRA = "pip install 'stablebptt[playground]'"
# Where MuJoCo Playground clones MuJoCo Menagerie from (mujoco_playground._src.mjx_env.ensure_menagerie_exists),
# into its MENAGERIE_PATH at its MENAGERIE_COMMIT_SHA.
MENAGERIE_REPOSITORY = "https://github.com/deepmind/mujoco_menagerie.git"
REPAIRS = "Playground's reward tolerance in a form whose derivative is finite (values unchanged)"
SLOPED_TAILS = (REPAIRS + "; past the end of a tolerance's linear, quadratic or cosine sigmoid its derivative keeps "
                "the sigmoid's mean slope (values unchanged)")


# Playground's torch and RSL-RL wrappers import these wherever they are installed; no command runs
# them, and PyTorch alone took 3.4 s of a GPU machine's cold start (one H200, CartpoleSwingup;
# the record: `git show fb065bd:results/startup/gpu-side-by-side/h200/phases_CartpoleSwingup.log`).
UNUSED_BY_COMMANDS = ("torch", "tensordict", "rsl_rl")
_left_out: tuple[str, ...] = ()


class PlaygroundMissing(InputError):
    """MuJoCo Playground is not installed."""


def leave_out_when_imported(names: Iterable[str]) -> None:
    """Import Playground, when it is first imported here, without ``names`` (``cli.leave_out_unused_backends``)."""
    global _left_out
    _left_out = tuple(names)


def _module(name: str) -> Any:
    """A module of Playground; its first import leaves out what ``leave_out_when_imported`` named."""
    with imported_without(_left_out if "mujoco_playground" not in sys.modules else ()):
        return importlib.import_module(name)


def registry() -> Any:
    """Playground's registry module; ``PlaygroundMissing`` names the extra to install."""
    try:
        with contextlib.redirect_stdout(io.StringIO()):  # its Warp import notice is not the user's business
            playground_registry = _module("mujoco_playground").registry
    except ImportError as error:
        raise PlaygroundMissing(f"MuJoCo Playground is not installed ({error}): {EXTRA}") from None
    return playground_registry


def names() -> tuple[str, ...]:
    """Every environment of Playground's registry."""
    return tuple(registry().ALL_ENVS)


def suite_names() -> tuple[str, ...]:
    """Playground's DeepMind Control Suite environments."""
    return tuple(_module("mujoco_playground").dm_control_suite.ALL_ENVS)


def dense_variant(name: str) -> str:
    """The registry's dense-reward counterpart of a sparse one (CartpoleSwingupSparse -> CartpoleSwingup), else ""."""
    dense = name.removesuffix("Sparse")
    return dense if dense != name and dense in names() else ""


def check_name(name: str) -> Any:
    """Playground's registry module, once ``name`` is known to be in it (nothing loaded, no device touched)."""
    known = registry()
    if name not in known.ALL_ENVS:
        close = [env for env in known.ALL_ENVS if env.lower() == name.lower()]
        hint = f"did you mean {close[0]}?" if close else "python -c 'from mujoco_playground import registry; print(registry.ALL_ENVS)' lists them"
        raise InputError(f"unknown environment {name!r}: not in MuJoCo Playground's registry ({hint})")
    return known


def fetch_menagerie(name: str) -> None:
    """Where ``name`` is one of Playground's robots (its locomotion and manipulation envs), the checkout of
    MuJoCo Menagerie it builds them from, fetched as Playground fetches it where it is missing (git, on
    first use); ``InputError`` naming the folder and how to provide it where that fails."""
    playground = _module("mujoco_playground")
    if name not in (*playground.locomotion.ALL_ENVS, *playground.manipulation.ALL_ENVS):
        return
    mjx_env = _module("mujoco_playground._src.mjx_env")
    if mjx_env.MENAGERIE_PATH.exists():
        return
    try:
        with contextlib.redirect_stderr(io.StringIO()):  # its progress bar and error line: the one line below says it
            mjx_env.ensure_menagerie_exists()
    except (subprocess.CalledProcessError, OSError) as error:
        if isinstance(error, subprocess.CalledProcessError):
            why = f"git clone {MENAGERIE_REPOSITORY} failed, exit status {error.returncode}: no network?"
        elif isinstance(error, FileNotFoundError) and "git" in str(error):
            why = "git is not installed"
        else:  # a folder that cannot be written, say
            why = f"{type(error).__name__}: {error}"
        raise InputError(f"{name} is built from MuJoCo Menagerie's robot models, which MuJoCo Playground fetches "
                         f"on first use into {mjx_env.MENAGERIE_PATH}, and fetching them failed ({why}): "
                         f"{_menagerie_remedy(mjx_env)}") from None


def _menagerie_remedy(mjx_env: Any) -> str:
    path = mjx_env.MENAGERIE_PATH
    return (f"run again with network, or provide the checkout there (git clone {MENAGERIE_REPOSITORY} {path} && "
            f"git -C {path} checkout {mjx_env.MENAGERIE_COMMIT_SHA}, or a copy of one from a machine with network)")


def require_jax_impl(env: Any, name: str, error: type[InputError] = InputError) -> None:
    """Refuse an env simulated by other than MJX's JAX implementation, the only one with gradients (one that
    names no implementation is left as it is)."""
    impl = getattr(getattr(env, "mjx_model", None), "impl", None)
    impl = None if impl is None else str(getattr(impl, "value", impl))
    if impl not in (None, "jax"):
        raise error(f"{name} runs on {impl}, not MJX's JAX implementation, the only one with gradients: load it "
                    f"with config_overrides={{'impl': 'jax'}}")


def load(name: str) -> Any:
    """The environment ``name`` of Playground's registry, simulated by MJX's JAX implementation."""
    known = check_name(name)
    config = known.get_default_config(name)
    if "impl" not in config:
        raise InputError(f"{name} has no 'impl' setting: it runs on MuJoCo Warp only, which has no gradients")
    fetch_menagerie(name)
    try:
        with mujoco_log.collected() as notices:
            env = known.load(name, config_overrides={"impl": "jax"})
    except Exception as error:  # noqa: BLE001 - an env that cannot be built on MJX's JAX implementation
        mjx_env = _module("mujoco_playground._src.mjx_env")
        if mjx_env.MENAGERIE_PATH.name in str(error):  # a checkout that lacks what the robot loads
            raise InputError(f"{name}: MuJoCo Menagerie's checkout at {mjx_env.MENAGERIE_PATH} lacks what it loads "
                             f"({first_line(error)}): remove the folder and {_menagerie_remedy(mjx_env)}") from None
        raise InputError(f"{name} cannot be built with impl='jax' ({first_line(error)}): it needs MuJoCo Warp, which "
                         "has no gradients") from None
    require_jax_impl(env, name)
    for notice in notices:  # an attribute Playground's own file uses, which MuJoCo will drop, is no user's to change
        if "is deprecated" not in notice:
            print(f"mujoco ({name}'s model): {notice}", file=sys.stderr)
    return env


def _sigmoid(distance: jnp.ndarray, value_at_1: float, kind: str, sloped_tail: bool = False) -> jnp.ndarray:
    """dm_control's tolerance sigmoids: 1 at distance 0, ``value_at_1`` at distance 1. The linear, quadratic
    and cosine ones reach 0 at a finite distance and stay there, flat; with ``sloped_tail`` their derivative
    past that end is the sigmoid's mean slope over its reach (the value stays 0)."""
    if kind == "gaussian":
        return jnp.exp(-0.5 * (distance * jnp.sqrt(-2 * jnp.log(value_at_1))) ** 2)
    if kind == "hyperbolic":
        return 1 / jnp.cosh(distance * jnp.arccosh(1 / value_at_1))
    if kind == "long_tail":
        return 1 / ((distance * jnp.sqrt(1 / value_at_1 - 1)) ** 2 + 1)
    if kind == "reciprocal":
        return 1 / (jnp.abs(distance) * (1 / value_at_1 - 1) + 1)
    if kind == "tanh_squared":
        return 1 - jnp.tanh(distance * jnp.arctanh(jnp.sqrt(1 - value_at_1))) ** 2
    reach = distance * {"cosine": jnp.arccos(2 * value_at_1 - 1) / jnp.pi, "linear": 1 - value_at_1,
                        "quadratic": jnp.sqrt(1 - value_at_1)}[kind]  # 0 at the bounds, 1 where the sigmoid ends
    inside = jnp.abs(reach) < 1
    scaled = jnp.where(inside, reach, 0.0)  # outside, the constant 0: no slope from an unused branch
    shape = {"cosine": (1 + jnp.cos(jnp.pi * scaled)) / 2, "linear": 1 - scaled, "quadratic": 1 - scaled ** 2}[kind]
    value = jnp.where(inside, shape, 0.0)
    if not sloped_tail:
        return value
    # Past its end the sigmoid's mean slope over its reach (from 1 to 0 as reach goes from 0 to 1), in the derivative only.
    return value + jnp.where(inside, 0.0, jax.lax.stop_gradient(reach) - reach)


def safe_tolerance(x, bounds=(0.0, 0.0), margin=0.0, sigmoid="gaussian", value_at_margin=0.1, sloped_tails=False):
    """Playground's ``reward.tolerance`` with the same values and a derivative that is never NaN (with
    ``sloped_tails``, sloped past the sigmoid's end: ``_sigmoid``).

    Playground evaluates the sigmoid at the distance to the bounds everywhere
    and keeps 1 inside them. With an infinite bound that distance is infinite
    inside, the sigmoid's slope there is inf x 0 = NaN, and the unused branch's
    NaN reaches the gradient. Here the sigmoid sees distance 0 inside the bounds
    (where its value is discarded), so inside the derivative is exactly 0.
    """
    lower, upper = bounds
    if lower > upper or margin < 0:
        raise ValueError("tolerance needs lower <= upper and margin >= 0")
    inside = jnp.logical_and(lower <= x, x <= upper)
    if margin == 0:
        return jnp.where(inside, 1.0, 0.0)
    # Differences are linear: an infinite one in an unused branch passes a finite (zero) slope.
    distance = jnp.where(inside, 0.0, jnp.where(x < lower, lower - x, x - upper)) / margin
    return jnp.where(inside, 1.0, _sigmoid(distance, value_at_margin, sigmoid, sloped_tails))


@contextlib.contextmanager
def repaired_rewards(sloped_tails: bool = False) -> Iterator[None]:
    """Within the block, Playground's rewards use ``safe_tolerance`` (enter it while a step traces). With
    ``sloped_tails`` a tolerance flat past its sigmoid's end (the walker's move reward at speed <= 0,
    the cheetah's run reward) has a slope there in the derivative only: the rewards' values, and so
    every return, stay as written.

    The block holds for its own thread: a step traced on another meanwhile (an epoch compiling beside
    a check) sees its own blocks, and leaving one block leaves the others as they are."""
    _dispatch_tolerance()
    entered = _REPAIRS.__dict__.setdefault("entered", [])
    entered.append(sloped_tails)
    try:
        yield
    finally:
        entered.pop()


_REPAIRS = threading.local()  # this thread's blocks of ``repaired_rewards``: their ``sloped_tails``, innermost last
_DISPATCH = threading.Lock()


def _dispatch_tolerance() -> None:
    """Playground's ``reward.tolerance``, once for all threads, made a function that computes the tolerance as
    the calling thread's innermost ``repaired_rewards`` block asks: Playground's own outside any."""
    from mujoco_playground._src import reward
    with _DISPATCH:
        if getattr(reward.tolerance, "dispatches_repairs", False):
            return
        playgrounds_own = reward.tolerance

        @functools.wraps(playgrounds_own)  # its name and signature stay Playground's for whoever inspects them
        def tolerance(*args, **kwargs):
            entered = getattr(_REPAIRS, "entered", None)
            if not entered:
                return playgrounds_own(*args, **kwargs)
            return safe_tolerance(*args, **kwargs, sloped_tails=entered[-1])

        tolerance.dispatches_repairs = True
        reward.tolerance = tolerance
