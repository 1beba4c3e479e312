"""Pieces every solver shares: the unit-cube view of the search box, stall detection, and turning a
solution into an :class:`IdentResult` (residuals at the solution, Cramér-Rao covariance)."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from pmcal.calib.solvers.problem import Problem
from pmcal.calib.solvers.result import IdentResult

#: ``callback(generation, best_cost)``; returning True stops the run (progress bars, time limits).
Callback = Callable[[int, float], bool | None]


def to_unit(problem: Problem, X: np.ndarray) -> np.ndarray:
    """Parameters -> unit-cube coordinates ``(x - lower) / (upper - lower)``."""
    return (np.asarray(X, float) - problem.lower) / (problem.upper - problem.lower)


def from_unit(problem: Problem, U: np.ndarray) -> np.ndarray:
    """Unit-cube coordinates -> parameters."""
    return problem.lower + np.asarray(U, float) * (problem.upper - problem.lower)


def initial_population(problem: Problem, size: int, rng: np.random.Generator) -> np.ndarray:
    """``size`` points in the unit cube: the prior ``x0`` first, the rest uniform (Latin hypercube)."""
    n = problem.n
    strata = (rng.permuted(np.tile(np.arange(size), (n, 1)), axis=1).T + rng.uniform(size=(size, n))) / size
    strata[0] = np.clip(to_unit(problem, problem.x0), 0.0, 1.0)
    return strata


@dataclass
class StallMonitor:
    """Stops when the best cost improved by less than ``tol`` (relative, plus ``atol``) over ``window``
    generations (MATLAB ``ga``'s MaxStallGenerations / FunctionTolerance rule)."""

    window: int = 50
    tol: float = 1e-6
    atol: float = 1e-12
    history: list[float] = field(default_factory=list)

    def update(self, best: float) -> bool:
        self.history.append(float(best))
        if len(self.history) <= self.window:
            return False
        old = self.history[-1 - self.window]
        return old - best <= self.tol * abs(old) + self.atol


class Counter:
    """Wraps a problem and counts residual-vector evaluations (a population of P counts P; a
    finite-difference Jacobian counts 2n)."""

    def __init__(self, problem: Problem):
        self.problem, self.n = problem, 0

    def residuals(self, X: np.ndarray) -> np.ndarray:
        self.n += 1 if np.ndim(X) == 1 else len(X)
        return self.problem.residuals(X)

    def cost(self, X: np.ndarray) -> np.ndarray:
        X = np.atleast_2d(X)
        self.n += len(X)
        return self.problem.cost(X)

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        if self.problem.jac is None:
            self.n += 2 * self.problem.n
        return self.problem.jacobian(x)


def crlb_covariance(J_white: np.ndarray, rcond: float = 1e-12) -> np.ndarray:
    """``(J^T J)^{-1}`` for a whitened Jacobian (unit-variance residuals): the Cramér-Rao bound.

    Columns are normalised before the (pseudo-)inverse so the tolerance is scale-free.
    """
    d = np.linalg.norm(J_white, axis=0)
    d = np.where(d > 0, d, 1.0)
    Jn = J_white / d
    U, s, Vt = np.linalg.svd(Jn, full_matrices=False)
    keep = s > rcond * s[0]
    inv = np.zeros_like(s)
    inv[keep] = 1.0 / s[keep] ** 2                      # only kept values: no 1/0 warning for a null one
    return ((Vt.T * inv) @ Vt) / np.outer(d, d)


def finalize(problem: Problem, x: np.ndarray, method: str, t0: float, *, n_eval: int, n_iter: int,
             success: bool, message: str, covariance: np.ndarray | None = None,
             info: dict | None = None) -> IdentResult:
    """Build the :class:`IdentResult` of a solution ``x`` of ``problem``.

    Residuals are the data residuals (prior pseudo-observations removed), in the problem's units.
    The covariance is the Cramér-Rao bound ``sigma^2 (J^T J)^{-1}`` at ``x`` unless given. Names cover
    the free parameters followed by the problem's fixed ones (zero rows/columns in the covariance).
    """
    x = np.asarray(x, float)
    r = problem.residuals(x)
    n_prior = problem.info.get("n_prior", 0)
    data = r[: r.size - n_prior] if n_prior else r
    if covariance is None:
        J = problem.jacobian(x) / problem.sigma
        covariance = crlb_covariance(J)
    n, nf = problem.n, len(problem.fixed)
    cov = np.zeros((n + nf, n + nf))
    cov[:n, :n] = covariance
    chi2 = float(np.sum((data / problem.sigma) ** 2))
    dof = max(data.size - n, 1)
    info = dict(info or {})
    info.update(chi2=chi2, dof=dof, chi2_reduced=chi2 / dof, residual_unit=problem.info.get("residual_unit", ""),
                sigma=problem.sigma)
    fixed_names = list(problem.fixed)
    return IdentResult(method=method, names=problem.names + fixed_names,
                       x=np.concatenate([x, [problem.fixed[k] for k in fixed_names]]), residuals=data,
                       covariance=cov, n_eval=int(n_eval), n_iter=int(n_iter),
                       wall_time=time.perf_counter() - t0, success=bool(success), message=message,
                       fixed=fixed_names, units=problem.units + [problem.fixed_units.get(k, "") for k in fixed_names],
                       info=info)

