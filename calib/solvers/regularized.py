"""Regularised linearised identification: Tikhonov with the L-curve corner (paper 000 eq. 18-20) and
truncated SVD (paper 003 eq. 27-29), on any :class:`Problem`.

The problem is linearised at the current estimate, ``r(x) ~ r(x_k) + J (x - x_k)``, and the step solves
the regularised linear system in box-scaled coordinates ``z = (x - x0) / scale`` (so mm and rad are
commensurable and the regularisation pulls towards the prior ``x0``):

    Tikhonov:  z = argmin |J_s z - b|^2 + lam |z|^2,    b = -r(x_k) / sigma + J_s z_k
    TSVD:      z = sum_{i<=k} (u_i^T b / s_i) v_i

For a linear model (the paper's pose-error model, eq. 19) one step is the paper's eq. 20; for a nonlinear
one the linearisation is repeated (Gauss-Newton) with the same lambda / rank until the step is below
``xtol``. lambda comes from the L-curve corner of the first linearisation (seed); the rank from
generalised cross-validation (no noise level needed) unless given.
"""

from __future__ import annotations

import time

import numpy as np

from pmcal.calib.solvers.base import Counter, finalize
from pmcal.calib.solvers.linear import lcurve_corner, tikhonov_solve, tsvd_solve
from pmcal.calib.solvers.problem import Problem
from pmcal.calib.solvers.result import IdentResult


def gcv_rank(J: np.ndarray, b: np.ndarray) -> int:
    """Truncation rank minimising generalised cross-validation ``|r_k|^2 / (m - k)^2``."""
    U, s, _ = np.linalg.svd(J, full_matrices=False)
    beta = U.T @ b
    perp = max(float(b @ b - beta @ beta), 0.0)
    m = J.shape[0]
    ks = np.arange(1, s.size + 1)
    res = perp + np.array([np.sum(beta[k:] ** 2) for k in ks])
    gcv = res / np.maximum(m - ks, 1) ** 2
    return int(ks[np.argmin(gcv)])


def _regularised(problem: Problem, method: str, step, max_iter: int, xtol: float) -> IdentResult:
    t0 = time.perf_counter()
    c = Counter(problem)
    s = problem.scale
    z = np.zeros(problem.n)
    sol, it, setting = None, 0, {}
    for it in range(1, max_iter + 1):
        x = problem.x0 + z * s
        Js = c.jacobian(x) / problem.sigma * s
        b = -c.residuals(x) / problem.sigma + Js @ z
        sol = step(Js, b, setting)
        dz = sol.dx - z
        z = sol.dx
        if np.linalg.norm(dz) <= xtol * (1.0 + np.linalg.norm(z)):
            break
    x = problem.x0 + z * s
    cov = sol.covariance_factor * np.outer(s, s)
    info = {"lambda": sol.lam, "rank": sol.rank, "singular_values": sol.singular_values, **setting}
    return finalize(problem, x, method, t0, n_eval=c.n, n_iter=it, success=True,
                    message=f"{it} linearisation(s)", covariance=cov, info=info)


def tikhonov(problem: Problem, *, lam: float | None = None, max_iter: int = 20, xtol: float = 1e-6,
             seed: int | None = None, callback=None) -> IdentResult:
    """Tikhonov-regularised (iterated) Gauss-Newton; ``lam`` from the L-curve corner if not given.

    ``lam`` is in units of squared whitened, box-scaled singular values. ``seed``/``callback`` unused.
    """
    def step(J, b, setting):
        if "lam" not in setting:
            setting["lam"] = float(lam) if lam is not None else lcurve_corner(J, b)
        return tikhonov_solve(J, b, setting["lam"])

    return _regularised(problem, "tikhonov", step, max_iter, xtol)


def tsvd(problem: Problem, *, rank: int | None = None, max_iter: int = 20, xtol: float = 1e-6,
         seed: int | None = None, callback=None) -> IdentResult:
    """Truncated-SVD (iterated) Gauss-Newton; ``rank`` by generalised cross-validation if not given.

    The covariance is that of the truncated estimator (zero along the truncated directions, which
    stay at the prior). ``seed``/``callback`` unused.
    """
    def step(J, b, setting):
        if "rank_chosen" not in setting:
            setting["rank_chosen"] = int(rank) if rank is not None else gcv_rank(J, b)
        return tsvd_solve(J, b, rank=setting["rank_chosen"])

    return _regularised(problem, "tsvd", step, max_iter, xtol)
