"""The planar MuJoCo twin against the closed forms (the independent oracle), and the MJCF files."""

import mujoco
import numpy as np
import pytest

from pmcal.calib.planar.design import boundary_positions
from pmcal.mechanism.planar.geometry import Errors
from pmcal.mechanism.planar.kinematics import actual_position, inverse, mm_vector
from pmcal.twin.planar.config import MODEL_XML, default_machine
from pmcal.twin.planar.model import build_model, scale_reference
from pmcal.twin.planar.twin import PlanarTwin

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
    assert poses.converged.all() and poses.gap.max() < 1e-12
    real = G.perturbed(err)
    r = actual_position(G, err, motor)
    assert np.abs(poses.r - r).max() <= 1e-9                         # mm
    length = np.linalg.norm(mm_vector(real, r), axis=-1)               # |O1' O2'|
    assert np.abs(poses.length - length).max() <= 1e-9
    assert np.abs(poses.scale - (length - scale_reference(M))).max() <= 1e-9


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
        assert np.abs(d.xmat[bid].reshape(3, 3) - np.eye(3)).max() < 1e-12


def test_standalone_mjcf_is_the_nominal_machine_of_machine_toml():
    """The XML's numbers (for viewing it alone) agree with machine.toml, and its home keyframe closes."""
    m_xml = mujoco.MjModel.from_xml_path(str(MODEL_XML))
    m_cfg, idx = build_model(M)
    assert np.allclose(m_xml.body_pos, m_cfg.body_pos, atol=1e-12)
    assert np.allclose(m_xml.site_pos, m_cfg.site_pos, atol=1e-12)
    assert np.allclose(m_xml.body_quat, m_cfg.body_quat, atol=1e-12)
    d = mujoco.MjData(m_xml)
    mujoco.mj_resetDataKeyframe(m_xml, d, 0)
    mujoco.mj_kinematics(m_xml, d)
    gaps = d.site_xpos[idx.site_s1] - d.site_xpos[idx.site_s2]
    assert np.abs(gaps).max() < 1e-12
    assert np.all(m_xml.eq_objtype == mujoco.mjtObj.mjOBJ_SITE)     # site-based connects


def test_simulation_holds_the_assembled_pose_under_gravity():
    """Real dynamics: position servos hold the motors, soft connects hold the loops. After settling, the
    platform is where the exact assembly puts it for the motor angles the servos really hold; the
    difference is bounded by the constraint softness (gaps of a few µm)."""
    twin = PlanarTwin(M.preset("group1"), M)
    m, d = twin.model, mujoco.MjData(twin.model)
    motor = inverse(G, np.array([150.0, -720.0]))
    d.qpos[:] = twin.assemble(motor[None]).qpos[0]
    d.ctrl[:] = motor
    for _ in range(1500):
        mujoco.mj_step(m, d)
    gaps = np.linalg.norm(d.site_xpos[twin.index.site_s1] - d.site_xpos[twin.index.site_s2], axis=1)
    assert gaps.max() < 2e-5                                           # m
    held = d.qpos[twin.index.qadr_base]
    exact = twin.assemble(held[None]).r[0]
    assert np.linalg.norm(twin.to_plane(d.site_xpos[twin.index.site_P]) - exact) < 0.02   # mm
