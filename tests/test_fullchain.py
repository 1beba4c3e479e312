"""Whole-closed-chain model: sensitivities, identification and compensation by inversion."""

import numpy as np
import pytest

from pmcal.mechanism.ocpm.params import LOG_RATIO, errors_and_ratio
from pmcal.twin.ocpm.forward import FullChainModel
from pmcal.calib.ocpm.fullchain import (FullChainOptions,
                                  identify_full, chain_commands_deg)
from pmcal.mechanism.ocpm.params import ErrorSet, all_keys, is_angular, random_errors
from pmcal.mechanism.rotations import pointing_error, tilt_torsion
from pmcal.twin.ocpm.campaign import nominal_commands, plan_campaign, run_campaign
from pmcal.twin.ocpm.machine import Twin
from pmcal.twin.ocpm.sensitivity import target_sensitivity
from pmcal.twin.tracker import LaserTracker

SIGMA = 0.01


def campaign(params, n=48, seed=3, noise_seed=5, sigma=SIGMA, ratio=None):
    twin = Twin(params, stiffness_ratio=ratio)
    return twin, run_campaign(twin, plan_campaign(n, 60, seed=seed), LaserTracker(sigma, np.random.default_rng(noise_seed)))


def test_sensitivities_match_finite_differences():
    rng = np.random.default_rng(0)
    params = random_errors(rng, 0.5, 0.1)
    twin = Twin(params)
    cmd = nominal_commands(rng.uniform(0, 360, 5), rng.uniform(0, 60, 5))
    keys = list(rng.choice(all_keys(), 14, replace=False)) + ["L1.dtheta", "SS.dcx", LOG_RATIO]
    sens = target_sensitivity(twin, twin.reach(cmd).qpos, keys)
    for c, key in enumerate(keys):
        if key == LOG_RATIO:
            h, r0 = 1e-4, 1000.0
            twin.set_stiffness_ratio(r0 * np.exp(h)); tp = twin.reach(cmd).targets
            twin.set_stiffness_ratio(r0 * np.exp(-h)); tm = twin.reach(cmd).targets
            twin.set_stiffness_ratio(r0)
        else:
            h = 1e-4 if is_angular(key) else 1e-3
            p = dict(params); p[key] = params.get(key, 0.0) + h; twin.set_errors(p); tp = twin.reach(cmd).targets
            p[key] = params.get(key, 0.0) - h; twin.set_errors(p); tm = twin.reach(cmd).targets
            twin.set_errors(params)
            h = np.deg2rad(h) if is_angular(key) else h
        fd = (tp - tm) / (2 * h)
        # dropped curvature terms are of the size gap / link length (~0.5 %)
        assert np.abs(fd - sens.d_targets[..., c]).max() <= 0.01 * np.abs(fd).max() + 1e-9, key


def test_consistent_data_zero_offsets_only_is_fitted_to_the_noise_and_recovered_within_crlb():
    params = {"L1.dtheta": 0.31, "L2.dtheta": -0.22}
    _, meas = campaign(params, n=24)
    res = identify_full(meas, FullChainModel())
    n = res.residuals.size
    # residuals at the noise level: chi^2 / (n - p_eff) = 1 within 3 of its standard deviations
    dof = res.info["dof"]
    assert res.info["chi2_per_dof"] == pytest.approx(1.0, abs=3 * np.sqrt(2 / dof))
    got = dict(zip(res.names, res.x))
    for k, v in params.items():
        i = res.names.index(k)
        assert abs(np.rad2deg(got[k]) - v) < 3 * np.rad2deg(res.std[i]) + 1e-4, k
    assert n == 24 * 9


def test_inversion_points_the_identified_machine_exactly():
    """Commands from the model of the *true* machine put the twin on target to solver precision."""
    rng = np.random.default_rng(2)
    params = random_errors(rng, 0.5, 0.1)
    twin = Twin(params)
    phi, theta = rng.uniform(0, 360, 20), rng.uniform(0, 60, 20)
    cmd = chain_commands_deg(FullChainModel(), ErrorSet.from_dict(params), phi, theta)
    err = np.rad2deg(pointing_error(twin.reach(cmd).R, tilt_torsion(np.deg2rad(phi), np.deg2rad(theta))))
    assert err.max() < 1e-6


