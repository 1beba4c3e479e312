"""Identification model of paper 003 (eq. 14-31): rank, condition numbers, solutions and their covariance."""

import numpy as np
import pytest

from pmcal.calib.planar.calibration import calibrate
from pmcal.calib.planar.design import (boundary_positions, choose_n, condition_study, optimal_positions,
                                 zero_offset_covariance, Region)
from pmcal.mechanism.planar.geometry import FULL_KEYS, Errors, Geometry, Workspace
from pmcal.calib.planar.identification import (difference_operator, identification_matrix, identify,
                                         reading_covariance)
from pmcal.mechanism.planar.kinematics import Q, actual_position, inverse, mm_vector
from pmcal.mechanism.planar.noise import Noise, scale_sigma, servo_sigma

G = Geometry()
W = Workspace()
R6 = boundary_positions(W, 3)


def readings(err: Errors, r, theta_noise=None, scale_noise=None):
    """Scale changes of the real machine ``err`` sent to nominal positions ``r`` (closed forms)."""
    cmd = inverse(G, r)
    if theta_noise is not None:
        cmd = cmd + theta_noise
    length = np.linalg.norm(mm_vector(G.perturbed(err), actual_position(G, err, cmd)), axis=-1)
    out = np.diff(length)
    return out if scale_noise is None else out + scale_noise


def test_noise_of_eq_34_35():
    assert scale_sigma(350.0) == pytest.approx(3.35e-3 / 3, rel=1e-12)          # mm
    assert np.rad2deg(servo_sigma(1e4, 4, 20)) == pytest.approx(0.0024, rel=1e-12)  # deg


def test_rank_of_the_simplified_model_is_four():
    for n in (3, 5, 9):
        assert np.linalg.matrix_rank(identification_matrix(G, boundary_positions(W, n))) == 4


def test_full_model_has_rank_nine_with_three_rigid_motion_null_vectors():
    """The paper states rank(G') = 12 for K > 13. Distances O1O2 do not change when the base translates
    together with O1 (2 directions) or when the robot turns about O1 (1 direction), so rank(G') = 9."""
    r = boundary_positions(W, 8)                      # K = 16
    Gf = identification_matrix(G, r, "full")
    assert Gf.shape == (15, 12)
    s = np.linalg.svd(Gf, compute_uv=False)
    assert s[8] / s[0] > 1e-5 and s[9] / s[0] < 1e-13
    idx = {k: i for i, k in enumerate(FULL_KEYS)}

    def vec(**v):
        out = np.zeros(12)
        for k, val in v.items():
            out[idx[k]] = val * (G.L[0] if k == "dtheta1" else G.L[1] if k == "dtheta2" else 1.0)
        return out

    tx = vec(de1x=1, de2x=1, drMx=1)
    ty = vec(de1y=1, de2y=1, drMy=1)
    qe1, qe2, qd = Q @ (G.e[0] - G.c), Q @ (G.e[1] - G.c), Q @ G.d
    rot = vec(dtheta1=1, dtheta2=1, de1x=qe1[0], de1y=qe1[1], de2x=qe2[0], de2y=qe2[1], drMx=qd[0], drMy=qd[1])
    for v in (tx, ty, rot):
        assert np.linalg.norm(Gf @ v) < 1e-12 * np.linalg.norm(Gf) * np.linalg.norm(v)
    # the robot's own ten parameters keep one of them: the turn about O1 with the translation that brings
    # O1 + d back (its MAEMM part cancels)
    robot_only = rot - qd[0] * tx - qd[1] * ty
    assert np.abs(robot_only[10:]).max() < 1e-12
    assert np.linalg.norm(Gf[:, :10] @ robot_only[:10]) < 1e-12 * np.linalg.norm(Gf) * np.linalg.norm(robot_only)
    assert np.linalg.matrix_rank(Gf[:, :10]) == 9


def test_condition_numbers_of_fig_8():
    ns = np.arange(3, 22, 2)
    k1, km = condition_study(G, W, ns, np.array([1.0, 0.5]))
    assert k1[0] == pytest.approx(475.34, abs=5e-3)                   # paper Fig. 8
    assert km[0] == pytest.approx(472.35, abs=5e-3)                   # seed: 472.54 (see docs/planar.md)
    assert km[0] == pytest.approx(472.54, rel=1e-3)
    # the correction's sign matters: λ + ΔrM instead of λ - ΔrM would raise κ above κ1
    assert np.linalg.cond(identification_matrix(G, R6, drM=np.array([-1.0, -0.5]))) > k1[0]
    assert np.all(np.diff(k1) > 0) and np.all(np.diff(km) > 0) and np.all(km < k1)
    assert choose_n(G, W, 0.01, np.array([1.0, 0.5])) == 3


def test_difference_operator_keeps_chains_apart():
    D = difference_operator(5, np.array([1, 1, 1, 2, 2]))
    assert D.tolist() == [[-1, 1, 0, 0, 0], [0, -1, 1, 0, 0], [0, 0, 0, -1, 1]]


