"""Non-finite epochs in words, and seeds that stop apart: a seed whose epoch went non-finite keeps
its last good state while the other seeds of its program train on.

Seeds trained in one program are independent, so one seed's NaN says nothing about the others. ``fit``
(``stablebptt.engine.fitting``) stops a whole run only where every seed has failed; a seed that fails
alone is retired: its state stays that of the epoch before, and its rows from that epoch on hold no
numbers (it trains and is scored no more). Its retirement is read back from those rows on a resume.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from stablebptt.engine.metrics import COLUMNS, METRICS
from stablebptt.engine.training import FLOW_BITS, nonfinite_names


def nonfinite_message(flows: tuple[str, ...], metrics: dict) -> str:
    """"non-finite <what>" when an epoch's metrics (host arrays over seeds) failed a check, else ""."""
    if np.all(metrics["finite"]):
        return ""
    what = nonfinite_names(flows, int(np.bitwise_or.reduce(np.atleast_1d(metrics["nonfinite"]))))
    return f"non-finite {', '.join(what)}"


def zeroed_notice(flows: tuple[str, ...], metrics: dict, seeds: np.ndarray) -> str:
    """What an epoch that went on through non-finite flow gradients (``nonfinite_flows`` "zero") left
    at zero, in words; "" where nothing was."""
    counts = np.atleast_1d(metrics.get("nonfinite_flow_updates", 0))
    if not counts.any() or not np.all(metrics["finite"]):
        return ""
    bits = int(np.bitwise_or.reduce(np.atleast_1d(metrics["nonfinite"]))) >> FLOW_BITS << FLOW_BITS
    where = ", ".join(f"seed {int(seed)}: {int(count)}" for seed, count in zip(seeds, counts) if count)
    return (f"{', '.join(nonfinite_names(flows, bits))} non-finite in some updates ({where}); mode C's sign "
            "agreement left those components at zero and training went on")


def failing(metrics: dict) -> np.ndarray:
    """bool [seeds]: the seeds whose epoch failed a check (``metrics["finite"]`` false)."""
    return ~np.atleast_1d(np.asarray(metrics["finite"], dtype=bool))


def retired_in(rows: np.ndarray, row_ids: np.ndarray) -> np.ndarray:
    """bool [seeds]: the seeds of ``row_ids`` whose last saved row holds no numbers (retired before a
    resume). A trained epoch's update norm is always a number; a retired seed's is NaN."""
    retired = np.zeros(len(row_ids), dtype=bool)
    norm = COLUMNS.index("update_norm")
    for index, seed in enumerate(row_ids):
        own = rows[rows[:, 1] == seed]
        retired[index] = len(own) > 0 and np.isnan(own[own[:, 0].argmax(), norm])
    return retired


@jax.jit
def keep_retired(new_state, old_state, retired: jax.Array):
    """``new_state`` with the retired seeds' slices (leading axis) taken from ``old_state``."""
    def pick(new, old):
        return jnp.where(retired.reshape((-1,) + (1,) * (new.ndim - 1)), old, new)

    return jax.tree.map(pick, new_state, old_state)


def without_retired(metrics: dict, retired: np.ndarray) -> dict:
    """``metrics`` as if the retired seeds had passed their checks, with none of their numbers: every
    recorded metric of theirs NaN, their failures left out of what the others' epoch reports."""
    blanked = dict(metrics)
    for name in METRICS:
        values = np.array(np.atleast_1d(metrics[name]), dtype=np.float64)
        values[retired] = np.nan
        blanked[name] = values
    blanked["finite"] = np.atleast_1d(np.asarray(metrics["finite"], dtype=bool)) | retired
    for name in ("nonfinite", "nonfinite_flow_updates"):
        if name in metrics:
            blanked[name] = np.where(retired, 0, np.atleast_1d(metrics[name]))
    return blanked


def failure(problem: str, epoch: int, seeds: np.ndarray) -> str:
    """What failed, when and for which seeds: "non-finite loss at epoch 12 (seed 43)"."""
    return f"{problem} at epoch {epoch} (seed {', '.join(str(int(seed)) for seed in seeds)})"


def retirement_notice(problem: str, seeds: np.ndarray, epoch: int, remaining: int) -> str:
    """One line for seeds retired at ``epoch``: what failed, what is kept, who trains on."""
    return (f"{failure(problem, epoch, seeds)}: {'it stops' if len(seeds) == 1 else 'they stop'} with "
            f"the parameters of epoch {epoch - 1}, the other {remaining} train on")
