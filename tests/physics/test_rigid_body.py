"""The step generated body by body (stablebptt/physics/rigid_body.py) is MuJoCo's physics and MJX's derivative.

Trajectories are compared with MuJoCo's C step (mujoco.mj_step) in float64 for
every model in models/ and for a tree that exercises each term the generator
writes out; Jacobians with plain autodiff through MJX's own stages. A scene with
contacts, joint limits and friction loss feeds the generated terms to MJX's
constraint stages: each of its steps is compared with MuJoCo's from the same
state, and its Jacobians with those of MJX's stages.
"""
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

# Every term the generator writes: a tilted base with a slide and an off-centre hinge in one
from stablebptt.physics import lean_step, rigid_body, scene
from stablebptt.physics.array_terms import ArrayTerms
from stablebptt.physics.written_out import WrittenOut

from conftest import ROOT

# body, a welded body without joints, branches, rotated inertias, armature, springs, joint damping
# (Euler's implicit damping), a clamped motor with a gear, a position servo with kv, a force limit,
# and gravity off the z axis.
BRANCHES = """<mujoco model="branches">
  <option timestep="0.005" integrator="{integrator}" gravity="0.3 -0.2 -9.81"/>
  <worldbody>
    <body name="base" pos="0.1 0.2 0.3" quat="0.9 0.1 0.3 0.2">
      <joint name="slide" type="slide" axis="1 0.2 0" damping="0.3" armature="0.05"/>
      <joint name="twist" type="hinge" axis="0 0 1" pos="0.05 0 0.1" stiffness="2" springref="0.3"/>
      <inertial pos="0.02 0.01 -0.03" quat="0.8 0.2 0.1 0.4" mass="1.3" diaginertia="0.02 0.03 0.04"/>
      <body name="arm" pos="0.2 0 0" euler="10 20 30">
        <joint name="shoulder" type="hinge" axis="0 1 0.3" pos="0 0 0.05" damping="0.1"/>
        <inertial pos="0.1 0 0.2" mass="0.4" diaginertia="0.004 0.005 0.002"/>
        <body name="welded" pos="0 0.1 0.3">
          <inertial pos="0 0.05 0" mass="0.2" diaginertia="0.001 0.002 0.003"/>
          <body name="hand" pos="0 0 0.2">
            <joint name="wrist" type="hinge" axis="1 0 0"/>
            <inertial pos="0 0 0.1" mass="0.1" diaginertia="0.001 0.001 0.0005"/>
          </body>
        </body>
      </body>
      <body name="leg" pos="-0.2 0 0">
        <joint name="hip" type="hinge" axis="0 1 0" armature="0.01"/>
        <joint name="knee" type="slide" axis="0 0 1" stiffness="5"/>
        <inertial pos="-0.1 0 0.2" mass="0.5" diaginertia="0.004 0.005 0.002"/>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor joint="slide" gear="2" ctrlrange="-0.5 0.5" ctrllimited="true"/>
    <position joint="shoulder" kp="3" kv="0.2" ctrlrange="-1 1"/>
    <motor joint="hip" forcelimited="true" forcerange="-0.3 0.3"/>
  </actuator>
</mujoco>"""

MODELS = {f"cartpole_{n}": lambda n=n: mujoco.MjModel.from_xml_path(str(ROOT / "stablebptt" / "models" / f"cartpole_{n}.xml"))
          for n in (1, 2, 3, 4)}
MODELS["branches, Euler"] = lambda: mujoco.MjModel.from_xml_string(BRANCHES.format(integrator="Euler"))
MODELS["branches, RK4"] = lambda: mujoco.MjModel.from_xml_string(BRANCHES.format(integrator="RK4"))
# Its hip motor pulls a fixed tendon of the hip and the shoulder instead.
TENDON_DRIVEN = BRANCHES.format(integrator="Euler").replace(
    '<motor joint="hip"', '<motor tendon="pull" gear="1.5"').replace(
    "<actuator>", '<tendon><fixed name="pull"><joint joint="hip" coef="0.5"/><joint joint="shoulder" coef="-0.8"/>'
    '</fixed></tendon>\n  <actuator>')
