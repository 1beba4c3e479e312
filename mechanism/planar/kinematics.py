"""Closed-form kinematics and first-order error model of the planar 2-DOF robot (paper eq. 1-13).

All functions are vectorised over leading axes: positions ``r`` are ``(..., 2)`` in mm (seed frame O-xy,
y up, see :mod:`pmcal.mechanism.planar.geometry`), motor angles ``theta`` are ``(..., 2)`` in radians.

Loop equation (eq. 1): ``r = e_i + L_i u_i + l_i w_i`` with ``u_i = (cos θ_i, sin θ_i)`` and ``w_i`` the
unit vector of the distal link. These closed forms are the independent oracle of the MuJoCo twin.
"""

from __future__ import annotations

import numpy as np

from pmcal.mechanism.planar.geometry import Errors, Geometry

#: rotation by +90 degrees (eq. 10): ``Δu_i = Q u_i Δθ_i``
Q = np.array([[0.0, -1.0], [1.0, 0.0]])

#: branch of eq. 3 per limb: limb 1 "elbow out" to the right (θ1 near 0), limb 2 to the left (θ2 near π)
_IK_BRANCH = np.array([-1.0, 1.0])


def unit(theta: np.ndarray) -> np.ndarray:
    """``u = (cos θ, sin θ)``, shape ``theta.shape + (2,)``."""
    theta = np.asarray(theta, dtype=float)
    return np.stack([np.cos(theta), np.sin(theta)], axis=-1)


def inverse(geom: Geometry, r: np.ndarray) -> np.ndarray:
    """Motor angles (..., 2) rad that bring the reference point P to ``r`` (..., 2) mm (eq. 3).

    Eq. 3 writes ``D_i cos θ_i + C_i sin θ_i + E_i = 0`` with ``C_i = -2 L_i (y - e_iy)``,
    ``D_i = -2 L_i (x - e_ix)``, ``E_i = (x - e_ix)^2 + (y - e_iy)^2 + L_i^2 - l_i^2`` and solves it with
    the half-angle substitution, which is singular at θ = π (the home angle of limb 2). The equivalent
    ``θ_i = atan2(C_i, D_i) ∓ arccos(-E_i / sqrt(C_i^2 + D_i^2))`` is used instead, with the assembly
    mode of the paper's robot (both elbows outwards). Unreachable positions give NaN.
    """
    r = np.asarray(r, dtype=float)
    dx = r[..., None, 0] - geom.e[:, 0]
    dy = r[..., None, 1] - geom.e[:, 1]
    C = -2.0 * geom.L * dy
    D = -2.0 * geom.L * dx
    E = dx * dx + dy * dy + geom.L**2 - geom.l**2
    with np.errstate(invalid="ignore"):
        return np.arctan2(C, D) + _IK_BRANCH * np.arccos(-E / np.hypot(C, D))


def forward(geom: Geometry, theta: np.ndarray) -> np.ndarray:
    """Position (..., 2) mm of P for motor angles ``theta`` (..., 2) rad (eq. 5-8).

    Subtracting the two circle equations gives ``x = -(M y + S) / F`` (eq. 6); substituting back gives
    ``N y^2 + Q y + R = 0`` (eq. 7); the platform hangs below the base, so ``y`` is the lower root (eq. 8).
    NaN where the circles do not meet.
    """
    theta = np.asarray(theta, dtype=float)
    # elbows B_i = e_i + L_i u_i, coordinate by coordinate (this runs inside every fit: no stacking)
    x1 = geom.e[0, 0] + geom.L[0] * np.cos(theta[..., 0])
    y1 = geom.e[0, 1] + geom.L[0] * np.sin(theta[..., 0])
    x2 = geom.e[1, 0] + geom.L[1] * np.cos(theta[..., 1])
    y2 = geom.e[1, 1] + geom.L[1] * np.sin(theta[..., 1])
    F = 2.0 * (x2 - x1)
    M = 2.0 * (y2 - y1)
    n1 = x1 * x1 + y1 * y1
    S = n1 - (x2 * x2 + y2 * y2) - (geom.l[0] ** 2 - geom.l[1] ** 2)
    SF, MF = S / F, M / F
    N = 1.0 + MF * MF
    Qc = 2.0 * MF * SF + 2.0 * (x1 * MF - y1)
    R = SF * SF + 2.0 * SF * x1 + n1 - geom.l[0] ** 2
    disc = Qc * Qc - 4.0 * N * R
    y = (-Qc - np.sqrt(np.where(disc >= 0.0, disc, np.nan))) / (2.0 * N)
    out = np.empty(y.shape + (2,))
    out[..., 1] = y
    out[..., 0] = -(M * y + S) / F
    return out


def actual_position(geom: Geometry, err: Errors, theta_cmd: np.ndarray) -> np.ndarray:
    """Where P really goes (mm) on the machine with ``err`` when the controller commands ``theta_cmd``."""
    return forward(geom.perturbed(err), np.asarray(theta_cmd, dtype=float) + err.dtheta)


def directions(geom: Geometry, r: np.ndarray, theta: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Unit vectors ``u`` (proximal) and ``w`` (distal) of both limbs at ``r``, each (..., 2, 2), rows = limbs."""
    r = np.asarray(r, dtype=float)
    theta = inverse(geom, r) if theta is None else np.asarray(theta, dtype=float)
    u = unit(theta)
    w = (r[..., None, :] - geom.e - geom.L[:, None] * u) / geom.l[:, None]
    return u, w


def jacobian(geom: Geometry, r: np.ndarray, model: str = "simplified") -> np.ndarray:
    """Error transfer matrix at the nominal position ``r``: ``Δr = J Δq``.

    ``model="simplified"`` (eq. 13): (..., 2, 2), ``Δq = (L1 Δθ1, L2 Δθ2)`` in mm.
    ``model="full"`` (eq. 12): (..., 2, 10), ``Δq' = (L1 Δθ1, Δe1x, Δe1y, ΔL1, Δl1, L2 Δθ2, ..., Δl2)``.
    Row ``i`` of eq. 11: ``w_i^T Δr = w_i^T Δe_i + ΔL_i w_i^T u_i + L_i w_i^T Q u_i Δθ_i + Δl_i``.
    """
    u, w = directions(geom, r)
    Winv = np.linalg.inv(w)                                      # rows of W are w_1^T, w_2^T
    wQu = np.einsum("...ij,jk,...ik->...i", w, Q, u)
    if model == "simplified":
        return Winv * wQu[..., None, :]
    if model == "full":
        wu = np.sum(w * u, -1)
        blocks = np.stack([wQu, w[..., 0], w[..., 1], wu, np.ones_like(wu)], axis=-1)  # (..., 2, 5)
        out = np.zeros(w.shape[:-2] + (2, 10))
        out[..., 0, :5] = blocks[..., 0, :]
        out[..., 1, 5:] = blocks[..., 1, :]
        return Winv @ out
    raise ValueError(f"unknown model '{model}' (simplified or full)")


def mm_vector(geom: Geometry, r: np.ndarray, drM: np.ndarray | None = None) -> np.ndarray:
    """Vector O1 -> O2 (..., 2) mm of the measuring mechanism with P at ``r`` (eq. 4, 14).

    ``drM`` is a MAEMM estimate to correct the nominal mechanism with (eq. 30): the corrected vector is
    ``r - (c + drM) - d``, the one the mechanism has if its MAEMM is ``drM``.
    """
    lam = np.asarray(r, dtype=float) - geom.c - geom.d
    return lam if drM is None else lam - np.asarray(drM, dtype=float)
