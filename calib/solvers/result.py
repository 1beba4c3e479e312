"""The one result type returned by every identification method (cf. ``scipy.optimize.OptimizeResult``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass
class IdentResult:
    """Outcome of one identification run.

    Attributes
    ----------
    method : name of the method that produced it (``"hga"``, ``"lm"``, ``"tsvd"``, ...).
    names : parameter keys in the order of ``x`` (e.g. ``"L1.dbx"``).
    x : identified parameter vector, in the problem's internal units (see ``units``).
    covariance : covariance of ``x`` from the Jacobian at the solution and the residual noise
        (Cramér-Rao bound for Gaussian noise); ``None`` if the method cannot provide it. Parameters that
        were fixed or truncated away have zero rows/columns and are listed in ``fixed``.
    residuals : residual vector at the solution (problem units, e.g. rad or mm).
    residual_rms : root mean square of ``residuals``.
    n_eval : number of residual-vector evaluations (a population of P counts P).
    n_iter : iterations / generations.
    wall_time : seconds.
    success, message : convergence flag and text.
    fixed : names held at their prior value (not identifiable, or fixed by the user).
    units : unit of each parameter (``"mm"`` / ``"rad"``), parallel to ``names``.
    info : method-specific details (e.g. GA history, chosen lambda, truncation rank).
    """

    method: str
    names: list[str]
    x: np.ndarray
    residuals: np.ndarray
    covariance: np.ndarray | None = None
    n_eval: int = 0
    n_iter: int = 0
    wall_time: float = 0.0
    success: bool = True
    message: str = ""
    fixed: list[str] = field(default_factory=list)
    units: list[str] = field(default_factory=list)
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def residual_rms(self) -> float:
        r = np.asarray(self.residuals, dtype=float)
        return float(np.sqrt(np.mean(r * r))) if r.size else 0.0

    @property
    def std(self) -> np.ndarray | None:
        """Standard deviation of each parameter (square root of the covariance diagonal)."""
        if self.covariance is None:
            return None
        return np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))

    def as_dict(self) -> dict[str, float]:
        """Parameters as ``{name: value}`` in the problem's internal units."""
        return {n: float(v) for n, v in zip(self.names, self.x)}
