"""Identifiability of a least-squares identification problem from its Jacobian.

For whitened residuals (unit noise variance) with Jacobian ``J`` (m, n):

- the *effect* of parameter k is ``|J_k| * scale_k``: how many noise standard deviations (root of the
  chi-square change) moving it across its whole prior range (search box half-width) produces. Below 1
  the data cannot see it at first order: it is *unidentifiable* and named in plain words;
- the condition number of the remaining columns, normalised to unit length (scale-free), and the
  singular values; the smallest singular directions name the parameter combinations the data barely see;
- the Cramér-Rao standard deviation per parameter ``sqrt(diag((J^T J)^{-1}))`` (unidentifiable ones:
  inf) and the correlation matrix; parameters whose CRLB exceeds their prior range are *weak*.

Units: the parameters' own (mm, rad inside calib); the Jacobian per those units.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from pmcal.calib.solvers.base import crlb_covariance
from pmcal.calib.solvers.problem import Problem


@dataclass
class Identifiability:
    """Result of :func:`analyse_jacobian` (see module docstring)."""

    names: list[str]
    units: list[str]
    effect: np.ndarray                 # (n,) whole-range effect in noise sigmas
    unidentifiable: list[str]
    weak: list[str]
    singular_values: np.ndarray        # of the identifiable, column-normalised Jacobian
    condition_number: float            # same, s_max / s_min
    condition_number_scaled: float     # identifiable columns scaled by the prior range
    crlb_std: np.ndarray               # (n,) parameter units; inf where unidentifiable
    correlation: np.ndarray            # (n, n); NaN rows/cols where unidentifiable
    weakest: list[dict[str, float]] = field(default_factory=list)   # smallest singular directions
    explanations: dict[str, str] = field(default_factory=dict)

    @property
    def identifiable(self) -> list[str]:
        return [k for k in self.names if k not in self.unidentifiable]

    def std(self, name: str) -> float:
        return float(self.crlb_std[self.names.index(name)])

    def strongest_correlations(self, count: int = 5) -> list[tuple[str, str, float]]:
        """The ``count`` largest |correlations| between distinct identifiable parameters."""
        C = np.nan_to_num(self.correlation, nan=0.0)
        iu = np.triu_indices(len(self.names), 1)
        order = np.argsort(-np.abs(C[iu]))[:count]
        return [(self.names[iu[0][o]], self.names[iu[1][o]], float(C[iu][o])) for o in order]

    def summary(self) -> dict:
        """JSON-friendly digest (for the parameters file and reports)."""
        return {"condition_number": self.condition_number, "condition_number_scaled": self.condition_number_scaled,
                "unidentifiable": self.unidentifiable, "weak": self.weak,
                "explanations": {k: self.explanations.get(k, "") for k in self.unidentifiable},
                "crlb_std": {k: float(v) for k, v in zip(self.names, self.crlb_std)},
                "rank": int(len(self.singular_values))}


def analyse_jacobian(J: np.ndarray, names: list[str], units: list[str] | None = None,
                     scale: np.ndarray | None = None, min_effect: float = 1.0,
                     explain: Callable[[str], str] | None = None, n_weakest: int = 3) -> Identifiability:
    """Identifiability from a whitened Jacobian ``J`` (m, n) (see module docstring)."""
    J = np.asarray(J, float)
    n = J.shape[1]
    scale = np.ones(n) if scale is None else np.asarray(scale, float)
    units = list(units) if units else [""] * n
    norms = np.linalg.norm(J, axis=0)
    effect = norms * scale
    ok = effect >= min_effect
    idx = np.flatnonzero(ok)
    crlb = np.full(n, np.inf)
    corr = np.full((n, n), np.nan)
    sv, cond, cond_s, weakest = np.zeros(0), np.inf, np.inf, []
    if idx.size:
        Jn = J[:, idx] / norms[idx]
        U, sv, Vt = np.linalg.svd(Jn, full_matrices=False)
        cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else np.inf
        ss = np.linalg.svd(J[:, idx] * scale[idx], compute_uv=False)
        cond_s = float(ss[0] / ss[-1]) if ss[-1] > 0 else np.inf
        cov = crlb_covariance(J[:, idx])
        d = np.sqrt(np.clip(np.diag(cov), 0, None))
        crlb[idx] = d
        corr[np.ix_(idx, idx)] = cov / np.outer(d, d)
        for k in range(1, min(n_weakest, idx.size) + 1):
            v = Vt[-k] / norms[idx]                        # direction in parameter units
            v = v / np.max(np.abs(v * scale[idx]))
            big = np.argsort(-np.abs(v * scale[idx]))[:4]
            weakest.append({"singular_value": float(sv[-k]),
                            **{names[idx[b]]: float(v[b]) for b in big if abs(v[b] * scale[idx[b]]) > 0.1}})
    weak = [names[k] for k in idx if crlb[k] > scale[k]]
    unid = [names[k] for k in range(n) if not ok[k]]
    explain = explain or (lambda k: "")
    return Identifiability(names=list(names), units=units, effect=effect, unidentifiable=unid, weak=weak,
                           singular_values=sv, condition_number=cond, condition_number_scaled=cond_s,
                           crlb_std=crlb, correlation=corr, weakest=weakest,
                           explanations={k: explain(k) for k in names})


def analyse(problem: Problem, x: np.ndarray | None = None, **kwargs) -> Identifiability:
    """:func:`analyse_jacobian` of a problem at ``x`` (default its prior ``x0``)."""
    x = problem.x0 if x is None else np.asarray(x, float)
    J = problem.jacobian(x) / problem.sigma
    n_prior = problem.info.get("n_prior", 0)
    if n_prior:
        J = J[: J.shape[0] - n_prior]
    return analyse_jacobian(J, problem.names, problem.units, problem.scale, **kwargs)
