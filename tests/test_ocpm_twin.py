"""The MuJoCo twin of the over-constrained PM against independent closed forms."""

import mujoco
import numpy as np
import pytest

from pmcal.mechanism.ocpm.config import MACHINE_DIR, default_geometry
from pmcal.mechanism.ocpm.kinematics import limb_ik, nominal_ik, nominal_pose
from pmcal.mechanism.ocpm.params import PAPER_TABLE2, ErrorSet, random_errors
from pmcal.mechanism.rotations import tilt_torsion_angles
from pmcal.twin.ocpm.assembly import _ChainJacobian
from pmcal.twin.ocpm.dynamics import DynamicTwin
from pmcal.twin.ocpm.machine import Twin
from pmcal.twin.ocpm.model import MM, build_model, load_model

G = default_geometry()


def commands(n, theta_max=80.0, seed=0):
    rng = np.random.default_rng(seed)
    phi, theta = rng.uniform(0, 2 * np.pi, n), np.deg2rad(rng.uniform(0, theta_max, n))
    return phi, theta, np.rad2deg(nominal_ik(phi, theta))


def test_model_matches_the_machine_configuration():
    m = load_model()
    d = mujoco.MjData(m)
    mujoco.mj_resetDataKeyframe(m, d, m.key("home").id)
    mujoco.mj_forward(m, d)
    assert m.opt.jacobian == mujoco.mjtJacobian.mjJAC_DENSE
    assert np.abs(d.efc_pos[:12]).max() < 1e-12                 # home keyframe is assembled
    assert m.body("platform").mass[0] == pytest.approx(G.platform_mass)
    assert m.body("platform").ipos * 1e3 == pytest.approx(G.platform_com)
    for j in range(1, 5):
        for k in (1, 2):
            assert m.body(f"limb{j}_link{k}").mass[0] == pytest.approx(G.link_mass)
            assert m.body(f"limb{j}_link{k}").ipos[0] == pytest.approx(G.l / 2 * MM)
    assert [m.actuator(a).name for a in range(m.nu)] == ["motor1", "motor2"]
    for k, name in enumerate(G.target_names):
        assert m.site(name).pos / MM == pytest.approx(G.targets[k])
    for j in range(1, 5):
        eq = m.equality(f"closure_S{j}").id
        assert m.eq_objtype[eq] == mujoco.mjtObj.mjOBJ_SITE      # site-based connects
    scene = mujoco.MjModel.from_xml_path(str(MACHINE_DIR / "scene.xml"))
    assert scene.nq == m.nq


def test_nominal_twin_matches_seed_eq4_and_eq7():
    phi, theta, cmd = commands(250)
    st = Twin().reach(cmd)
    r0, R0 = nominal_pose(phi, theta)
    assert st.converged.all()
    assert np.abs(st.r - r0).max() <= 1e-9                        # mm
    ph, th = tilt_torsion_angles(st.R)
    assert np.rad2deg(np.abs(th - theta)).max() <= 1e-9           # deg
    assert np.rad2deg(np.abs(np.angle(np.exp(1j * (ph - phi))))).max() <= 1e-9
    assert st.closure_residual.max() <= 1e-9


def test_zero_offsets_only_match_the_closed_form_real_ik():
    rng = np.random.default_rng(2)
    _, _, cmd = commands(200, seed=1)
    for _ in range(3):
        params = {"L1.dtheta": rng.uniform(-0.5, 0.5), "L2.dtheta": rng.uniform(-0.5, 0.5)}
        twin = Twin(params)
        st = twin.reach(cmd)
        beta = limb_ik(st.r, st.R, ErrorSet.from_dict(params)).beta
        assert np.rad2deg(np.abs(beta - np.deg2rad(cmd) - np.deg2rad(
            [params["L1.dtheta"], params["L2.dtheta"]]))).max() <= 1e-6
        assert st.closure_residual.max() <= 1e-9


def test_consistent_geometric_errors_in_actuated_limbs_close_every_loop():
    """Errors that keep the machine consistent (here: the mirror-symmetric SS length) close all loops."""
    _, _, cmd = commands(50, seed=3)
    st = Twin({"SS.dh": 0.0, "L1.dtheta": 0.1}).reach(cmd)
    assert st.closure_residual.max() <= 1e-9


