"""Physical effects in the twin against independent computations (twin/ocpm/effects.py, docs/effects.md)."""

import json

import numpy as np
import pytest

from pmcal.mechanism.ocpm.config import default_geometry
from pmcal.mechanism.ocpm.effects import with_context
from pmcal.twin.ocpm.effect_model import EffectChainModel
from pmcal.mechanism.ocpm.kinematics import limb_ik, nominal_fk, nominal_ik, nominal_pose
from pmcal.mechanism.ocpm.params import PAPER_TABLE2, ErrorSet, is_angular, random_errors
from pmcal.cli import main
from pmcal.ocpm.io import read_measurements
from pmcal.twin.ocpm.dynamics import DynamicTwin
from pmcal.apps.ocpm.effect_scenarios import parse_effects
from pmcal.twin.ocpm.effects import (EffectTwin, Effects, HeavyTailedTracker, add_payload, motor_torques, nominal_commands,
                          passive_errors, plan_effect_campaign)
from pmcal.twin.ocpm.machine import Twin
from pmcal.twin.ocpm.model import MM
from pmcal.twin.tracker import LaserTracker

G = default_geometry()


def commands(n, theta_max=60.0, seed=0):
    rng = np.random.default_rng(seed)
    return np.rad2deg(nominal_ik(rng.uniform(0, 2 * np.pi, n), np.deg2rad(rng.uniform(0, theta_max, n))))


def potential(theta_rad, payload_kg):
    """Gravity potential (J) of the nominal machine at motor angles (N, 2) rad, from the closed-form
    kinematics and the MJCF model's inertia: platform 6 kg at (0, 0, 40) mm, payload at the top centre, every
    link 0.5 kg at its middle, the SS link at the middle of O-C_E."""
    phi, th = nominal_fk(theta_rad, G)
    r, R = nominal_pose(phi, th, G)
    ik = limb_ik(r, R, None, G, limbs=(1, 2, 3, 4))
    B = G.base_points()[None]
    z = lambda p: p[..., 2] * MM  # noqa: E731
    U = G.platform_mass * z(r + R @ G.platform_com) + payload_kg * z(r + R @ np.array([0, 0, G.hs]))
    U = U + G.link_mass * (z((B + ik.S) / 2).sum(-1) + z((ik.S + ik.A) / 2).sum(-1)) + G.ss_mass * z(r / 2)
    return 9.81 * U


def gravity_torque(theta_rad, payload_kg, h=1e-6):
    """dU/dtheta (N, 2) N m by central differences of the closed-form potential (virtual work)."""
    g = np.zeros_like(theta_rad)
    for j in range(2):
        d = np.zeros(2)
        d[j] = h
        g[:, j] = (potential(theta_rad + d, payload_kg) - potential(theta_rad - d, payload_kg)) / (2 * h)
    return g


@pytest.mark.parametrize("payload", [0.0, 10.0])
def test_joint_compliance_deflects_by_gravity_torque_over_stiffness(payload):
    """Nominal machine (no internal forces): the series springs twist by -tau/K with tau the closed-form
    virtual-work gravity torque; the fixed point K d + tau(theta + d) = 0 agrees to 1e-4."""
    cmd = commands(8)
    K = 5e4
    st = EffectTwin(None, Effects(joint_compliance=(K, K))).reach(cmd, payload_kg=np.full(8, payload))
    defl = st.joint - np.deg2rad(cmd)
    d = np.zeros_like(defl)
    for _ in range(5):
        d = -gravity_torque(np.deg2rad(cmd) + d, payload) / K
    assert np.abs(d).max() > 1e-4                                   # a real deflection (20..60 arcsec)
    assert np.abs(defl - d).max() < 1e-4 * np.abs(d).max()
    # and the held machine's motor torque (the diagnosis' signature input) is that torque
    tau = motor_torques(ErrorSet(), cmd, np.full(8, payload))
    assert np.abs(tau - gravity_torque(np.deg2rad(cmd), payload)).max() < 1e-3 * np.abs(tau).max()


def test_series_springs_agree_with_mujoco_dynamics():
    """Paper Table 2 errors (internal forces too): MuJoCo's time-domain simulation with position servos of
    stiffness K, started from the held pose, sags to the quasi-static spring solution."""
    cmd = np.rad2deg(nominal_ik(np.deg2rad(40), np.deg2rad(35)))[0]
    K = 2e5
    held = EffectTwin(PAPER_TABLE2, stiffness_ratio=1e6)          # gravity on, motors held
    st_dyn, info = DynamicTwin(held.twin, servo_kp=K).settle(cmd, duration=1.0)
    st_qs = EffectTwin(PAPER_TABLE2, Effects(joint_compliance=(K, K)), stiffness_ratio=1e6).reach(cmd[None])
    assert info.settled
    sag = st_qs.joint - np.deg2rad(cmd) - np.deg2rad([PAPER_TABLE2["L1.dtheta"], PAPER_TABLE2["L2.dtheta"]])
    assert np.abs(sag).max() > 1e-5
    assert np.abs(st_dyn.joint - st_qs.joint).max() < 1e-3 * np.abs(sag).max()
    assert np.abs(st_dyn.targets - st_qs.targets).max() < 1e-4                  # mm