MODELS["branches, tendon-driven"] = lambda: mujoco.MjModel.from_xml_string(TENDON_DRIVEN)


def lean_of(model):
    effects = scene.analyze(model)
    return scene.lean_model(model, effects), effects


@pytest.mark.parametrize("name", MODELS)
def test_the_generated_step_follows_mujocos_c_step(x64, form, name):
    model = MODELS[name]()
    lean, effects = lean_of(model)
    assert lean_step.generated_step_applies(lean, effects)
    step = jax.jit(lean_step.make_step(lean, effects))
    rng = np.random.default_rng(0)
    data = mujoco.MjData(model)
    data.qpos[:] = model.qpos0 + rng.uniform(-1, 1, model.nq)
    data.qvel[:] = rng.uniform(-2, 2, model.nv)
    state = lean_step.State(jnp.array(data.qpos), jnp.array(data.qvel), jnp.zeros(0))
    for _ in range(200):  # controls beyond the ranges test the clamps
        data.ctrl[:] = rng.uniform(-2, 2, model.nu)
        state = step(state, jnp.array(data.ctrl))
        mujoco.mj_step(model, data)
        scale = max(1.0, np.abs(data.qvel).max())
        np.testing.assert_allclose(state.qpos, data.qpos, rtol=0, atol=1e-10 * scale)
        np.testing.assert_allclose(state.qvel, data.qvel, rtol=0, atol=1e-10 * scale)
    assert np.abs(data.qvel).max() > 0.1  # it moved


def random_point(model, seed):
    rng = np.random.default_rng(seed)
    state = lean_step.State(jnp.array(model.qpos0 + rng.normal(size=model.nq)), jnp.array(rng.normal(size=model.nv)),
                        jnp.zeros(0))
    return state, jnp.array(rng.uniform(-0.4, 0.4, model.nu))  # inside the clamps: differentiable there


def test_the_generated_steps_derivative_is_plain_autodiff_through_mjx(x64, form):
    """Reverse mode through the inverse-dynamics derivative of a branching tree gives MJX's Jacobians
    (forward mode, which differentiates the same inverse dynamics, on the chains of cartpole_3 in
    tests/tasks/test_cartpole.py and cartpole_2 with RK4 below)."""
    model = MODELS["branches, Euler"]()
    lean, effects = lean_of(model)
    generated = lean_step.make_step(lean, effects)
    mjx_autodiff = lean_step.make_step(lean, effects, "stages", implicit=False)
    state, control = random_point(model, 1)
    expected = jax.jit(jax.jacfwd(mjx_autodiff, argnums=(0, 1)))(state, control)
    got = jax.jit(jax.jacrev(generated, argnums=(0, 1)))(state, control)
    for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(expected)):
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-11)
    assert np.abs(np.asarray(expected.qvel[0].qpos)).max() > 1e-3  # d qvel' / d qpos is not trivial


def test_rk4s_derivative_passes_its_stages(x64):
    """RK4 chains four accelerations: its Jacobian against central differences of the step itself."""
    model = MODELS["cartpole_2"]()
    effects = scene.analyze(model)
    lean = scene.lean_model(model, effects, integrator="rk4")
    assert lean_step.generated_step_applies(lean, effects)
    step = lean_step.make_step(lean, effects)
    state, control = random_point(model, 2)
    for jacobian in (jax.jacfwd, jax.jacrev):
        assert_central_differences(step, (state.qpos, state.qvel, control), jacobian, rtol=1e-6, atol=1e-8)