def test_whole_chain_calibration_reaches_the_noise_floor_on_held_out_poses():
    rng = np.random.default_rng(11)
    params = random_errors(rng, 0.5, 0.1)
    twin, meas = campaign(params)
    res = identify_full(meas, FullChainModel())
    assert res.success
    assert res.info["chi2_per_dof"] == pytest.approx(1.0, abs=3 * np.sqrt(2 / res.info["dof"]))
    e, _ = errors_and_ratio(res.names, res.x)
    test = plan_campaign(24, 60, seed=99)
    Rt = tilt_torsion(np.deg2rad(test.phi_deg), np.deg2rad(test.theta_deg))
    before = np.rad2deg(pointing_error(twin.reach(nominal_commands(test.phi_deg, test.theta_deg)).R, Rt))
    after = np.rad2deg(pointing_error(twin.reach(chain_commands_deg(FullChainModel(), e, test.phi_deg, test.theta_deg)).R, Rt))
    # noise floor of one pose measured with sigma = 0.01 mm on this target layout: ~0.006 deg mean
    assert after.mean() < 0.006 and after.mean() < 0.05 * before.mean()


def test_a_different_stiffness_ratio_is_identified():
    rng = np.random.default_rng(21)
    params = random_errors(rng, 0.5, 0.1)
    _, meas = campaign(params, ratio=100.0)
    res = identify_full(meas, FullChainModel(), FullChainOptions(fit_stiffness_ratio=True))
    ratio = res.info["stiffness_ratio"]
    i = res.names.index(LOG_RATIO)
    assert abs(np.log(ratio) - np.log(100.0)) < 3 * res.std[i] + 0.05


def test_on_consistent_data_both_methods_compensate_exactly():
    """Errors only in the motor zero offsets: the closures stay consistent, eq. 7 holds, and both the
    paper's method (HGA + real IK at the eq. 7 position) and the whole chain reach the noise floor."""
    from pmcal.calib.ocpm import compensation as comp
    from pmcal.calib.ocpm import paper_calibration

    params = {"L1.dtheta": -0.28, "L2.dtheta": -0.4}
    twin, meas = campaign(params, n=24, seed=8, noise_seed=9)
    test = plan_campaign(24, 60, seed=98)
    ph, th = np.deg2rad(test.phi_deg), np.deg2rad(test.theta_deg)
    Rt = tilt_torsion(ph, th)
    cal = paper_calibration.calibrate(meas, "hga", (1, 2), seed=0)
    m_seed = np.rad2deg(comp.ik_commands_rad(ph, th, cal.errors()))
    res = identify_full(meas, FullChainModel())
    e, _ = errors_and_ratio(res.names, res.x)
    m_full = chain_commands_deg(FullChainModel(), e, test.phi_deg, test.theta_deg)
    before = np.rad2deg(pointing_error(twin.reach(nominal_commands(test.phi_deg, test.theta_deg)).R, Rt))
    for m in (m_seed, m_full):
        after = np.rad2deg(pointing_error(twin.reach(m).R, Rt))
        # exact up to the parameter noise: well under the single-pose tracker floor (~0.006 deg)
        assert after.mean() < 0.004 and after.mean() < 0.02 * before.mean()


def test_a_model_that_cannot_assemble_a_pose_predicts_nan_and_a_fit_says_so():
    """Poses the closure solve does not converge on (here: one Gauss-Newton iteration allowed) predict NaN,
    so a fit's trust region rejects such a step; a fit that cannot even start says how many rows."""
    from pmcal.calib.ocpm.fullchain import UnassembledError

    params = random_errors(np.random.default_rng(2), 0.5, 0.1)
    meas = campaign(params, n=24)[1]
    model = FullChainModel()
    model.set(params)                              # strained passive loops: no exact closed-form start
    T, _ = model.predict(meas.m_cmd_deg)
    assert np.isfinite(T).all()
    model.twin.assembler.max_iter = 1
    model._cmd_key = None
    T, _ = model.predict(meas.m_cmd_deg)
    assert np.isnan(T).all(axis=(1, 2)).sum() >= 20
    model.twin.assembler.max_iter = 0                # not even the nominal start assembles
    with pytest.raises(UnassembledError, match="cannot assemble 24 measured pose"):
        identify_full(meas, model, FullChainOptions(keys=["L3.dbx"]))
