"""Rotation matrices, vectorised over leading dimensions. Angles in radians."""

from __future__ import annotations

import numpy as np


def _axis_rot(angle, i: int, j: int) -> np.ndarray:
    angle = np.asarray(angle, dtype=float)
    c, s = np.cos(angle), np.sin(angle)
    R = np.zeros(angle.shape + (3, 3))
    k = 3 - i - j
    R[..., k, k] = 1.0
    R[..., i, i] = c
    R[..., j, j] = c
    R[..., i, j] = -s
    R[..., j, i] = s
    return R


def rot_x(angle) -> np.ndarray:
    """Rotation about x by ``angle`` (rad); shape ``angle.shape + (3, 3)``."""
    return _axis_rot(angle, 1, 2)


def rot_y(angle) -> np.ndarray:
    """Rotation about y by ``angle`` (rad)."""
    return _axis_rot(angle, 2, 0)


def rot_z(angle) -> np.ndarray:
    """Rotation about z by ``angle`` (rad)."""
    return _axis_rot(angle, 0, 1)


def tilt_torsion(phi, theta) -> np.ndarray:
    """Platform orientation of paper 000 eq. 4: ``R = Rz(phi) Ry(theta) Rz(-phi)``.

    ``phi`` is the azimuth of the tilt axis' normal, ``theta`` the tilt; both rad, broadcast together.
    """
    phi, theta = np.broadcast_arrays(np.asarray(phi, float), np.asarray(theta, float))
    return rot_z(phi) @ rot_y(theta) @ rot_z(-phi)


def tilt_torsion_angles(R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(phi, theta) of a rotation matrix by paper eq. 17: ``theta = acos(R33)``, ``phi = atan2(R23, R13)``.

    ``phi`` is returned in [0, 2 pi); at ``theta = 0`` it is undefined and returned as 0.
    """
    R = np.asarray(R, dtype=float)
    theta = np.arccos(np.clip(R[..., 2, 2], -1.0, 1.0))
    phi = np.mod(np.arctan2(R[..., 1, 2], R[..., 0, 2]), 2 * np.pi)
    return phi, theta


def pointing_error(R_a: np.ndarray, R_b: np.ndarray) -> np.ndarray:
    """Angle (rad) between the platform normals (third columns) of two orientations.

    This is the pointing error of the platform: the tilt-torsion parametrisation makes the normal
    ``w`` the pointing direction. It is free of the phi singularity at theta = 0.
    """
    w_a, w_b = np.asarray(R_a)[..., :, 2], np.asarray(R_b)[..., :, 2]
    c = np.clip(np.sum(w_a * w_b, axis=-1), -1.0, 1.0)
    s = np.linalg.norm(np.cross(w_a, w_b), axis=-1)
    return np.arctan2(s, c)


def rotation_angle(R_a: np.ndarray, R_b: np.ndarray) -> np.ndarray:
    """Full rotation angle (rad) of ``R_a^T R_b`` (includes torsion about the normal)."""
    M = np.swapaxes(np.asarray(R_a), -1, -2) @ np.asarray(R_b)
    tr = np.trace(M, axis1=-2, axis2=-1)
    skew = np.stack([M[..., 2, 1] - M[..., 1, 2], M[..., 0, 2] - M[..., 2, 0], M[..., 1, 0] - M[..., 0, 1]], -1)
    return np.arctan2(0.5 * np.linalg.norm(skew, axis=-1), 0.5 * (tr - 1.0))


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices ``[v]x`` (..., 3, 3) of vectors (..., 3): ``skew(v) @ u == cross(v, u)``."""
    v = np.asarray(v, dtype=float)
    S = np.zeros(v.shape + (3,))
    S[..., 0, 1], S[..., 0, 2], S[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    S[..., 1, 0], S[..., 2, 0], S[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    return S


def rotvec_matrix(v: np.ndarray) -> np.ndarray:
    """Rotation matrices ``exp([v]x)`` (..., 3, 3) of rotation vectors ``v`` (..., 3), rad (Rodrigues)."""
    v = np.asarray(v, dtype=float)
    a = np.linalg.norm(v, axis=-1)[..., None, None]
    S = skew(v)
    small = a < 1e-8
    a_ = np.where(small, 1.0, a)
    c1 = np.where(small, 1.0 - a * a / 6.0, np.sin(a_) / a_)
    c2 = np.where(small, 0.5 - a * a / 24.0, (1.0 - np.cos(a_)) / (a_ * a_))
    return np.eye(3) + c1 * S + c2 * (S @ S)


def so3_left_jacobian(v: np.ndarray) -> np.ndarray:
    """Left Jacobian of SO(3) (..., 3, 3) at rotation vectors ``v`` (..., 3), rad.

    ``d/dv_k exp([v]x) = [J_l(v) e_k]x exp([v]x)``: the angular velocity (in the frame ``v`` is written in) of
    the rotation ``exp([v]x)`` per unit change of ``v_k``. ``J_l(0) = I``.
    """
    v = np.asarray(v, dtype=float)
    a = np.linalg.norm(v, axis=-1)[..., None, None]
    S = skew(v)
    small = a < 1e-6
    a_ = np.where(small, 1.0, a)
    c1 = np.where(small, 0.5 - a * a / 24.0, (1.0 - np.cos(a_)) / (a_ * a_))
    c2 = np.where(small, 1.0 / 6.0 - a * a / 120.0, (a_ - np.sin(a_)) / (a_ ** 3))
    return np.eye(3) + c1 * S + c2 * (S @ S)
