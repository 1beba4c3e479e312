"""Platform pose from measured tracker targets.

A pose is the rigid transform (r, R) that maps the targets' platform coordinates X (k, 3) onto their
measured base-frame coordinates Y: ``Y_i ≈ r + R X_i``. Units: mm.
"""

from __future__ import annotations

import numpy as np


def fit_pose(Y: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares rigid fit (Kabsch/Umeyama without scale) for k ≥ 3 targets.

    Parameters
    ----------
    Y : (..., k, 3) measured target coordinates in the base frame, mm.
    X : (k, 3) target coordinates in the platform frame, mm.

    Returns
    -------
    r : (..., 3) position of the platform frame origin (C_E), mm.
    R : (..., 3, 3) platform orientation.
    rms : (...,) root-mean-square distance of the fitted targets from the measured ones, mm.
    """
    Y = np.asarray(Y, dtype=float)
    X = np.asarray(X, dtype=float)
    if X.ndim != 2 or X.shape[0] < 3 or Y.shape[-2:] != X.shape:
        raise ValueError(f"need Y (..., k, 3) and X (k, 3) with k >= 3, got {Y.shape} and {X.shape}")
    xc = X.mean(axis=0)
    yc = Y.mean(axis=-2)
    H = np.einsum("ki,...kj->...ij", X - xc, Y - yc[..., None, :])
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.swapaxes(Vt, -1, -2) @ np.swapaxes(U, -1, -2)))
    D = np.zeros(H.shape)
    D[..., 0, 0] = 1.0
    D[..., 1, 1] = 1.0
    D[..., 2, 2] = d
    R = np.swapaxes(Vt, -1, -2) @ D @ np.swapaxes(U, -1, -2)
    r = yc - np.einsum("...ij,j->...i", R, xc)
    pred = r[..., None, :] + np.einsum("...ij,kj->...ki", R, X)
    rms = np.sqrt(np.mean(np.sum((pred - Y) ** 2, axis=-1), axis=-1))
    return r, R, rms


def _three_point_frame(P: np.ndarray) -> np.ndarray:
    """Paper 000 eq. 16: u along P2->P1, w normal to the plane of P1, P2, P3, v = w × u."""
    P = np.asarray(P, dtype=float)
    p21 = P[..., 0, :] - P[..., 1, :]
    p23 = P[..., 2, :] - P[..., 1, :]
    u = p21 / np.linalg.norm(p21, axis=-1, keepdims=True)
    w = np.cross(p21, p23)
    w /= np.linalg.norm(w, axis=-1, keepdims=True)
    v = np.cross(w, u)
    return np.stack([u, v, w], axis=-1)


def pose_from_three_points(Y: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The paper's three-point construction (eq. 16) generalised to any platform target layout.

    The frame of eq. 16 built on the measured points, composed with the inverse of the same frame built
    on the nominal platform coordinates, gives the platform orientation; the position follows from the
    centroid. Exact on noise-free data; with noise it is not least-squares (use :func:`fit_pose`).
    """
    Y = np.asarray(Y, dtype=float)[..., :3, :]
    X = np.asarray(X, dtype=float)[:3]
    R = _three_point_frame(Y) @ _three_point_frame(X).T
    r = Y.mean(axis=-2) - np.einsum("...ij,j->...i", R, X.mean(axis=0))
    return r, R