def assert_central_differences(step, inputs, jacobian, rtol, atol):
    """``jacobian`` (jax.jacfwd or jacrev) of ``step`` at ``inputs`` = (qpos, qvel, ctrl) against central
    differences of the step itself; returns the Jacobian's blocks."""
    flat = jax.jit(lambda q, v, u: jnp.concatenate(jax.tree.leaves(step(lean_step.State(q, v, jnp.zeros(0)), u))))
    got = jax.jit(jacobian(flat, argnums=(0, 1, 2)))(*inputs)
    for argument, block in enumerate(got):
        columns = []
        for k in range(inputs[argument].shape[0]):
            shifted = lambda e: [x + e * (i == argument) * jnp.eye(x.shape[0])[k] for i, x in enumerate(inputs)]
            columns.append((flat(*shifted(1e-6)) - flat(*shifted(-1e-6))) / 2e-6)
        np.testing.assert_allclose(block, np.stack(columns, axis=1), rtol=rtol, atol=atol)
    return got


# A planar hopper that lands on its capsules: contacts, two limited joints, friction loss on
# one, a spring, dampers, armature and clamped motors.
HOPPING = """<mujoco model="hopping">
  <option timestep="0.005" integrator="{integrator}"/>
  <worldbody>
    <geom name="floor" type="plane" size="5 5 0.1"/>
    <body name="torso" pos="0 0 0.4">
      <joint name="rootx" type="slide" axis="1 0 0" damping="0.1"/>
      <joint name="rootz" type="slide" axis="0 0 1"/>
      <joint name="rooty" type="hinge" axis="0 1 0" frictionloss="0.05"/>
      <geom type="capsule" fromto="0 0 0 0 0 0.3" size="0.05" mass="2"/>
      <body name="thigh" euler="0 20 0">
        <joint name="hip" type="hinge" axis="0 1 0" range="-30 30" damping="0.2" armature="0.01"/>
        <geom type="capsule" fromto="0 0 0 0 0 -0.25" size="0.04" mass="1"/>
        <body name="foot" pos="0 0 -0.25">
          <joint name="ankle" type="hinge" axis="0 1 0" range="-20 40" stiffness="3"/>
          <geom type="capsule" fromto="-0.05 0 -0.02 0.15 0 -0.02" size="0.02" mass="0.5"/>
        </body>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor joint="hip" gear="5" ctrlrange="-1 1" ctrllimited="true"/>
    <motor joint="ankle" gear="3" ctrlrange="-1 1" ctrllimited="true"/>
  </actuator>
</mujoco>"""


# The branched tree against a floor and a mocap box: a hand with a limited, offset wrist under
# friction loss, in bodies of several joints, a welded body and rotated frames.
BRANCHES_IN_CONTACT = BRANCHES.format(integrator="Euler").replace(
    '<joint name="wrist" type="hinge" axis="1 0 0"/>',
    '<joint name="wrist" type="hinge" axis="1 0 0" pos="0 0.02 0" range="-0.5 0.5" frictionloss="0.02"/>'
    '<geom type="sphere" size="0.06" pos="0 0 0.1"/>').replace(
    "<worldbody>", '<worldbody><geom type="plane" size="5 5 0.1" pos="0 0 0.55"/>'
    '<body name="target" mocap="true" pos="0.3 0.1 0.7"><geom type="box" size="0.05 0.05 0.05"/></body>')
