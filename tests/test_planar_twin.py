"""The planar twin (the generic closed-chain core on mjcf/planar_2dof/chain) against the paper's closed forms
(the independent oracle), and the MJCF files."""

import mujoco
import numpy as np
import pytest

from pmcal.calib.planar.design import boundary_positions
from pmcal.mechanism.planar.geometry import Errors
from pmcal.mechanism.planar.kinematics import actual_position, inverse, mm_vector
from pmcal.twin.planar.config import MODEL_XML, default_machine
from pmcal.twin.planar.twin import PlanarTwin

MM = 1e-3

M = default_machine()
G = M.geometry


def random_errors(rng):
    return Errors(dtheta=np.deg2rad(rng.uniform(-2, 2, 2)), de=rng.uniform(-0.5, 0.5, (2, 2)),
                  dL=rng.uniform(-0.5, 0.5, 2), dl=rng.uniform(-0.5, 0.5, 2), drM=rng.uniform(-2, 2, 2))


def motor_samples(rng, n=80):
    r = np.stack([rng.uniform(-300, 300, n), rng.uniform(-850, -560, n)], 1)
    return inverse(G, r)


@pytest.mark.parametrize("which", ["group1", "random"])
def test_twin_forward_kinematics_and_scale_equal_closed_forms(which):
    rng = np.random.default_rng(3)
    err = M.preset("group1") if which == "group1" else random_errors(rng)
    twin = PlanarTwin(err, M)
    motor = motor_samples(rng)
    poses = twin.assemble(motor)
    real = G.perturbed(err)
    r = actual_position(G, err, motor)
    assert np.abs(poses.r - r).max() <= 1e-9                         # mm
    length = np.linalg.norm(mm_vector(real, r), axis=-1)               # |O1' O2'|
    assert np.abs(poses.length - length).max() <= 1e-9


def test_closed_form_inverse_kinematics_drives_the_twin_to_the_target():
    rng = np.random.default_rng(5)
    err = random_errors(rng)
    twin = PlanarTwin(err, M)
    targets = boundary_positions(M.workspace, 5)
    motor = inverse(G.perturbed(err), targets) - err.dtheta             # the real machine's IK (eq. 3)
    assert np.abs(twin.assemble(motor).r - targets).max() <= 1e-9


def test_platform_stays_translational_with_errors():
    twin = PlanarTwin(random_errors(np.random.default_rng(7)), M)
    poses = twin.assemble(motor_samples(np.random.default_rng(8), 20))
    bid = mujoco.mj_name2id(twin.model, mujoco.mjtObj.mjOBJ_BODY, "platform")
    d = mujoco.MjData(twin.model)
    for q in poses.qpos:
        d.qpos[:] = q
        mujoco.mj_kinematics(twin.model, d)
        # the closures are met to 1e-12 m (ClosedChainTwin.TOL_M) over the 60 mm parallelogram offsets
        assert np.abs(d.xmat[bid].reshape(3, 3) - np.eye(3)).max() < 1e-10


def test_standalone_mjcf_is_the_nominal_machine_of_machine_toml():
    """The XML's numbers are the nominal machine of machine.toml [geometry], and its home keyframe closes."""
    m = mujoco.MjModel.from_xml_path(str(MODEL_XML))
    body = lambda n: m.body_pos[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, n)] / MM  # noqa: E731
    site = lambda n: m.site_pos[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, n)] / MM  # noqa: E731
    plane = lambda v: np.array([v[0], 0.0, v[1]])  # noqa: E731
    np.testing.assert_allclose(body("right_proximal"), plane(G.e[0]), atol=1e-9)
    np.testing.assert_allclose(body("left_proximal"), plane(G.e[1]), atol=1e-9)
    np.testing.assert_allclose([body("right_shaft")[0], body("left_distal")[0]], G.L, atol=1e-9)
    np.testing.assert_allclose([body("platform")[0], site("left_distal_tip")[0]], G.l, atol=1e-9)
    np.testing.assert_allclose(site("O1"), plane(G.c), atol=1e-9)
    np.testing.assert_allclose(site("O2"), plane(-G.d), atol=1e-9)
    d = mujoco.MjData(m)
    mujoco.mj_resetDataKeyframe(m, d, 0)
    mujoco.mj_kinematics(m, d)
    assert np.allclose(d.qpos[[m.joint("right_motor").qposadr[0], m.joint("left_motor").qposadr[0]]], G.home)
    s1, s2 = m.eq_obj1id, m.eq_obj2id
    assert np.abs(d.site_xpos[s1] - d.site_xpos[s2]).max() < 1e-12
    assert np.all(m.eq_objtype == mujoco.mjtObj.mjOBJ_SITE)     # site-based connects


def test_simulation_holds_the_assembled_pose_under_gravity():
    """Real dynamics: position servos hold the motors, soft connects hold the loops. After settling, the
    platform is where the exact assembly puts it for the motor angles the servos really hold; the
    difference is bounded by the constraint softness (gaps of a few µm)."""
    twin = PlanarTwin(M.preset("group1"), M)
    chain = twin.chain
    motor = inverse(G, np.array([150.0, -720.0]))
    q = twin.assemble(motor[None]).qpos[0]
    m = twin.model                                      # the model with group 1's frame errors
    d = mujoco.MjData(m)
    d.qpos[:] = q
    d.ctrl[:] = q[chain.motor_qadr]                     # the servos hold the joints (zero offsets included)
    for _ in range(1500):
        mujoco.mj_step(m, d)
    gaps = np.linalg.norm(d.site_xpos[m.eq_obj1id] - d.site_xpos[m.eq_obj2id], axis=1)
    assert gaps.max() < 2e-5                                           # m
    held = d.qpos[chain.motor_qadr] - M.preset("group1").dtheta       # back to commands
    exact = twin.assemble(held[None]).r[0]
    assert np.linalg.norm(chain.task_of(d.qpos[None])[0] - exact) < 0.02   # mm