def test_closure_residuals_follow_the_stiffness_ratio():
    """With errors in every limb the misfit is shared in proportion to compliance: actuated gaps scale
    as 1 / ratio, passive gaps barely change, SS deflection scales as 1 / ratio."""
    rng = np.random.default_rng(4)
    params = random_errors(rng, 0.5, 0.1)
    _, _, cmd = commands(40, 60, seed=5)
    states = {ratio: Twin(params, stiffness_ratio=ratio).reach(cmd) for ratio in (100.0, 1000.0, 10000.0)}
    act = {k: s.closure_residual[:, :2] for k, s in states.items()}
    pas = {k: s.closure_residual[:, 2:] for k, s in states.items()}
    assert np.median(pas[1000.0]) > 0.05                         # the machine really is inconsistent
    for lo, hi in ((100.0, 1000.0), (1000.0, 10000.0)):
        assert np.median(act[lo] * lo / (act[hi] * hi)) == pytest.approx(1.0, rel=0.03)
        assert np.median(pas[lo] / pas[hi]) == pytest.approx(1.0, abs=0.03)
    assert (act[1000.0] < 0.01 * pas[1000.0].max(axis=1, keepdims=True)).all()


def test_changing_the_stiffness_ratio_keeps_the_passive_closures():
    """A fit may pass through ratios below 1 on its way; the passive closures keep their stiffness and the
    machine comes back exactly to a fresh twin's (a regression: the passive stiffness was once taken as
    the smallest closure stiffness, which a ratio below 1 replaced for good)."""
    params = random_errors(np.random.default_rng(6), 0.5, 0.1)
    _, _, cmd = commands(20, 60, seed=7)
    tw = Twin(params, stiffness_ratio=1000.0)
    k_p = G.passive_closure_stiffness / MM
    for ratio in (1e-3, 0.5, 1e6, 1000.0):
        tw.set_stiffness_ratio(ratio)
        assert np.allclose(tw.stiffness.closure[2:], k_p) and np.allclose(tw.stiffness.closure[:2], ratio * k_p)
    assert np.abs(tw.reach(cmd).targets - Twin(params, stiffness_ratio=1000.0).reach(cmd).targets).max() < 1e-9


def test_assembly_steps_are_capped_and_singular_poses_give_up():
    """Far from the equilibrium (a joint 0.6 rad off) the capped Gauss-Newton steps still reach the
    closed-form pose; a stack with a singular normal matrix gives NaN for that row only."""
    from pmcal.twin.closures import solve_stacked

    phi, theta, cmd = commands(10, 60, seed=8)
    tw = Twin()
    q = tw.initial_qpos(np.deg2rad(cmd))
    q[:, tw.index.qadr_base[2]] += 0.6                       # a passive limb's first joint far off
    st = tw.reach_joint(np.deg2rad(cmd), qpos=q)
    assert st.converged.all() and st.iterations.min() > 3    # 0.6 rad at <= 0.2 rad a step
    assert np.allclose(st.R[:, :, 2], nominal_pose(phi, theta)[1][:, :, 2], atol=1e-9)
    A = np.stack([np.eye(3), np.zeros((3, 3)), 2 * np.eye(3)])
    x = solve_stacked(A, np.ones((3, 3)))
    assert np.allclose(x[0], 1.0) and np.isnan(x[1]).all() and np.allclose(x[2], 0.5)


def test_table2_passive_loops_miss_closing_by_about_1p5_mm():
    """docs/fullchain.md: Table 2 errors in limbs 1-2, perfect passive limbs -> ~1.5 mm at the passive loops."""
    st = Twin(PAPER_TABLE2).reach([[-39.351, -39.351]])
    assert st.closure_residual[0, 2:] == pytest.approx([1.5, 1.5], abs=0.1)
    assert st.closure_residual[0, :2].max() < 0.01


def test_batched_jacobian_equals_mj_jacSite():
    m, idx = build_model(ErrorSet.from_dict(PAPER_TABLE2))
    d = mujoco.MjData(m)
    rng = np.random.default_rng(0)
    d.qpos[:] = m.key_qpos[0] + rng.normal(0, 0.2, m.nq)
    d.qpos[7:11] /= np.linalg.norm(d.qpos[7:11])
    mujoco.mj_kinematics(m, d)
    mujoco.mj_comPos(m, d)
    sites = np.concatenate([idx.site_s1, idx.site_s2])
    Jg = _ChainJacobian(m, sites).gap(d.site_xpos[sites][None], d.xanchor[None], d.xaxis[None], d.xmat[None])[0]
    ref = []
    for a, b in zip(idx.site_s1, idx.site_s2):
        ja, jb = np.zeros((3, m.nv)), np.zeros((3, m.nv))
        mujoco.mj_jacSite(m, d, ja, None, a)
        mujoco.mj_jacSite(m, d, jb, None, b)
        ref.append(ja - jb)
    assert np.abs(np.concatenate(ref) - Jg).max() < 1e-14