# A floating torso on a free joint, an arm on a ball joint with friction loss, a limited elbow, and
# a hand on a slide and a limited ball joint: quaternions in the kinematics, three-dof groups in
# Newton-Euler, MJX's Euler integrating on the sphere.
HAND = """          <body name="hand" pos="0.15 0 0" euler="0 30 0">
            <joint name="twist" type="slide" axis="1 0 0" range="-0.02 0.02"/>
            <joint name="wrist" type="ball" pos="0.01 0 0" range="0 40" damping="0.02"/>
            <geom type="sphere" size="0.04" pos="0.03 0 0" mass="0.2"/>
          </body>
"""
FLOATING = """<mujoco model="floating">
  <option timestep="0.005" gravity="0.3 -0.2 -9.81"/>
  <worldbody>
    <geom name="floor" type="plane" size="5 5 0.1"/>
    <body name="torso" pos="0.1 0.2 0.35" quat="0.9 0.1 0.3 0.2">
      <joint name="root" type="free" damping="0.01"/>
      <geom type="capsule" fromto="-0.1 0 0 0.1 0 0" size="0.05" mass="2"/>
      <body name="arm" pos="0.12 0 0" euler="10 20 30">
        <joint name="shoulder" type="ball" pos="0 0 0.02" damping="0.05" armature="0.01" frictionloss="0.01"/>
        <geom type="capsule" fromto="0 0 0 0.2 0 0" size="0.03" mass="0.5"/>
        <body name="forearm" pos="0.2 0 0">
          <joint name="elbow" type="hinge" axis="0 1 0" range="-30 30"/>
          <geom type="capsule" fromto="0 0 0 0.15 0 0" size="0.025" mass="0.3"/>
          <body name="hand" pos="0.15 0 0" euler="0 30 0">
            <joint name="twist" type="slide" axis="1 0 0" range="-0.02 0.02"/>
            <joint name="wrist" type="ball" pos="0.01 0 0" range="0 40" damping="0.02"/>
            <geom type="sphere" size="0.04" pos="0.03 0 0" mass="0.2"/>
          </body>
        </body>
      </body>
      <body name="leg" pos="-0.1 0 -0.05">
        <joint name="hip" type="hinge" axis="1 0 0" range="-40 40" stiffness="2" damping="0.1"/>
        <geom type="capsule" fromto="0 0 0 0 0 -0.3" size="0.03" mass="0.6"/>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor joint="elbow" gear="2" ctrlrange="-1 1" ctrllimited="true"/>
    <motor joint="hip" ctrlrange="-1 1" ctrllimited="true"/>
  </actuator>
</mujoco>"""
LEG = """      <body name="leg" pos="-0.1 0 -0.05">
        <joint name="hip" type="hinge" axis="1 0 0" range="-40 40" stiffness="2" damping="0.1"/>
        <geom type="capsule" fromto="0 0 0 0 0 -0.3" size="0.03" mass="0.6"/>
      </body>
"""
# The torso and its arm (10 dofs), within the size a GPU writes the terms out (WRITTEN_OUT_DOFS), a free
# and a ball joint still in it. Written out, the 15-dof scene compiles for minutes and is never so built.
FLOATING_ARM = FLOATING.replace(HAND, "").replace(LEG, "").replace(
    '    <motor joint="hip" ctrlrange="-1 1" ctrllimited="true"/>\n', "")
CONSTRAINED = {"hopping, Euler": HOPPING.format(integrator="Euler"), "hopping, RK4": HOPPING.format(integrator="RK4"),
               "branches in contact": BRANCHES_IN_CONTACT, "floating": FLOATING}


@pytest.mark.parametrize("backend, six_dofs", [("cpu", ArrayTerms), ("gpu", WrittenOut)])
def test_the_terms_of_a_few_dofs_are_written_out_and_more_in_arrays(monkeypatch, backend, six_dofs):
    monkeypatch.setattr(jax, "default_backend", lambda: backend)
    assert isinstance(rigid_body.make_scene(MODELS["cartpole_4"]()), WrittenOut)  # 5 dofs
    assert isinstance(rigid_body.make_scene(MODELS["branches, Euler"]()), six_dofs)
    assert isinstance(rigid_body.make_scene(mujoco.MjModel.from_xml_string(FLOATING)), ArrayTerms)  # 15 dofs


# A ball on slides tethered to a cup on limited slides by a limited spatial tendon, as dm_control's
# ball_in_cup: the ball falls until the string is taut, and the tendon's limit row holds it.
TETHERED = """<mujoco model="tethered">
  <option timestep="0.005"/>
  <worldbody>
    <geom name="floor" type="plane" size="5 5 0.1"/>
    <body name="cup" pos="0 0 0.6">
      <joint name="cup_x" type="slide" axis="1 0 0" damping="0.5" range="-0.3 0.3"/>
      <joint name="cup_z" type="slide" axis="0 0 1" damping="0.5" range="-0.2 0.2"/>
      <geom type="capsule" fromto="-0.05 0 0 0.05 0 0" size="0.02" mass="0.5"/>
      <site name="cup" pos="0 0 -0.03"/>
    </body>
    <body name="ball" pos="0.05 0 0.35">
      <joint name="ball_x" type="slide" axis="1 0 0"/>
      <joint name="ball_z" type="slide" axis="0 0 1"/>
      <geom type="sphere" size="0.03" mass="0.1"/>
      <site name="ball"/>
    </body>
  </worldbody>
  <tendon><spatial name="string" limited="true" range="0 0.3"><site site="ball"/><site site="cup"/></spatial></tendon>
  <actuator>
    <motor joint="cup_x" gear="5" ctrlrange="-1 1" ctrllimited="true"/>
    <motor joint="cup_z" gear="5" ctrlrange="-1 1" ctrllimited="true"/>
  </actuator>
</mujoco>"""


