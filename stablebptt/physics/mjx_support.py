"""What MJX can simulate: the integrators by name, the support check and putting a model on MJX.

``check_supported(model)`` mirrors MJX's own checks and names the first feature
it cannot simulate with what to change, so no MJX traceback reaches a user;
``put_model`` runs it before ``mjx.put_model``.
"""
from __future__ import annotations

import mujoco
import numpy as np

from stablebptt.errors import InputError
from stablebptt.physics.mjx_internals import collision_driver, mjx
from stablebptt.physics.mjx_internals import types as mjx_types

_ENABLE = mujoco.mjtEnableBit
INTEGRATORS = {"euler": mujoco.mjtIntegrator.mjINT_EULER, "rk4": mujoco.mjtIntegrator.mjINT_RK4,
               "implicitfast": mujoco.mjtIntegrator.mjINT_IMPLICITFAST}
# What to tell a user about the enable flags MJX cannot simulate.
_ENABLE_ADVICE = {int(_ENABLE.mjENBL_OVERRIDE): "contact override: remove <flag override=\"enable\"/>",
                  int(_ENABLE.mjENBL_DIAGEXACT): "exact constraint diagonal: remove <flag diagexact=\"enable\"/>",
                  int(_ENABLE.mjENBL_SPECULATIVE): "speculative contacts: remove <flag speculative=\"enable\"/>"}
_GEOM_NAMES = {int(t): t.name[len("mjGEOM_"):].lower() for t in (
    mujoco.mjtGeom.mjGEOM_PLANE, mujoco.mjtGeom.mjGEOM_HFIELD, mujoco.mjtGeom.mjGEOM_SPHERE,
    mujoco.mjtGeom.mjGEOM_CAPSULE, mujoco.mjtGeom.mjGEOM_ELLIPSOID, mujoco.mjtGeom.mjGEOM_CYLINDER,
    mujoco.mjtGeom.mjGEOM_BOX, mujoco.mjtGeom.mjGEOM_MESH, mujoco.mjtGeom.mjGEOM_SDF)}


def _name(model: mujoco.MjModel, kind, index: int) -> str:
    return mujoco.mj_id2name(model, kind, index) or f"#{index}"


def check_supported(model: mujoco.MjModel) -> None:
    """Raise ``InputError`` naming the first feature of ``model`` that MJX cannot simulate, and what to change.

    Call it on the copy that will be simulated (``lean_model``'s), before
    ``mjx.put_model``: it mirrors MJX's own checks, so no MJX traceback reaches a user.
    """
    def refuse(feature: str):
        raise InputError(f"MJX cannot simulate {feature}")

    if model.nflex:
        refuse("flexible bodies (<flex>, <flexcomp>): remove them")
    for bit, advice in _ENABLE_ADVICE.items():
        if model.opt.enableflags & bit:
            refuse(advice)
    supported_integrators = {int(v) for v in INTEGRATORS.values()}
    if int(model.opt.integrator) not in supported_integrators:
        refuse(f"integrator {mujoco.mjtIntegrator(model.opt.integrator).name[len('mjINT_'):].lower()}: "
               "choose euler, rk4 or implicitfast (--integrator)")
    if int(model.opt.solver) == int(mujoco.mjtSolver.mjSOL_PGS):
        refuse('the PGS constraint solver: set <option solver="Newton"/> or "CG"')
    fluid = model.opt.density > 0 or model.opt.viscosity > 0 or np.any(model.opt.wind)
    if fluid and int(model.opt.integrator) == int(mujoco.mjtIntegrator.mjINT_IMPLICITFAST):
        refuse("fluid forces with the implicitfast integrator: choose euler or rk4 (--integrator)")
    geom = mujoco.mjtObj.mjOBJ_GEOM
    for g1, g2, _ in collision_driver.geom_pairs(model):
        t1, t2 = int(model.geom_type[g1]), int(model.geom_type[g2])
        if not collision_driver.has_collision_fn(t1, t2):
            refuse(f"{_GEOM_NAMES.get(t1, t1)}-{_GEOM_NAMES.get(t2, t2)} contacts (geoms '{_name(model, geom, g1)}' and "
                   f"'{_name(model, geom, g2)}'): change one geom's type, or stop the pair colliding "
                   "(contype/conaffinity or <exclude>)")
        if {t1, t2} & {int(mujoco.mjtGeom.mjGEOM_MESH), int(mujoco.mjtGeom.mjGEOM_HFIELD)} and (
                model.geom_margin[g1] + model.geom_margin[g2] > 0):
            refuse(f"a contact margin on a mesh or height field (geoms '{_name(model, geom, g1)}' and "
                   f"'{_name(model, geom, g2)}'): set margin=\"0\"")
    if np.any(model.actuator_damping) or np.any(model.actuator_dampingpoly) or np.any(model.actuator_armature):
        refuse("an actuator's damping or armature (its damping=, armature= attributes), which MJX's JAX "
               "implementation ignores: remove them, or give the joint its own damping and armature")
    disabled = lambda bit: bool(model.opt.disableflags & bit)  # noqa: E731
    dsbl = mujoco.mjtDisableBit
    if model.opt.noslip_iterations and not disabled(dsbl.mjDSBL_CONSTRAINT) and not (
            disabled(dsbl.mjDSBL_CONTACT) and disabled(dsbl.mjDSBL_FRICTIONLOSS)):  # where it has friction to act on
        refuse('the noslip solver: set <option noslip_iterations="0"/>')
    for values, supported, kind, what in (
            (model.actuator_gaintype, mjx_types.GainType, mujoco.mjtGain, "actuator gain"),
            (model.actuator_biastype, mjx_types.BiasType, mujoco.mjtBias, "actuator bias"),
            (model.actuator_dyntype, mjx_types.DynType, mujoco.mjtDyn, "actuator dynamics"),
            (model.actuator_trntype, mjx_types.TrnType, mujoco.mjtTrn, "actuator transmission"),
            (model.eq_type, mjx_types.EqType, mujoco.mjtEq, "equality constraint"),
            (model.wrap_type, mjx_types.WrapType, mujoco.mjtWrap, "tendon wrap")):
        missing = sorted(set(int(v) for v in values) - set(int(s) for s in supported))
        if missing:
            refuse(f"{what} type {kind(missing[0]).name.split('_', 1)[1].lower()}: replace it")


def put_model(model: mujoco.MjModel):
    """``mjx.put_model`` after ``check_supported``; anything MJX still refuses becomes one ``InputError`` line."""
    check_supported(model)
    try:
        return mjx.put_model(model, impl="jax")
    except NotImplementedError as error:
        raise InputError(f"MJX cannot simulate this model: {error}") from None


def constraint_rows(model) -> int:
    """The rows of MJX's constraint system for ``model`` (every candidate contact's and limit's, active or not):
    the size of the solver's matrices, and so of its per-step work. ``model``: a MuJoCo model or one on MJX."""
    mjx_model = put_model(model) if isinstance(model, mujoco.MjModel) else model
    return int(mjx.make_data(mjx_model)._impl.efc_J.shape[0])

