"""Identification of the zero offsets (and the MAEMM) from distance changes between adjacent positions
(paper sections 4, eq. 14-30).

At position k the measuring mechanism's length is ``ρ_k ≈ λ_k + λ̂_k^T (Δr_k - ΔrM)`` (eq. 19-20), i.e.
``ρ_k - λ_k = g_k Δp`` with ``g_k = λ̂_k^T [J_k  -I]`` (eq. 21, 28). The linear scale reads changes
between adjacent positions, so each reading gives ``(ρ_{k+1} - ρ_k) - (λ_{k+1} - λ_k) = (g_{k+1} - g_k) Δp``
(eq. 23); stacked, ``Δλ = G Δp`` (eq. 24, 28).

Unknowns, scaled as in the seed (all mm): simplified model ``Δp = (L1 Δθ1, L2 Δθ2, ΔrMx, ΔrMy)``; full
model ``Δp' = (L1 Δθ1, Δe1x, Δe1y, ΔL1, Δl1, L2 Δθ2, ..., Δl2, ΔrMx, ΔrMy)``. Results are returned as
:class:`pmcal.calib.solvers.result.IdentResult` in calib units (rad for zero offsets, mm otherwise).

Positions ``r`` are the nominal positions the controller believes it commanded (mm, seed frame).
"""

from __future__ import annotations

import time

import numpy as np

from pmcal.mechanism.planar.geometry import FULL_KEYS, SIMPLIFIED_KEYS, Geometry, internal_unit
from pmcal.mechanism.planar.kinematics import jacobian, mm_vector
from pmcal.mechanism.planar.noise import Noise
from pmcal.calib.closed_chain import reading_operator
from pmcal.calib.solvers.linear import tsvd_solve
from pmcal.calib.solvers.result import IdentResult

MODELS = {"simplified": SIMPLIFIED_KEYS, "full": FULL_KEYS}
METHODS = ("tsvd", "ls", "gls")
#: default relative singular-value cut of the TSVD: keeps the numerical rank (the paper's eq. 29 keeps all
#: four singular values of the simplified model, κ ≈ 475; the full model loses three, see docs/planar.md)
DEFAULT_RTOL = 1e-9


def difference_operator(n_positions: int, segments: np.ndarray | None = None) -> np.ndarray:
    """(rows, n_positions) matrix of adjacent differences ``x_{k+1} - x_k`` within each segment: the scale
    read relative to the previous position (eq. 23), the generic core's
    :func:`pmcal.calib.closed_chain.reading_operator` with reference ``"previous"``.

    ``segments`` labels the positions of separate chains of readings (a campaign each, the scale reset
    at its start); ``None`` is one chain. Rows follow the order of the positions.
    """
    return reading_operator(n_positions, "previous", segments)