def test_compiled_model_edits_equal_an_mjspec_edit_and_recompile():
    """The fast path (body/site edits + mj_setConst) builds the same machine as editing the MjSpec."""
    rng = np.random.default_rng(6)
    e = ErrorSet.from_dict(random_errors(rng, 1.0, 0.3))
    m_fast, _ = build_model(e)
    spec = mujoco.MjSpec.from_file(str(MACHINE_DIR / "ocpm_2dof.xml"))
    for j in range(4):
        for k in (1, 2):
            name = f"limb{j + 1}_link{k}"
            body = spec.body(name)
            body.pos = m_fast.body(name).pos.copy()
            body.alt.type = mujoco.mjtOrientation.mjORIENTATION_QUAT   # drop the XML's euler
            body.quat = m_fast.body(name).quat.copy()
        spec.site(f"limb{j + 1}_S1").pos = [(G.l + e.dl1[j]) * MM, 0, 0]
        spec.site(f"limb{j + 1}_S2").pos = [(G.l + e.dl2[j]) * MM, 0, 0]
    spec.body("platform").pos = m_fast.body("platform").pos.copy()
    spec.joint("platform_ball").pos = np.asarray(e.ss_dc) * MM
    m_spec = spec.compile()
    d1, d2 = mujoco.MjData(m_fast), mujoco.MjData(m_spec)
    q = m_fast.key_qpos[0] + rng.normal(0, 0.1, m_fast.nq)
    q[7:11] /= np.linalg.norm(q[7:11])
    for m, d in ((m_fast, d1), (m_spec, d2)):
        d.qpos[:] = q
        mujoco.mj_forward(m, d)
    assert np.abs(d1.site_xpos - d2.site_xpos).max() < 1e-14
    M1, M2 = np.zeros((m_fast.nv,) * 2), np.zeros((m_fast.nv,) * 2)
    mujoco.mj_fullM(m_fast, d1, M1)
    mujoco.mj_fullM(m_spec, d2, M2)
    assert np.abs(M1 - M2).max() < 1e-12                      # same inertia too


def test_geometric_errors_move_the_model_as_the_closed_form_says():
    """With errors, the first links' sites sit where B_j + (l + dl1) Q_j Ry(beta) e1 puts them."""
    rng = np.random.default_rng(8)
    e = ErrorSet.from_dict(random_errors(rng, 1.0, 0.3))
    _, _, cmd = commands(20, 60, seed=9)
    twin = Twin(e)
    st = twin.reach(cmd)
    ik = limb_ik(st.r, st.R, e, limbs=(1, 2, 3, 4))
    m, idx = twin.model, twin.index
    d = mujoco.MjData(m)
    for i in range(len(cmd)):
        d.qpos[:] = st.qpos[i]
        mujoco.mj_kinematics(m, d)
        # A_j of the closed form equals the platform-side site's link origin
        A_model = d.xpos[idx.link2] / MM
        assert np.abs(A_model - ik.A[i]).max() < 1e-9


def test_dynamic_settling_agrees_with_the_quasi_static_twin_under_gravity():
    twin = Twin(PAPER_TABLE2)
    dyn = DynamicTwin(twin)
    cmd = np.rad2deg(nominal_ik(np.deg2rad(40), np.deg2rad(35)))[0]
    st, info = dyn.settle(cmd, duration=1.0)
    assert info.settled
    sag = np.rad2deg(st.joint[0] - np.deg2rad(cmd) - twin.errors.dtheta[:2])
    assert 1e-4 < np.abs(sag).max() < 0.05                       # servo of finite stiffness sags a little
    static = Twin(PAPER_TABLE2, stiffness_ratio=1e6, gravity=True).reach_joint(st.joint)
    # The gravity load deflects the passive closures by ~2e-5 mm here (stiff machine); the two
    # physics paths agree well below that.
    assert np.abs(static.targets - st.targets).max() < 1e-5     # mm


def test_unreachable_commands_are_refused():
    with pytest.raises(ValueError, match="outside the workspace"):
        Twin().reach([[60.0, -170.0]])