def test_thermal_expansion_scales_every_length_exactly():
    """Per-pose models: links, radii, SS limb and target nests scale by exactly 1 + alpha dT; without
    gravity the whole pose then scales about O (same joint angles)."""
    rng = np.random.default_rng(1)
    params = random_errors(rng, 0.5, 0.1)
    cmd = commands(10, seed=2)
    temp = np.linspace(10.0, 35.0, 10)
    alpha = 23e-6
    et = EffectTwin(params, Effects(thermal_expansion=alpha), gravity=False)
    models = et.pose_models(10, temp)
    e, idx = et.twin.errors, et.twin.index
    for m, t in zip(models, temp):
        s = 1 + alpha * (t - 20.0)
        assert m.site_pos[idx.site_s1, 0] / MM == pytest.approx((G.l + e.dl1) * s, rel=1e-14)
        assert m.site_pos[idx.site_s2, 0] / MM == pytest.approx((G.l + e.dl2) * s, rel=1e-14)
        assert m.site_pos[idx.site_targets] / MM == pytest.approx(G.targets * s, rel=1e-14)
        assert m.body_pos[idx.link1] / MM == pytest.approx((G.base_points() + e.db) * s, rel=1e-14)
    st = et.reach(cmd, temp_c=temp)
    ref = Twin(params).reach(cmd)
    s = (1 + alpha * (temp - 20.0))[:, None, None]
    assert np.abs(st.targets - s * ref.targets).max() < 1e-9               # mm
    assert np.abs(st.targets - ref.targets).max() > 0.05                   # the effect is there
    # the diagnosis model's scaling identity equals the twin's physics (gravity on: ~1e-4 of its sag)
    et_g = EffectTwin(params, Effects(thermal_expansion=alpha))
    plan = plan_effect_campaign(10, 60, 2, temp_c=(10.0, 35.0))
    meas = et_g.measure(plan, LaserTracker(0.0))
    model = EffectChainModel()
    keys = list(params) + ["thermal_expansion.alpha"]
    x = np.array([np.deg2rad(params[k]) if is_angular(k) else params[k] for k in params] + [alpha])
    model.set_vector(keys, x, G.stiffness_ratio)
    T, _ = model.predict_meas(with_context(meas)[0], keys)
    assert np.abs(T - meas.targets).max() < 2e-4


def test_joint_angle_layer_shifts_the_joints_as_defined():
    rng = np.random.default_rng(3)
    plan = plan_effect_campaign(20, 60, 4)
    cmd = nominal_commands(plan.phi_deg, plan.theta_deg)
    eff = Effects(backlash=(0.02, 0.01), encoder_eccentricity=(0.01, 0.03), encoder_phase_deg=(30.0, 200.0),
                  zero_offset_drift=(0.05, -0.02))
    params = {"L1.dtheta": 0.1, "L2.dtheta": -0.2}
    st = EffectTwin(params, eff, gravity=False).reach(cmd, plan.approach, plan.time_s)
    hours = (plan.time_s - plan.time_s[0]) / 3600.0
    a = plan.approach
    expect = (cmd + [0.1, -0.2] - np.array([0.02, 0.01]) * a
              + np.array([0.01, 0.03]) * np.sin(np.deg2rad(cmd) + np.deg2rad([30.0, 200.0]))
              + np.outer(hours, [0.05, -0.02]))
    assert np.rad2deg(st.joint) == pytest.approx(expect, abs=1e-12)
    ref = Twin(params).reach_joint(np.deg2rad(expect))
    assert np.abs(st.targets - ref.targets).max() < 1e-9
    del rng


def test_overconstraint_inserts_passive_limb_errors_into_the_model():
    pe = passive_errors(0.5, seed=7)
    assert set(pe) == {f"L{j}.{f}" for j in (3, 4) for f in
                       ("dbx", "dby", "dbz", "dalpha", "dgamma", "dl1", "dl2", "dax", "day", "daz", "dmu", "dnu")}
    assert max(abs(v) for k, v in pe.items() if not is_angular(k)) <= 0.5
    assert max(abs(v) for k, v in pe.items() if is_angular(k)) <= 0.1
    et = EffectTwin({"L1.dbx": 0.3}, Effects(overconstraint=0.5), seed=7, gravity=False)
    assert et.passive_errors == pe
    cmd = commands(6)
    assert np.abs(et.reach(cmd).targets - Twin({"L1.dbx": 0.3, **pe}).reach(cmd).targets).max() < 1e-9


