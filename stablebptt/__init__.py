"""stablebptt: stable backpropagation through time through differentiable physics.

The gradient flows R, M, S and their combination C live in ``stablebptt.flows``;
the training engine in ``stablebptt.training``; run directories in ``stablebptt.runs``.
"""
from stablebptt.flows import FLOWS, MODES, Dynamics, flow_gradients, select_flow, sign_agreement

__all__ = ["FLOWS", "MODES", "Dynamics", "flow_gradients", "select_flow", "sign_agreement"]
