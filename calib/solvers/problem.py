"""The generic least-squares identification problem every solver takes.

A problem is ``min_x 1/2 sum_i (r_i(x) / sigma)^2`` over a bounded box, where the residual entries
``r_i`` are independent with noise standard deviation ``sigma`` (the model whitens them if they are
not). It knows nothing about mechanisms: the paper's per-limb motor-angle model
(:mod:`pmcal.calib.ocpm.paper_model`) and a whole-chain forward model (residuals = measured minus predicted
target coordinates, mm, ``sigma`` = tracker noise) plug into the same solvers.

Residual functions are vectorised over a population: ``residuals(X)`` with ``X`` of shape (P, n) returns
(P, m); with ``x`` of shape (n,) it returns (m,). NaN marks a parameter set for which the model is
undefined (e.g. a pose out of reach); solvers treat its cost as infinite.

Units: whatever the model says, per parameter in ``units`` (inside ``calib``: mm and rad).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Callable, Protocol, Sequence, runtime_checkable

import numpy as np
import scipy.linalg

ResidualFn = Callable[[np.ndarray], np.ndarray]


@runtime_checkable
class LeastSquaresProblem(Protocol):
    """What a solver needs. :class:`Problem` is the standard implementation."""

    names: list[str]
    units: list[str]
    x0: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    sigma: float
    scale: np.ndarray

    def residuals(self, X: np.ndarray) -> np.ndarray: ...

    def jacobian(self, x: np.ndarray) -> np.ndarray: ...


@dataclass
class Problem:
    """A bounded least-squares problem with a population-vectorised residual.

    fun : ``fun(X (P, n)) -> (P, m)`` residuals, problem units; NaN where undefined.
    names, units : parameter keys and their units (``"mm"``, ``"rad"``).
    x0 : prior / starting point (n,); also the centre of regularisation.
    lower, upper : search box (n,) for the global methods; local methods respect it too.
    sigma : noise standard deviation of every residual entry (entries independent).
    scale : typical magnitude of each parameter (n,): the search box half-width by default, used to
        make the parameters commensurable (regularisation, identifiability, finite differences).
    jac : optional analytic Jacobian ``jac(x (n,)) -> (m, n)``; otherwise central differences over
        a population of 2n parameter sets in one call.
    fixed, fixed_units : ``{name: value}`` and ``{name: unit}`` of parameters held out of the problem.
    design : optional companion problem with the same parameters on noise-free, consistent data
        (e.g. the nominal machine at the measured orientations): where first-order identifiability is
        judged (at its ``x0``). Measured data are inconsistent with the model at the prior, and that
        defect lends parameters a spurious first-order effect.
    info : model details to carry into results (e.g. the raw residual unit).
    """

    fun: ResidualFn
    names: list[str]
    units: list[str]
    x0: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    sigma: float = 1.0
    scale: np.ndarray | None = None
    jac: Callable[[np.ndarray], np.ndarray] | None = None
    fixed: dict[str, float] = field(default_factory=dict)
    fixed_units: dict[str, str] = field(default_factory=dict)
    design: "Problem | None" = None
    info: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.names = list(self.names)
        n = len(self.names)
        self.units = list(self.units) if self.units else [""] * n
        self.x0 = np.asarray(self.x0, float).reshape(n)
        self.lower = np.broadcast_to(np.asarray(self.lower, float), (n,)).copy()
        self.upper = np.broadcast_to(np.asarray(self.upper, float), (n,)).copy()
        if np.any(self.lower >= self.upper):
            k = int(np.flatnonzero(self.lower >= self.upper)[0])
            raise ValueError(f"empty search box for {self.names[k]}: [{self.lower[k]}, {self.upper[k]}]")
        if self.scale is None:
            self.scale = 0.5 * (self.upper - self.lower)
        self.scale = np.broadcast_to(np.asarray(self.scale, float), (n,)).copy()
        if not (np.isfinite(self.sigma) and self.sigma > 0):
            raise ValueError(f"noise sigma must be positive, got {self.sigma}")

    @property
    def n(self) -> int:
        return len(self.names)

    def residuals(self, X: np.ndarray) -> np.ndarray:
        """Residuals for one parameter vector (n,) -> (m,) or a population (P, n) -> (P, m)."""
        X = np.asarray(X, float)
        if X.ndim == 1:
            return np.asarray(self.fun(X[None]))[0]
        return np.asarray(self.fun(X))

    def cost(self, X: np.ndarray) -> np.ndarray:
        """Objective ``sum (r / sigma)^2`` (chi-square) per parameter set; inf where undefined."""
        r = self.residuals(X) / self.sigma
        c = np.sum(r * r, axis=-1)
        return np.where(np.isfinite(c), c, np.inf)

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        """(m, n) Jacobian at ``x``: analytic if given, else central differences in one population call.

        Steps are ``1e-4 * scale`` (the residuals are smooth; curvature error ~ step^2).
        """
        x = np.asarray(x, float)
        if self.jac is not None:
            return np.asarray(self.jac(x))
        h = 1e-4 * self.scale
        E = np.diag(h)
        R = self.residuals(np.concatenate([x + E, x - E]))
        return ((R[: self.n] - R[self.n:]) / (2 * h[:, None])).T

    def clip(self, X: np.ndarray) -> np.ndarray:
        return np.clip(X, self.lower, self.upper)

    # ---------------------------------------------------------------- derived problems
    def fix(self, names: Sequence[str], values: Sequence[float] | None = None) -> "Problem":
        """The problem with ``names`` held at ``values`` (default: their ``x0``), removed from ``x``."""
        drop = [self.names.index(k) for k in names]
        if not drop:
            return self
        keep = np.setdiff1d(np.arange(self.n), drop)
        base = self.x0.copy()
        if values is not None:
            base[drop] = np.asarray(values, float)
        fun = self.fun

        def sub(X: np.ndarray) -> np.ndarray:
            full = np.broadcast_to(base, X.shape[:-1] + (base.size,)).copy()
            full[..., keep] = X
            return fun(full)

        jac = None if self.jac is None else (lambda x: self._embed_jac(x, base, keep))
        fixed = dict(self.fixed)
        fixed.update({self.names[k]: float(base[k]) for k in drop})
        fixed_units = dict(self.fixed_units)
        fixed_units.update({self.names[k]: self.units[k] for k in drop})
        design = None if self.design is None else self.design.fix(names, values)
        return replace(self, fun=sub, fixed_units=fixed_units, design=design, names=[self.names[k] for k in keep],
                       units=[self.units[k] for k in keep], x0=self.x0[keep], lower=self.lower[keep],
                       upper=self.upper[keep], scale=self.scale[keep], jac=jac, fixed=fixed)

    def _embed_jac(self, x: np.ndarray, base: np.ndarray, keep: np.ndarray) -> np.ndarray:
        full = base.copy()
        full[keep] = x
        return self.jac(full)[:, keep]

    def with_prior(self, std: np.ndarray | float | None = None, *, cov: np.ndarray | None = None) -> "Problem":
        """Add pseudo-observations ``(x - x0) / std`` (scaled to ``sigma``): a Gaussian prior / ridge.

        The maximum a-posteriori estimate with prior ``N(x0, std^2)``: regularises the directions the
        data cannot see and leaves the well-determined ones alone. ``std`` in parameter units. With
        ``cov`` (n, n) instead, a correlated prior ``N(x0, cov)``: the pseudo-observations are
        ``L^-1 (x - x0)`` with ``cov = L L^T`` (e.g. base parameters that each regroup several errors).
        """
        if (std is None) == (cov is None):
            raise ValueError("give the prior as std or as cov, not both")
        if cov is None:
            std = np.broadcast_to(np.asarray(std, float), (self.n,)).copy()
            W = np.diag(1.0 / std)
        else:
            cov = np.asarray(cov, float)
            W = scipy.linalg.solve_triangular(np.linalg.cholesky(cov), np.eye(self.n), lower=True)
            std = np.sqrt(np.diag(cov))
        fun, x0, sigma = self.fun, self.x0, self.sigma

        def aug(X: np.ndarray) -> np.ndarray:
            return np.concatenate([fun(X), sigma * (X - x0) @ W.T], axis=-1)

        jac = None
        if self.jac is not None:
            base_jac = self.jac
            jac = lambda x: np.vstack([base_jac(x), sigma * W])  # noqa: E731
        info = dict(self.info, prior_std=std, n_prior=self.n)   # the last n residuals are the prior
        return replace(self, fun=aug, jac=jac, info=info)

    def full_vector(self, x: np.ndarray, names: Sequence[str]) -> np.ndarray:
        """Values of ``names`` (free or fixed) from a solution ``x`` of this problem."""
        d = dict(self.fixed)
        d.update(zip(self.names, np.asarray(x, float)))
        return np.array([d.get(k, 0.0) for k in names])


def box_problem(fun: ResidualFn, names: Sequence[str], units: Sequence[str], half_width: np.ndarray,
                x0: np.ndarray | None = None, **kwargs) -> Problem:
    """A :class:`Problem` whose search box is ``x0 ± half_width`` (the usual calibration set-up)."""
    half_width = np.asarray(half_width, float)
    x0 = np.zeros(len(names)) if x0 is None else np.asarray(x0, float)
    return Problem(fun=fun, names=list(names), units=list(units), x0=x0, lower=x0 - half_width,
                   upper=x0 + half_width, scale=kwargs.pop("scale", half_width), **kwargs)
