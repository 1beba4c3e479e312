"""Tracker noise from the measurements alone, without any model of the machine (numerics only).

A pose's k targets determine its platform pose and, because the platform is rigid (or, with thermal
expansion, uniformly scaled), leave 3k - 7 coordinates of pure noise: the residuals of the best
similarity transform of their platform coordinates. Units: mm.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from pmcal.mechanism.ocpm.config import Geometry
from pmcal.mechanism.ocpm.data import Measurements


@dataclass
class NoiseEstimate:
    """sigma_mm: the value used; source: "given" or "estimated"; free/free_robust: model-free estimates
    (classical, median-based) from the similarity residuals with ``dof`` degrees of freedom; repeat: from
    repeated commands (None without repeats)."""

    sigma_mm: float
    source: str
    free_mm: float
    free_robust_mm: float
    dof: int
    repeat_mm: float | None = None


def similarity_residuals(targets: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Residuals (N, k, 3) mm of the best similarity transform (rotation, translation, scale) of the
    platform coordinates X (k, 3) onto each pose's measured targets (N, k, 3): pure noise on a rigid or
    uniformly expanding platform, 3k - 7 dof a pose."""
    Xc = X - X.mean(0)
    Yc = targets - targets.mean(1, keepdims=True)
    H = np.einsum("ki,nkj->nij", Xc, Yc)
    U, S, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.swapaxes(Vt, 1, 2) @ np.swapaxes(U, 1, 2)))
    D = np.ones((len(targets), 3))
    D[:, 2] = d
    R = np.swapaxes(Vt, 1, 2) @ (D[:, :, None] * np.swapaxes(U, 1, 2))
    s = np.sum(S * D, axis=1) / np.sum(Xc * Xc)
    return Yc - s[:, None, None] * np.einsum("nij,kj->nki", R, Xc)


def estimate_noise(meas: Measurements, geom: Geometry, sigma_mm: float | None = None) -> NoiseEstimate:
    """Tracker noise from the data (and the given value, if any)."""
    X = geom.targets[: meas.targets.shape[1]]
    res = similarity_residuals(meas.targets, X)
    per_dof = 3 * len(X) - 7
    u = np.sum(res**2, axis=(1, 2))
    free = float(np.sqrt(u.sum() / (per_dof * len(meas))))
    robust = float(np.sqrt(np.median(u) / stats.chi2.median(per_dof)))
    repeat = None
    key = np.round(meas.m_cmd_deg, 6)
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    if np.any(counts > 1):
        inv = inv.ravel()
        groups = [np.flatnonzero(inv == g) for g in np.flatnonzero(counts > 1)]
        ss = sum(float(np.sum((meas.targets[g] - meas.targets[g].mean(0)) ** 2)) for g in groups)
        dof = sum((len(g) - 1) * meas.targets[0].size for g in groups)
        repeat = float(np.sqrt(ss / dof))
    given = sigma_mm is not None
    return NoiseEstimate(sigma_mm=float(sigma_mm) if given else free, source="given" if given else "estimated",
                         free_mm=free, free_robust_mm=robust, dof=per_dof * len(meas), repeat_mm=repeat)