def steps_from_mujocos_states(step, model, data, rng, steps=200):
    """``steps`` steps of ``step``, each from the state ``mj_step`` reached, so that a contact's chaos does
    not compound the solvers' tolerances, against ``mj_step``; returns the constraint rows' types seen."""
    rows = set()
    for _ in range(steps):
        data.ctrl[:] = rng.uniform(-2, 2, model.nu)
        state = step(lean_step.State(jnp.array(data.qpos), jnp.array(data.qvel), jnp.zeros(0)), jnp.array(data.ctrl))
        mujoco.mj_step(model, data)
        rows |= set(data.efc_type[:data.nefc].tolist())
        scale = max(1.0, np.abs(data.qvel).max())
        np.testing.assert_allclose(state.qpos, data.qpos, rtol=0, atol=1e-10 * scale)
        np.testing.assert_allclose(state.qvel, data.qvel, rtol=0, atol=1e-9 * scale)
    return rows


def test_a_limited_spatial_tendon_steps_as_mujocos_c_step(x64, form):
    """The tendon's length and moments are MJX's, from the generated site frames; its limit row is
    MJX's too. Every step from the state MuJoCo reached, against ``mj_step``."""
    model = mujoco.MjModel.from_xml_string(TETHERED)
    lean, effects = lean_of(model)
    assert effects.tendons and effects.tendon_limits and lean_step.generated_step_applies(lean, effects)
    step = jax.jit(lean_step.make_step(lean, effects))
    rng = np.random.default_rng(0)
    data = mujoco.MjData(model)
    rows = steps_from_mujocos_states(step, model, data, rng)
    assert int(mujoco.mjtConstraint.mjCNSTR_LIMIT_TENDON) in rows


@pytest.mark.parametrize("form", [WrittenOut, ArrayTerms], ids=["written-out", "arrays"])
@pytest.mark.parametrize("name", ["branches in contact", "floating", "tethered"])
def test_both_forms_of_the_rigid_body_terms_are_mujocos(x64, form, name):
    """Each term MJX's constraint stages read, in either form, against MuJoCo's own at a moving state
    with turned quaternions (not normalised: the kinematics normalises them as MuJoCo's does)."""
    model = mujoco.MjModel.from_xml_string({**CONSTRAINED, "tethered": TETHERED}[name])
    rng = np.random.default_rng(3)
    data = mujoco.MjData(model)
    data.qpos[:] = model.qpos0 + rng.uniform(-0.5, 0.5, model.nq)
    data.qvel[:], data.ctrl[:] = rng.uniform(-2, 2, model.nv), rng.uniform(-0.5, 0.5, model.nu)
    qpos = data.qpos.copy()
    mujoco.mj_forward(model, data)
    terms = jax.jit(form(model).rigid_body)(jnp.array(qpos), jnp.array(data.qvel), jnp.array(data.ctrl))
    mass_matrix = np.zeros((model.nv, model.nv))
    mujoco.mj_fullM(model, data, mass_matrix)
    expected = {"xpos": data.xpos, "xmat": data.xmat.reshape(-1, 3, 3), "geom_xpos": data.geom_xpos,
                "geom_xmat": data.geom_xmat.reshape(-1, 3, 3), "site_xpos": data.site_xpos,
                "site_xmat": data.site_xmat.reshape(-1, 3, 3), "subtree_com": data.subtree_com, "cdof": data.cdof,
                "mass_matrix": mass_matrix, "qfrc_smooth": data.qfrc_smooth, "qacc_smooth": data.qacc_smooth}
    for field, value in expected.items():
        np.testing.assert_allclose(getattr(terms, field), value, rtol=1e-10, atol=1e-10, err_msg=field)
    assert np.abs(data.qacc_smooth).max() > 1.0


