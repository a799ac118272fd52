"""Process-level settings a program may ask for: the library itself changes none on import."""
from __future__ import annotations

import os


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
