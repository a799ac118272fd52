"""The physics: a MuJoCo model simulated with only the effects its scene calls for.

- ``scene``: what a model can produce at all (``effects.SceneEffects``), the lean model, the one-line summary.
- ``simulator``: ``build(model, config)`` owns a model and returns its step, as a Playground env does.
- ``lean_step``: the step over the minimal state; ``rigid_body``: the rigid-body terms generated per scene.
- ``symmetries``: Jacobian columns a scene fixes; ``constraint_derivatives``: the constraint solver
  differentiated implicitly; ``mjx_support`` and ``mjx_internals``: what MJX supports and the parts of it used.
- ``integrators``: the hand-written integrators; ``mujoco_log``: MuJoCo's warnings, never a log file.
"""