def observation_rows(geom: Geometry, r: np.ndarray, model: str = "simplified",
                     drM: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Rows ``g_k`` (K, n) of eq. 21 / 28 and nominal mechanism lengths ``λ_k`` (K,) mm.

    ``drM``: MAEMM already identified, corrects the nominal mechanism vector (eq. 30).
    """
    if model not in MODELS:
        raise ValueError(f"unknown model '{model}' (simplified or full)")
    lam = mm_vector(geom, r, drM)
    length = np.linalg.norm(lam, axis=-1)
    lhat = lam / length[..., None]
    J = jacobian(geom, r, model)
    g = np.concatenate([np.einsum("ki,kij->kj", lhat, J), -lhat], axis=-1)
    return g, length


def system(geom: Geometry, r: np.ndarray, readings: np.ndarray, model: str = "simplified",
           drM: np.ndarray | None = None, segments: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Identification matrix ``G`` (rows, n) and left-hand side ``Δλ`` (rows,) mm of eq. 24 / 28.

    ``readings``: the scale changes ``ρ_{k+1} - ρ_k`` (mm), one per row of :func:`difference_operator`.
    """
    g, lam = observation_rows(geom, r, model, drM)
    D = difference_operator(len(lam), segments)
    readings = np.asarray(readings, dtype=float)
    if readings.shape != (D.shape[0],):
        raise ValueError(f"{readings.size} readings for {D.shape[0]} adjacent pairs")
    return D @ g, readings - D @ lam


def identification_matrix(geom: Geometry, r: np.ndarray, model: str = "simplified",
                          drM: np.ndarray | None = None, segments: np.ndarray | None = None) -> np.ndarray:
    """``G`` of eq. 24 / 28 alone (for rank and condition studies)."""
    g, _ = observation_rows(geom, r, model, drM)
    return difference_operator(len(g), segments) @ g


def reading_covariance(geom: Geometry, r: np.ndarray, noise: Noise,
                       segments: np.ndarray | None = None) -> np.ndarray:
    """Covariance (rows, rows) mm² of the readings of eq. 24 under the noise of eq. 34-35.

    Each reading carries one scale error (σ_m², independent); the servo error ξ at position k moves P by
    ``J_k diag(L) ξ_k`` and the mechanism length by ``λ̂_k^T J_k diag(L) ξ_k``; it enters the readings
    before and after position k, which correlates adjacent readings.
    """
    g, _ = observation_rows(geom, r, "simplified")
    return covariance_from_sensitivity(servo_sensitivity(geom, g), noise, difference_operator(len(g), segments))


def servo_sensitivity(geom: Geometry, g: np.ndarray) -> np.ndarray:
    """``|dρ_k/dθ_k|²`` (..., K) mm²/rad²: how much the servo errors of both motors at position k move the
    mechanism length, from the simplified rows ``g`` (..., K, 4) of :func:`observation_rows`."""
    return np.sum((g[..., :2] * geom.L) ** 2, axis=-1)


def covariance_from_sensitivity(sens_sq: np.ndarray, noise: Noise, D: np.ndarray) -> np.ndarray:
    """Reading covariance ``σ_m² I + ξ² D diag(|dρ_k/dθ_k|²) D^T`` (..., rows, rows), batched over designs."""
    servo = (D * sens_sq[..., None, :]) @ D.T
    return noise.scale**2 * np.eye(D.shape[0]) + noise.servo**2 * servo


def condition_number(G: np.ndarray) -> float:
    """``κ = σ_max / σ_min`` of a matrix (the paper's criterion, eq. 31)."""
    s = np.linalg.svd(G, compute_uv=False)
    return float(s[0] / s[-1]) if s[-1] > 0 else float("inf")


def _scale(geom: Geometry, model: str) -> np.ndarray:
    """Factors from calib units (rad, mm) to the paper's scaled unknowns (mm)."""
    keys = MODELS[model]
    return np.array([geom.L[0] if k == "dtheta1" else geom.L[1] if k == "dtheta2" else 1.0 for k in keys])


def identify(geom: Geometry, r: np.ndarray, readings: np.ndarray, *, model: str = "simplified",
             method: str = "tsvd", rank: int | None = None, rtol: float = DEFAULT_RTOL,
             drM: np.ndarray | None = None, segments: np.ndarray | None = None,
             noise: Noise | None = None) -> IdentResult:
    """Identify ``Δp`` from scale readings at nominal positions ``r`` (K, 2) mm.

    method ``"tsvd"`` (eq. 29 / 27): truncated SVD of ``G``, ``rank`` singular values kept (default: the
    numerical rank, relative cut ``rtol``). ``"ls"`` (eq. 25): normal equations; flagged unsuccessful
    (and solved minimum-norm) when ``G^T G`` is singular, as for the full model. ``"gls"``: TSVD of the
    system whitened with :func:`reading_covariance` (needs ``noise``), the best linear unbiased estimate.

    ``drM`` corrects the mechanism with a previous MAEMM estimate (eq. 30); the result is then the
    remaining MAEMM. ``noise`` (if given) is used for the parameter covariance; otherwise the covariance
    is scaled by the residual variance when there are more readings than kept singular values.
    """
    t0 = time.perf_counter()
    if method not in METHODS:
        raise ValueError(f"unknown method '{method}' ({', '.join(METHODS)})")
    G, y = system(geom, r, readings, model, drM, segments)
    n = G.shape[1]
    C = reading_covariance(geom, r, noise, segments) if noise is not None else None
    success, message = True, ""
    if method == "gls":
        if C is None:
            raise ValueError("method 'gls' needs the noise model")
        Lc = np.linalg.cholesky(C)
        Gs, ys = np.linalg.solve(Lc, G), np.linalg.solve(Lc, y)
    else:
        Gs, ys = G, y
    sol = tsvd_solve(Gs, ys, rank=rank if method != "ls" else None, rtol=rtol)
    if method == "ls":
        if sol.rank < n:
            success = False
            message = (f"G^T G is singular (rank {sol.rank} < {n} unknowns): eq. 25 has no unique solution; "
                       f"minimum-norm solution returned")
        else:
            sol.dx = np.linalg.solve(G.T @ G, G.T @ y)
    s = sol.singular_values
    U, _, Vt = np.linalg.svd(Gs, full_matrices=False)
    k = sol.rank
    P = Vt[:k].T @ (U[:, :k] / s[:k]).T                          # the pseudo-inverse applied
    if method == "gls":
        cov_scaled = P @ P.T
    elif C is not None:
        cov_scaled = P @ C @ P.T
    else:
        dof = G.shape[0] - k
        res0 = y - G @ sol.dx
        s2 = float(res0 @ res0) / dof if dof > 0 else float("nan")
        cov_scaled = s2 * (P @ P.T)
    f = _scale(geom, model)
    x = sol.dx / f
    cov = cov_scaled / np.outer(f, f)
    residuals = y - G @ sol.dx
    keys = list(MODELS[model])
    return IdentResult(
        method=method, names=keys, x=x, residuals=residuals, covariance=cov, n_eval=1, n_iter=1,
        wall_time=time.perf_counter() - t0, success=success, message=message,
        units=[internal_unit(k) for k in keys],
        info={"model": model, "rank": int(k), "singular_values": s, "cond": condition_number(G),
              "scaled_x_mm": sol.dx, "n_readings": int(G.shape[0]),
              "drM_correction": None if drM is None else np.asarray(drM, dtype=float)})