def test_payload_point_mass():
    m, idx = Twin().model, Twin().index
    import copy
    m2 = copy.copy(m)
    add_payload(m2, idx.platform, 10.0, np.array([0, 0, 0.08]))
    assert m2.body_mass[idx.platform] == pytest.approx(16.0)
    assert m2.body_ipos[idx.platform] == pytest.approx([0, 0, (6 * 0.04 + 10 * 0.08) / 16])
    # parallel-axis: Ixx about the new centre of mass
    c = (6 * 0.04 + 10 * 0.08) / 16
    assert m2.body_inertia[idx.platform][0] == pytest.approx(0.0488 + 6 * (0.04 - c) ** 2 + 10 * (0.08 - c) ** 2)


def test_effects_parse_and_refuse():
    e = parse_effects(["backlash=0.0125", "joint_compliance=5e4,3e4", "thermal_expansion=23e-6"])
    assert e.backlash == (0.0125, 0.0125) and e.joint_compliance == (5e4, 3e4) and e.thermal_expansion == 23e-6
    assert e.active() == ["joint_compliance", "backlash", "thermal_expansion"]
    for bad, msg in [("bogus=1", "NAME one of"), ("backlash", "NAME=VALUE"), ("backlash=x", "must be a number"),
                     ("backlash=1", "plausible"), ("thermal_expansion=1e-5,2e-5", "one number"),
                     ("joint_compliance=-5", "plausible")]:
        with pytest.raises(ValueError, match=msg):
            parse_effects([bad])


def test_effect_campaign_varies_payload_temperature_and_order():
    plan = plan_effect_campaign(40, 70, 5, payloads=(0.0, 10.0), temp_c=(18.0, 28.0))
    assert set(plan.payload_kg) == {0.0, 10.0}
    for level in (0.0, 10.0):                     # each payload level spans the tilt range
        th = plan.theta_deg[plan.payload_kg == level]
        assert th.min() < 15 and th.max() > 60
    assert plan.temp_c[0] == 18.0 and plan.temp_c[-1] == 28.0 and np.all(np.diff(plan.temp_c) > 0)
    assert np.any(np.diff(plan.theta_deg) < 0)    # shuffled, not in tilt order
    assert set(np.unique(plan.approach)) == {-1.0, 1.0}
    with pytest.raises(ValueError, match="payloads"):
        plan_effect_campaign(10, payloads=(-1.0,))


def test_heavy_tailed_tracker_has_the_requested_std():
    pts = np.zeros((20000, 3))
    noise = HeavyTailedTracker(0.01, nu=3.0, rng=np.random.default_rng(0)).measure(pts)
    # Student-t(3) scaled to std 0.01: heavy tails (kurtosis), median absolute value below a Gaussian's
    assert np.median(np.abs(noise)) < 0.6745 * 0.01
    assert np.mean(np.abs(noise) > 0.05) > 1e-4


# ---------------------------------------------------------------------------------------- CLI
def test_twin_measure_with_effects_writes_the_context_columns(tmp_path, capsys):
    out = tmp_path / "m.csv"
    rc = main(["--quiet", "twin", "measure", "--preset", "paper-table2", "--poses", "30", "--theta-max", "60",
               "--effect", "backlash=0.02", "--effect", "thermal_expansion=23e-6", "--payload", "0,10",
               "--temperature", "18,28", "--shuffle", "--seed", "3", "-o", str(out)])
    assert rc == 0, capsys.readouterr().err
    meas = read_measurements(out)
    assert meas.temp_c[0] == pytest.approx(18.0) and meas.temp_c[-1] == pytest.approx(28.0)
    assert set(meas.payload_kg) == {0.0, 10.0}
    assert set(np.unique(meas.approach)) == {-1.0, 1.0}
    # the same machine and context without noise: the recorded targets differ by the tracker noise only
    et = EffectTwin(PAPER_TABLE2, Effects(backlash=(0.02, 0.02), thermal_expansion=23e-6))
    truth = et.reach(meas.m_cmd_deg, meas.approach, meas.time_s, meas.temp_c, meas.payload_kg).targets
    assert np.std(meas.targets - truth) == pytest.approx(0.01, rel=0.25)


@pytest.mark.parametrize("args, message", [
    (["--effect", "bogus=1"], "NAME one of"),
    (["--effect", "backlash=abc"], "must be a number"),
    (["--effect", "thermal_expansion=23e-6"], "needs the machine temperature"),
    (["--payload", "-5"], "outside 0..100 kg"),
    (["--temperature", "18,28,30"], "expected 1..2 values"),
    (["--effect", "backlash=0.01", "--seconds-per-pose", "0"], "seconds per pose must be positive"),
])
def test_twin_measure_bad_effect_arguments_exit_2(tmp_path, capsys, args, message):
    out = tmp_path / "m.csv"
    rc = main(["--quiet", "twin", "measure", "--poses", "10", *args, "-o", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and message in err[0]
    assert not out.exists() and not list(tmp_path.iterdir())


def test_effect_values_are_json_ready():
    e = Effects(joint_compliance=(5e4, 5e4), overconstraint=0.5)
    assert json.loads(json.dumps(e.values())) == {"joint_compliance": [5e4, 5e4], "overconstraint": 0.5}
