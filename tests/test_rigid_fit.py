"""Pose from tracker targets: exactness, the paper's three-point construction, noise statistics."""

import numpy as np
import pytest

from pmcal.mechanism.ocpm.config import default_geometry
from pmcal.mechanism.ocpm.kinematics import nominal_pose
from pmcal.mechanism.rigid import fit_pose, pose_from_three_points
from pmcal.mechanism.rotations import pointing_error
from pmcal.twin.tracker import LaserTracker

X = default_geometry().targets


def poses(n, seed=0):
    rng = np.random.default_rng(seed)
    return nominal_pose(rng.uniform(0, 2 * np.pi, n), np.deg2rad(rng.uniform(0, 80, n)))


def targets_of(r, R):
    return r[:, None, :] + np.einsum("nij,kj->nki", R, X)


def test_fit_is_exact_without_noise_and_agrees_with_eq16():
    r, R = poses(100)
    Y = targets_of(r, R)
    r1, R1, rms = fit_pose(Y, X)
    r2, R2 = pose_from_three_points(Y, X)
    assert np.abs(r1 - r).max() < 1e-10 and np.abs(R1 - R).max() < 1e-13 and rms.max() < 1e-10
    assert np.abs(r2 - r).max() < 1e-10 and np.abs(R2 - R).max() < 1e-13


def test_tracker_round_trip_statistics_follow_sigma():
    """Monte Carlo: errors of the fitted pose have the spread predicted from sigma and the target layout.

    Targets: equilateral triangle of circumradius rho = 100 mm at w = 80 mm. Each in-plane rotation has
    std s = sigma / sqrt(3 rho^2 / 2); the pointing error (tilt of the normal) is Rayleigh with mean
    s sqrt(pi/2). The origin C_E lies 80 mm below the centroid, so its horizontal error has std
    sqrt(sigma^2 / 3 + (80 s)^2) and its vertical error sigma / sqrt(3). The fit residual satisfies
    E[sum |res|^2] = (3k - 6) sigma^2.
    """
    sigma, n = 0.01, 20000
    r, R = poses(n, seed=1)
    tracker = LaserTracker(sigma, np.random.default_rng(7))
    r1, R1, rms = fit_pose(tracker.measure(targets_of(r, R)), X)
    s = sigma / np.sqrt(1.5 * 100.0**2)
    point = pointing_error(R, R1)
    rel = 4.0 / np.sqrt(n)                     # ~4 standard errors of a mean / std estimate
    assert point.mean() == pytest.approx(s * np.sqrt(np.pi / 2), rel=rel)
    # position error in platform axes (the prediction is for the platform frame)
    dr = np.einsum("nji,nj->ni", R, r1 - r)
    assert dr[:, 0].std() == pytest.approx(np.hypot(sigma / np.sqrt(3), 80 * s), rel=rel)
    assert dr[:, 1].std() == pytest.approx(np.hypot(sigma / np.sqrt(3), 80 * s), rel=rel)
    assert dr[:, 2].std() == pytest.approx(sigma / np.sqrt(3), rel=rel)
    assert np.mean(3 * rms**2) == pytest.approx(3 * sigma**2, rel=rel * 2)
    assert abs(dr.mean(axis=0)).max() < 4 * sigma / np.sqrt(n) * 2


def test_tracker_rejects_negative_noise():
    with pytest.raises(ValueError, match="non-negative"):
        LaserTracker(-0.01)
