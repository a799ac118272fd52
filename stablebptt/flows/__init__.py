"""The gradient flows of backpropagation through time and their combination.

A controller ``policy(params, state) -> control`` drives a simulator
``step(state, control) -> state`` for ``horizon`` steps and a loss is taken on
the visited states and controls. The flows differ only in where the backward
pass is cut, never in the forward values (Schnell & Thuerey, ICLR 2024):

====  ==========================  ===========================  ======================
flow  policy sees                 simulator sees               gradient
====  ==========================  ===========================  ======================
R     x_t                         x_t                          regular BPTT
M     stop_gradient(x_t)          x_t                          physics path only
S     stop_gradient(x_t)          stop_gradient(x_t)           one-step only
====  ==========================  ===========================  ======================

The combined update C keeps g_M where it agrees in sign with g_R, else 0.

All flows a training step needs come from ONE forward rollout, in one of two
ways (``Plan.step_derivative``):

- ``"reverse"``: every step is a ``custom_vjp`` that stores the simulator's
  and the policy's pullbacks once and, in the reverse pass, pulls back one
  cotangent per flow through them together.
- ``"forward"``: the rollout stores only states and controls. A step's
  Jacobian depends on nothing but its own (x_t, u_t), so the Jacobians of ALL
  steps are built afterwards in one batched forward-mode pass (not one small
  pass per step), and the reverse pass becomes a linear recurrence of small
  matrix products, one adjoint per flow. The policy's parameter gradient is
  then one batched pullback over every visited state.

``reference_rollout`` is the literal stop_gradient transcription of the table,
kept as the definition both paths are tested against.

The parts live in modules of their own, each importing only those named before it: ``dynamics``
(the contract, the plan of how to differentiate it, and the state's leaves), ``modes`` (the flows by name
and the modes that combine them), ``adjoint_step`` (the reverse-mode step), ``linearized`` (step
Jacobians, the forward-mode path) and ``gradients`` (every flow's gradient from one rollout, and the
reference they are tested against). This package's face names what a user of the flows needs.
"""
from stablebptt.flows.dynamics import Dynamics, Plan
from stablebptt.flows.gradients import flow_gradients, reference_loss, reference_rollout
from stablebptt.flows.modes import FLOWS, MODE_TABLE, MODES, select_flow, sign_agreement

__all__ = ["FLOWS", "MODES", "MODE_TABLE", "Dynamics", "Plan", "flow_gradients", "reference_loss", "reference_rollout",
           "select_flow", "sign_agreement"]
