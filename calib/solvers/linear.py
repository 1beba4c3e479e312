"""Linear least-squares solvers for ill-conditioned identification models.

``J dx = r`` with ``J`` the (m, n) identification Jacobian. Truncated SVD (paper 003 eq. 27-29) and
Tikhonov regularisation with the L-curve corner (paper 000 eq. 18-20, Hansen & O'Leary 1993).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class LinearSolution:
    dx: np.ndarray          # the solution
    rank: int               # singular values kept (TSVD) or effective rank (Tikhonov)
    lam: float              # regularisation parameter (0 for TSVD)
    singular_values: np.ndarray
    covariance_factor: np.ndarray  # C such that cov(dx) = sigma^2 * C


def tsvd_solve(J: np.ndarray, r: np.ndarray, rank: int | None = None,
               rtol: float | None = None) -> LinearSolution:
    """Truncated-SVD solution of ``J dx = r``.

    Keeps the ``rank`` largest singular values; if ``rank`` is None, keeps those above
    ``rtol * s_max`` (default ``rtol = max(m, n) * eps``: the numerical rank).
    """
    J = np.asarray(J, dtype=float)
    U, s, Vt = np.linalg.svd(J, full_matrices=False)
    if rank is None:
        tol = (rtol if rtol is not None else max(J.shape) * np.finfo(float).eps) * (s[0] if s.size else 0.0)
        rank = int(np.sum(s > tol))
    k = int(max(0, min(rank, s.size)))
    inv = np.zeros_like(s)
    inv[:k] = 1.0 / s[:k]
    dx = Vt.T @ (inv * (U.T @ r))
    cov = (Vt.T * inv**2) @ Vt
    return LinearSolution(dx=dx, rank=k, lam=0.0, singular_values=s, covariance_factor=cov)


def tikhonov_solve(J: np.ndarray, r: np.ndarray, lam: float) -> LinearSolution:
    """Tikhonov solution ``(J^T J + lam I)^{-1} J^T r`` (paper 000 eq. 20), via the SVD.

    ``lam`` is in the units of ``J^T J`` (squared singular values), as in the seed.
    """
    U, s, Vt = np.linalg.svd(np.asarray(J, dtype=float), full_matrices=False)
    f = s / (s**2 + lam)
    dx = Vt.T @ (f * (U.T @ r))
    cov = (Vt.T * f**2) @ Vt
    eff = int(np.round(np.sum(s**2 / (s**2 + lam))))
    return LinearSolution(dx=dx, rank=eff, lam=float(lam), singular_values=s, covariance_factor=cov)


def lcurve(J: np.ndarray, r: np.ndarray, n: int = 200) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Residual norms and solution norms of Tikhonov solutions over a log grid of lambda.

    Returns ``(lams, residual_norm, solution_norm)``; the grid spans the squared singular values.
    """
    U, s, Vt = np.linalg.svd(np.asarray(J, dtype=float), full_matrices=False)
    beta = U.T @ r
    r_perp2 = max(float(r @ r - beta @ beta), 0.0)
    smax, smin = s[0], max(s[-1], s[0] * 1e-12)
    lams = np.logspace(np.log10(smin**2) - 2, np.log10(smax**2) + 1, n)
    f = s[None, :] / (s[None, :] ** 2 + lams[:, None])
    sol = np.sqrt(np.sum((f * beta) ** 2, axis=1))
    res = np.sqrt(np.sum(((1 - f * s) * beta) ** 2, axis=1) + r_perp2)
    return lams, res, sol


def lcurve_corner(J: np.ndarray, r: np.ndarray, n: int = 200) -> float:
    """Lambda at the corner of the L-curve: the point of maximum curvature in log-log coordinates."""
    lams, res, sol = lcurve(J, r, n)
    x, y = np.log(np.maximum(res, 1e-300)), np.log(np.maximum(sol, 1e-300))
    t = np.log(lams)
    dx, dy = np.gradient(x, t), np.gradient(y, t)
    ddx, ddy = np.gradient(dx, t), np.gradient(dy, t)
    kappa = (dx * ddy - dy * ddx) / np.maximum((dx**2 + dy**2) ** 1.5, 1e-300)
    # Hansen's curvature of (log residual, log solution norm) along increasing lambda: the corner, where
    # the curve turns from the steep (noise-dominated) branch to the flat (over-smoothed) one, is the
    # largest POSITIVE curvature. (The most negative one sits at the far end of the flat branch;
    # tests/test_solvers_linear.py checks the corner on a problem with a known best lambda.)
    return float(lams[int(np.argmax(kappa[2:-2])) + 2])