# The floating scene's written-out terms and RK4's hopper in arrays are left to the other form: each
# form's terms of the floating body are MuJoCo's (test_both_forms_of_the_rigid_body_terms_are_mujocos),
# and RK4 combines the same constrained accelerations in either.
@pytest.mark.parametrize("form, name", [(form, name) for form in ("written out", "in arrays") for name in CONSTRAINED
                                        if (form, name) not in (("written out", "floating"), ("in arrays", "hopping, RK4"))],
                         indirect=["form"])
def test_the_generated_step_with_constraints_takes_mujocos_c_steps(x64, form, name):
    """Every step from the state MuJoCo reached, so that a contact's chaos does not compound the solvers'
    tolerances: the hopper falls, lands and kicks against its limits; the branches swing into the floor."""
    model = mujoco.MjModel.from_xml_string(CONSTRAINED[name])
    lean, effects = lean_of(model)
    assert effects.contacts and effects.joint_limits and effects.friction_loss
    assert lean_step.generated_step_applies(lean, effects)
    step = jax.jit(lean_step.make_step(lean, effects))
    rng = np.random.default_rng(0)
    data = mujoco.MjData(model)
    if name == "branches in contact":  # moving from the start, as the contact-free test above
        data.qpos[:] = model.qpos0 + rng.uniform(-1, 1, model.nq)
        data.qvel[:] = rng.uniform(-2, 2, model.nv)
    if name == "floating":  # faster, a ball limit's row is solved to MJX's tolerance, not MuJoCo's
        data.qvel[:] = rng.uniform(-1, 1, model.nv)
    rows = steps_from_mujocos_states(step, model, data, rng)
    kinds = mujoco.mjtConstraint
    assert {int(kinds.mjCNSTR_FRICTION_DOF), int(kinds.mjCNSTR_LIMIT_JOINT)} <= rows
    assert rows & {int(kinds.mjCNSTR_CONTACT_PYRAMIDAL), int(kinds.mjCNSTR_CONTACT_ELLIPTIC)}


# The hopper's foot on the floor and its hip just past its limit, moving, with a control inside the clamps.
IN_CONTACT_QPOS = [0.1, -0.26, 0.2, np.radians(30.2), 0.1]
IN_CONTACT_QVEL = [0.5, -0.3, 0.4, 0.2, -0.1]
IN_CONTACT_CONTROL = [0.3, -0.2]


# The branches in contact, coupled: a joint equality (a quadratic in the other joint) and a fixed tendon's
# equality; actuators on fixed tendons beside the joints', one a position servo whose length is the tendon's.
# As manipulator's grasp and coupling. LOOPED adds a connect that holds the leg's foot to the hand.
COUPLED = BRANCHES_IN_CONTACT.replace(
    "<actuator>", """<tendon>
    <fixed name="pull"><joint joint="hip" coef="0.5"/><joint joint="shoulder" coef="-0.8"/></fixed>
    <fixed name="couple"><joint joint="twist" coef="1"/><joint joint="knee" coef="2"/></fixed>
  </tendon>
  <equality>
    <joint joint1="wrist" joint2="shoulder" polycoef="0.1 0.5 0.3 0 0"/>
    <tendon tendon1="couple" solref="0.01 1"/>
  </equality>
  <actuator>
    <position tendon="pull" kp="4" kv="0.3" ctrlrange="-1 1"/>
    <motor tendon="couple" gear="3" ctrlrange="-1 1" ctrllimited="true"/>""")
