"""stablebptt: stable backpropagation through time through differentiable physics.

The gradient flows R, M, S and their combination C live in ``stablebptt.flows``;
the training engine in ``stablebptt.training``; run directories in ``stablebptt.runs``.
"""
import os

# One XLA:CPU intra-op thread, set before JAX creates its CPU client (it reads
# PJRT_NPROC then). jaxlib's LAPACK kernels (MJX's Newton solver: cholesky and
# triangular solves, batched over every step's Jacobian) split a large batch into
# chunks queued on the intra-op pool and block the pool thread that runs them until
# the chunks are done; when as many such calls run at once as the pool has threads,
# every thread waits and the program hangs (jaxlib 0.10.2, 2 cores). With one
# thread the kernels run the batch in place. A user's own PJRT_NPROC is kept.
os.environ.setdefault("PJRT_NPROC", "1")

from stablebptt.flows import FLOWS, MODES, Dynamics, flow_gradients, select_flow, sign_agreement

__all__ = ["FLOWS", "MODES", "Dynamics", "flow_gradients", "select_flow", "sign_agreement"]
