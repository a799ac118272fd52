"""Process-level settings a program may ask for: the library itself changes none on import."""
from __future__ import annotations

import gc
import os

# Objects allocated between two collections of Python's youngest generation (Python's own: 700).
SPACED_COLLECTIONS = 20_000


def one_cpu_thread() -> None:
    """Give XLA:CPU's intra-op pool one thread (``PJRT_NPROC=1``), unless ``PJRT_NPROC`` is set already.

    jaxlib's batched LAPACK kernels (MJX's Newton solver: Cholesky and triangular solves over every
    step's Jacobian) split a large batch into chunks queued on the intra-op pool and block the pool
    thread that runs them until the chunks are done: when as many such calls run at once as the pool
    has threads, every thread waits and the program hangs. With one thread the kernels run the batch
    in place. JAX reads the variable when it creates its CPU client, so call this before the first
    computation; the ``stablebptt`` commands call it as they start.

    Example::

      import stablebptt as sb
      sb.one_cpu_thread()  # before anything runs on JAX's CPU backend
    """
    os.environ.setdefault("PJRT_NPROC", "1")


def rarer_garbage_collections() -> None:
    """Collect Python's cyclic garbage after every ``SPACED_COLLECTIONS`` new objects (Python's own
    threshold is 700) where it would collect more often; a threshold of 0 (collections off) stays.

    Tracing a program makes millions of small objects, and each collection of the older generations
    walks all of them: a start's traces run a tenth to a fifth sooner, its peak memory about the same
    (docs/performance.md, "Python's garbage collected less often", gives the commands and figures). The
    garbage is still collected, later. The ``stablebptt`` commands call it as they start.

    Example::

      import stablebptt as sb
      sb.rarer_garbage_collections()  # before a start's traces
    """
    youngest, *older = gc.get_threshold()
    if 0 < youngest < SPACED_COLLECTIONS:
        gc.set_threshold(SPACED_COLLECTIONS, *older)
