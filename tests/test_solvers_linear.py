"""Tikhonov, TSVD and the L-curve corner (calib/solvers/linear.py) against closed forms."""

import numpy as np

from pmcal.calib.solvers.linear import lcurve, lcurve_corner, tikhonov_solve, tsvd_solve


def ill_posed(rng, m=60, n=20, decay=6.0):
    """A discrete ill-posed problem with singular values 1..1e-decay and a Picard-decaying solution."""
    U, _ = np.linalg.qr(rng.normal(size=(m, m)))
    V, _ = np.linalg.qr(rng.normal(size=(n, n)))
    s = np.logspace(0, -decay, n)
    J = (U[:, :n] * s) @ V.T
    x = V @ (np.sqrt(s) * rng.choice([-1.0, 1.0], n))
    return J, x


def test_tikhonov_matches_normal_equations():
    rng = np.random.default_rng(1)
    J, x = ill_posed(rng)
    b = J @ x + 1e-3 * rng.normal(size=J.shape[0])
    lam = 1e-4
    expected = np.linalg.solve(J.T @ J + lam * np.eye(J.shape[1]), J.T @ b)
    np.testing.assert_allclose(tikhonov_solve(J, b, lam).dx, expected, rtol=1e-8, atol=1e-10)


def test_tsvd_full_rank_is_least_squares_and_truncation_drops_directions():
    rng = np.random.default_rng(2)
    J = rng.normal(size=(30, 5))
    b = rng.normal(size=30)
    np.testing.assert_allclose(tsvd_solve(J, b).dx, np.linalg.lstsq(J, b, rcond=None)[0], rtol=1e-10)
    U, s, Vt = np.linalg.svd(J, full_matrices=False)
    sol = tsvd_solve(J, b, rank=3)
    assert sol.rank == 3
    np.testing.assert_allclose(Vt[3:] @ sol.dx, 0.0, atol=1e-12)


def test_lcurve_corner_tracks_the_best_lambda():
    """The corner must sit near the error-minimising lambda and grow with the noise level. (With the
    curvature's sign reversed it sat at the flat, over-smoothed end: lambda ~ 1 whatever the noise.)"""
    rng = np.random.default_rng(3)
    J, x = ill_posed(rng)
    corners = []
    for sigma in (1e-6, 1e-4, 1e-2):
        b = J @ x + sigma * rng.normal(size=J.shape[0])
        lams, res, sol = lcurve(J, b)
        errors = np.array([np.linalg.norm(tikhonov_solve(J, b, lam).dx - x) for lam in lams])
        corner = lcurve_corner(J, b)
        assert abs(np.log10(corner) - np.log10(lams[np.argmin(errors)])) < 3.0
        assert np.linalg.norm(tikhonov_solve(J, b, corner).dx - x) < 25 * errors.min()
        corners.append(corner)
    assert corners[0] < corners[1] < corners[2] < 1e-1     # far from the over-smoothed end (s_max^2 = 1)
