"""Local least-squares methods (scipy.optimize): Levenberg-Marquardt and the polish step of the HGA.

All work on the whitened residuals ``r / sigma`` with the problem's Jacobian (analytic or one
population call of central differences), parameters scaled by ``problem.scale``.
"""

from __future__ import annotations

import time

import numpy as np
from scipy.optimize import least_squares, minimize

from pmcal.calib.solvers.base import Counter, finalize
from pmcal.calib.solvers.problem import Problem
from pmcal.calib.solvers.result import IdentResult


def _funs(counter: Counter):
    p = counter.problem
    fun = lambda x: counter.residuals(x) / p.sigma  # noqa: E731
    jac = lambda x: counter.jacobian(x) / p.sigma  # noqa: E731
    return fun, jac


def lsq_polish(counter: Counter, x_start: np.ndarray, *, bounded: bool = True, method: str | None = None,
               max_nfev: int | None = None, xtol: float = 1e-10, ftol: float = 1e-12):
    """``scipy.optimize.least_squares`` from ``x_start`` (trust-region reflective inside the box, or
    ``method="lm"`` unbounded). Returns scipy's result object."""
    p = counter.problem
    fun, jac = _funs(counter)
    method = method or ("trf" if bounded else "lm")
    kw = dict(bounds=(p.lower, p.upper)) if method != "lm" else {}
    x_start = np.clip(x_start, p.lower, p.upper) if method != "lm" else np.asarray(x_start, float)
    return least_squares(fun, x_start, jac=jac, method=method, x_scale=p.scale, xtol=xtol, ftol=ftol,
                         gtol=1e-12, max_nfev=max_nfev, **kw)


def sqp_polish(counter: Counter, x_start: np.ndarray, *, maxiter: int = 200, ftol: float = 1e-12):
    """The paper's polish: SQP (``scipy.optimize.minimize(method="SLSQP")``) on the chi-square, in
    box-scaled coordinates, gradient ``2 J^T r / sigma^2``. Returns scipy's result object."""
    p = counter.problem
    fun, jac = _funs(counter)
    s = p.scale

    def f(z):
        r = fun(p.x0 + z * s)
        return float(r @ r), 2.0 * (jac(p.x0 + z * s).T @ r) * s

    res = minimize(f, (np.asarray(x_start) - p.x0) / s, jac=True, method="SLSQP",
                   bounds=list(zip((p.lower - p.x0) / s, (p.upper - p.x0) / s)),
                   options={"maxiter": maxiter, "ftol": ftol})
    res.x = p.x0 + res.x * s
    return res


def lm(problem: Problem, *, x_start: np.ndarray | None = None, max_nfev: int | None = None,
       seed: int | None = None, callback=None) -> IdentResult:
    """Levenberg-Marquardt (MINPACK via ``scipy.optimize.least_squares(method="lm")``) from the prior
    ``x0`` (or ``x_start``); unbounded, as LM is. ``seed``/``callback`` are accepted for a uniform
    signature and unused (LM is deterministic and short)."""
    t0 = time.perf_counter()
    c = Counter(problem)
    x_start = problem.x0 if x_start is None else x_start
    try:
        res = lsq_polish(c, x_start, method="lm", max_nfev=max_nfev)
    except ValueError as exc:                      # residuals undefined (NaN) along the way
        return finalize(problem, x_start, "lm", t0, n_eval=c.n, n_iter=0, success=False,
                        message=f"LM failed: {exc}")
    return finalize(problem, res.x, "lm", t0, n_eval=c.n, n_iter=int(res.nfev), success=res.status > 0,
                    message=res.message)