LOOPED = COUPLED.replace("</equality>", '<connect body1="leg" body2="hand" anchor="-0.1 0 0.2"/></equality>')


def coupled_scene(source):
    model = mujoco.MjModel.from_xml_string(source)
    lean, effects = lean_of(model)
    assert effects.equality and lean_step.generated_step_applies(lean, effects)
    data = mujoco.MjData(model)
    data.qvel[:] = np.random.default_rng(0).uniform(-1, 1, model.nv)
    return model, lean, effects, data


def test_fixed_tendon_actuators_and_equality_constraints_step_as_mujocos_c_step(x64, form):
    """The actuators' lengths and moments on fixed tendons are generated; the equality rows are MJX's, fed
    the generated frames and MJX's tendon lengths. Every step from the state MuJoCo reached, against
    ``mj_step``."""
    model, lean, effects, data = coupled_scene(COUPLED)
    rows = steps_from_mujocos_states(jax.jit(lean_step.make_step(lean, effects)), model, data, np.random.default_rng(1))
    assert int(mujoco.mjtConstraint.mjCNSTR_EQUALITY) in rows
    assert np.abs(data.actuator_force[:2]).min() > 0  # both tendon actuators pulled


WELDED = BRANCHES.format(integrator="Euler").replace(
    "</worldbody>", '</worldbody>\n  <equality><weld body1="leg" body2="hand"/></equality>')


@pytest.mark.parametrize("source, edit, reason", [
    (WELDED, None, "weld equality constraints"),
    (BRANCHES.format(integrator="implicitfast"), None, "mjINT_IMPLICITFAST integrator"),
    (BRANCHES.format(integrator="Euler").replace('type="hinge" axis="1 0 0"', 'type="ball"'), None,
     "free or ball joints"),
    (BRANCHES.format(integrator="Euler"), lambda m: m.body_gravcomp.__setitem__(2, 1.0), "gravity compensation"),
    (FLOATING.replace("<option ", '<option integrator="RK4" '), None, "free or ball joints with an integrator"),
    (TETHERED.replace('range="0 0.3"', 'range="0 0.3" stiffness="10"'), None, "tendons with stiffness"),
    (FLOATING.replace('name="wrist" type="ball"', 'name="wrist" type="ball" stiffness="1"'), None,
     "springs on free or ball joints"),
    (TENDON_DRIVEN.replace('<fixed name="pull"', '<fixed name="pull" actuatorfrcrange="-0.05 0.05"'), None,
     "actuator force limits on tendons"),
    (TETHERED.replace("</actuator>", '<motor tendon="string"/></actuator>'), None,
     "actuators other than fixed-gain actuators of joints or fixed tendons"),
    (FLOATING.replace('<joint name="root" type="free" damping="0.01"/>',
                      '<joint name="root" type="free" damping="0.01"/><site name="thrust"/>').replace(
        "</actuator>", '<general site="thrust" gear="0 0 1 0 0 0"/></actuator>'), None,
     "actuators other than fixed-gain actuators of joints or fixed tendons"),
])
def test_scenes_the_generator_does_not_cover_are_refused_by_it_and_take_mjxs_step(source, edit, reason):
    model = mujoco.MjModel.from_xml_string(source)
    if edit:
        edit(model)
    lean, effects = lean_of(model)
    assert reason in rigid_body.unsupported(lean, effects)
    assert not lean_step.generated_step_applies(lean, effects)
    # The default pipeline then is MJX's: its step runs and stays finite. A floating body's MJX step in
    # contact compiles for a minute or more on a CPU: there it is only traced, which builds every stage.
    step = lean_step.make_step(lean, effects)
    initial = lean_step.initial_state(lean)
    if 'type="free"' in source:
        shapes = jax.eval_shape(step, initial, jnp.zeros(lean.nu))
        assert shapes.qpos.shape == initial.qpos.shape and shapes.qvel.shape == initial.qvel.shape
        return
    state = jax.jit(step)(initial, jnp.zeros(lean.nu))
    assert np.all(np.isfinite(state.qpos)) and np.all(np.isfinite(state.qvel))