def test_noise_free_loop_converges_to_the_zero_offsets_and_maemm():
    """No geometric errors and no noise: the only model error is the first-order approximation, which the
    compensation loop removes; the MAEMM correction (eq. 30) must have the right sign for this."""
    err = Errors.from_interface({"dtheta1": 2.0, "dtheta2": -1.0, "drMx": 1.0, "drMy": 0.5})
    run = calibrate(G, R6, lambda cmd: _meas(err, cmd), max_iter=8, stop=False)
    assert np.rad2deg(run.steps[-1].comp) == pytest.approx([2.0, -1.0], abs=1e-7)
    assert run.steps[-1].drM_total == pytest.approx([1.0, 0.5], abs=1e-5)
    # eq. 32: μ is the RMS change of the identified increments; the rule stops at the first μ < μ0
    mus = np.rad2deg([s.mu for s in run.steps[1:]])
    assert run.converged and mus[run.m - 2] < 0.1 and np.all(mus[: run.m - 2] >= 0.1)


def _meas(err, cmd):
    length = np.linalg.norm(mm_vector(G.perturbed(err), actual_position(G, err, cmd)), axis=-1)
    return np.diff(length)


def test_geometric_errors_bias_the_simplified_model_as_the_full_model_predicts():
    """With geometric errors the simplified model converges to a biased compensation; to first order the
    bias is the simplified pseudo-inverse applied to the full model's geometric columns (eq. 12 vs 13)."""
    err = Errors.from_interface({"dtheta1": 2.0, "dtheta2": -1.0, "de1x": 0.03, "de1y": -0.02, "de2x": -0.02,
                                 "de2y": 0.01, "dL1": 0.01, "dL2": 0.02, "dl1": -0.03, "dl2": -0.02,
                                 "drMx": 1.0, "drMy": 0.5})
    run = calibrate(G, R6, lambda cmd: _meas(err, cmd), max_iter=10, stop=False)
    Gs = identification_matrix(G, R6, drM=run.steps[-1].drM_total)
    Gf = identification_matrix(G, R6, "full", drM=run.steps[-1].drM_total)
    geo = np.array([0, 0.03, -0.02, 0.01, -0.03, 0, -0.02, 0.01, 0.02, -0.02, 0, 0])
    predicted = (np.linalg.pinv(Gs) @ (Gf @ geo))[:2] / G.L
    bias = run.steps[-1].comp - err.dtheta
    assert np.rad2deg(bias) == pytest.approx(np.rad2deg(predicted), abs=2e-4)
    assert np.all(np.abs(np.rad2deg(bias)) > 3e-3)               # the bias is real (10x the tolerance)


@pytest.mark.parametrize("method", ["tsvd", "gls"])
def test_predicted_covariance_matches_monte_carlo(method):
    """The covariance an identification reports (from eq. 34-35 propagated through G) agrees with the
    scatter of the estimates over noise draws: 400 draws, 10 % sampling error on a standard deviation."""
    noise = Noise()
    err = Errors.from_interface({"drMx": 1.0, "drMy": 0.5})
    rng = np.random.default_rng(11)
    est, res = [], None
    clean_cmd = inverse(G, R6)
    for _ in range(400):
        th = rng.normal(0, noise.servo, clean_cmd.shape)
        y = readings(err, R6, th, rng.normal(0, noise.scale, len(R6) - 1))
        res = identify(G, R6, y, method=method, noise=noise, drM=err.drM)
        est.append(res.x)
    emp = np.std(est, axis=0)
    assert emp == pytest.approx(res.std, rel=0.2)
    # and the bound computed by the design module is the GLS covariance
    assert np.sqrt(np.diag(zero_offset_covariance(G, R6, noise))) == pytest.approx(
        identify(G, R6, np.zeros(5), method="gls", noise=noise).std, rel=1e-6)


def test_reading_covariance_structure():
    C = reading_covariance(G, R6, Noise(scale=1e-3, servo=0.0))
    assert np.allclose(C, 1e-6 * np.eye(5))
    C = reading_covariance(G, R6, Noise(scale=0.0, servo=1e-4))
    assert np.all(np.diag(C, 1) < 0) and np.allclose(np.diag(C, 2), 0)   # shared servo error of a position


def test_least_squares_on_the_full_model_reports_the_singular_normal_matrix():
    r = boundary_positions(W, 7)
    res = identify(G, r, np.zeros(13), model="full", method="ls")
    assert not res.success and "rank 9" in res.message
    assert res.names == list(FULL_KEYS) and res.units[0] == "rad" and res.units[1] == "mm"


def test_optimal_positions_respect_the_region_and_the_scale_range():
    region = Region(x=(-400.0, 400.0), y=(-900.0, -500.0), scale_range=300.0)
    r = optimal_positions(G, region, 6, Noise(), step=50.0, restarts=2)
    assert np.all((r[:, 0] >= -400) & (r[:, 0] <= 400) & (r[:, 1] >= -900) & (r[:, 1] <= -500))
    length = np.linalg.norm(mm_vector(G, r), axis=1)
    assert length.max() - length.min() <= 300.0
    sd_opt = np.sqrt(np.diag(zero_offset_covariance(G, r, Noise()))[:2])
    sd_seed = np.sqrt(np.diag(zero_offset_covariance(G, R6, Noise()))[:2])
    assert np.all(sd_opt < sd_seed)
