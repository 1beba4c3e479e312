"""Measurement positions: the paper's boundary positions and condition numbers (section 5, eq. 31, Fig. 7-8),
and positions chosen for the smallest zero-offset uncertainty (this project's addition, docs/planar.md).

Positions are (K, 2) arrays in mm (seed frame, y up), in the order the platform visits them.
"""

from __future__ import annotations


import numpy as np

from pmcal.mechanism.planar.geometry import Geometry, Workspace
from pmcal.calib.planar.identification import (condition_number, covariance_from_sensitivity, difference_operator,
                                         identification_matrix, observation_rows, servo_sensitivity)
from pmcal.mechanism.planar.kinematics import mm_vector
from pmcal.mechanism.planar.noise import Noise
from pmcal.mechanism.planar.region import Region


def boundary_positions(ws: Workspace, n: int) -> np.ndarray:
    """Fig. 7: ``n`` evenly spaced positions on the upper boundary of W (corners included, left to right),
    then ``n`` on the lower boundary (left to right); K = 2n. This order reproduces the paper's
    κ1 = 475.34 at n = 3 (Fig. 8)."""
    if n < 2:
        raise ValueError("at least 2 positions per boundary")
    x = np.linspace(-ws.b / 2, ws.b / 2, n)
    upper = np.stack([x, np.full(n, ws.y_upper)], 1)
    lower = np.stack([x, np.full(n, ws.y_lower)], 1)
    return np.concatenate([upper, lower])


def condition_study(geom: Geometry, ws: Workspace, ns, drM_later: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """κ1 (first identification) and κm (later identifications, mechanism corrected by ``drM_later``, eq. 30)
    of the simplified model for each n in ``ns`` (Fig. 8)."""
    k1, km = [], []
    for n in ns:
        r = boundary_positions(ws, n)
        k1.append(condition_number(identification_matrix(geom, r)))
        km.append(condition_number(identification_matrix(geom, r, drM=drM_later)))
    return np.array(k1), np.array(km)


def choose_n(geom: Geometry, ws: Workspace, eps0: float, drM_later: np.ndarray, ns=range(3, 22, 2)) -> int:
    """Eq. 31: the smallest n (K = 2n > 5) whose relative difference ``|κ1 - κm| / κ1`` is within ``eps0``.

    The paper's Fig. 8 evaluates odd n = 3..21, over which κ1 and κm grow with n, so the smallest
    admissible n also gives the smallest condition numbers (even n = 4 dips to κ1 = 457.8)."""
    ns = [n for n in ns if 2 * n > 5]
    k1, km = condition_study(geom, ws, ns, drM_later)
    ok = np.abs(k1 - km) / k1 <= eps0
    if not np.any(ok):
        raise ValueError(f"no n in {ns[0]}..{ns[-1]} meets eps0 = {eps0}")
    return int(np.asarray(ns)[np.argmax(ok)])


def zero_offset_covariance(geom: Geometry, r: np.ndarray, noise: Noise) -> np.ndarray:
    """Covariance (4, 4) of the best linear unbiased estimate of (Δθ1, Δθ2 [rad], ΔrMx, ΔrMy [mm]) from one
    chain of readings at ``r`` under ``noise`` (the Cramér-Rao bound for Gaussian noise)."""
    g, sens_sq, _ = _candidate_terms(geom, r)
    return _batch_covariance(g, sens_sq, noise, geom)


def _candidate_terms(geom: Geometry, r: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    g, _ = observation_rows(geom, r)
    length = np.linalg.norm(mm_vector(geom, r), axis=-1)
    return g, servo_sensitivity(geom, g), length


def _batch_covariance(g: np.ndarray, sens_sq: np.ndarray, noise: Noise, geom: Geometry) -> np.ndarray:
    """GLS covariance (..., 4, 4) in (rad, rad, mm, mm) for designs g (..., K, 4), sens_sq (..., K)."""
    D = difference_operator(g.shape[-2])
    G = D @ g
    C = covariance_from_sensitivity(sens_sq, noise, D)
    F = np.swapaxes(G, -1, -2) @ np.linalg.solve(C, G)
    ev = np.linalg.eigvalsh(F)
    singular = ev[..., 0] <= 1e-10 * ev[..., -1]                  # Δp not identifiable: no covariance
    F = np.where(singular[..., None, None], np.eye(F.shape[-1]), F)
    cov = np.linalg.inv(F)
    cov = np.where(singular[..., None, None], np.inf, cov)
    f = np.array([geom.L[0], geom.L[1], 1.0, 1.0])
    return cov / np.outer(f, f)


def optimal_positions(geom: Geometry, region: Region, K: int, noise: Noise, *, step: float = 25.0,
                      restarts: int = 6, seed: int = 0, max_sweeps: int = 8) -> np.ndarray:
    """K positions (in visiting order) that minimise the variance of the zero-offset estimates.

    Criterion: ``var(Δθ1) + var(Δθ2)`` of the GLS estimate (:func:`zero_offset_covariance`) with the
    MAEMM unknown, over the grid :meth:`Region.candidates`; designs whose mechanism lengths span more than
    the scale's range are refused. Exchange algorithm (Fedorov): replace one position at a time by the
    best candidate, until a sweep changes nothing; best of ``restarts`` random starts. Deterministic for a
    given ``seed``.
    """
    cand = region.candidates(geom, step)
    if len(cand) < K:
        raise ValueError("the region holds fewer admissible positions than requested")
    g, sens, length = _candidate_terms(geom, cand)
    rng = np.random.default_rng(seed)

    def crit(designs: np.ndarray) -> np.ndarray:
        cov = _batch_covariance(g[designs], sens[designs], noise, geom)
        val = cov[..., 0, 0] + cov[..., 1, 1]
        span = length[designs].max(-1) - length[designs].min(-1)
        bad = (span > region.scale_range) | ~np.isfinite(val) | (val <= 0)
        return np.where(bad, np.inf, val)

    best, best_val = None, np.inf
    for _ in range(restarts):
        for _try in range(200):
            design = rng.choice(len(cand), K, replace=False)
            if np.isfinite(crit(design[None])[0]):
                break
        else:
            continue
        val = crit(design[None])[0]
        for _sweep in range(max_sweeps):
            changed = False
            for a in range(K):
                trial = np.repeat(design[None], len(cand), axis=0)
                trial[:, a] = np.arange(len(cand))
                v = crit(trial)
                j = int(np.argmin(v))
                if v[j] < val * (1 - 1e-9):
                    design, val, changed = trial[j], v[j], True
            if not changed:
                break
        if val < best_val:
            best, best_val = design.copy(), val
    if best is None:
        raise ValueError("no admissible design found in the region (scale range too small?)")
    return cand[best]
