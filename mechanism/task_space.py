"""Task coordinates of a closed-chain machine: the pose of its task site as the columns a machine.toml names.

Coordinates (:data:`pmcal.mechanism.machine_spec.TASK_COORDINATES`): ``x_mm``, ``y_mm``, ``z_mm`` (the
site's position, mm, world frame); ``rx_deg``, ``ry_deg``, ``rz_deg`` (the site frame's orientation
``R = Rz(rz) Ry(ry) Rx(rx)`` relative to the world frame, deg, in (-180, 180]); ``phi_deg``, ``theta_deg``
(the tilt-torsion pair of the site's z axis, :func:`pmcal.mechanism.rotations.tilt_torsion_angles`, deg).

Example
-------
>>> import numpy as np
>>> task_coordinates(np.array([[1.0, 2.0, 3.0]]), np.eye(3)[None], ("z_mm", "rz_deg"))
array([[3., 0.]])
"""

from __future__ import annotations

import numpy as np

from pmcal.mechanism.rotations import tilt_torsion_angles

POSITION = ("x_mm", "y_mm", "z_mm")
ANGLES = ("rx_deg", "ry_deg", "rz_deg", "phi_deg", "theta_deg")


def rpy_angles(R: np.ndarray) -> np.ndarray:
    """(rx, ry, rz) rad (..., 3) of rotation matrices (..., 3, 3) with ``R = Rz(rz) Ry(ry) Rx(rx)``."""
    R = np.asarray(R, dtype=float)
    ry = np.arcsin(np.clip(-R[..., 2, 0], -1.0, 1.0))
    rx = np.arctan2(R[..., 2, 1], R[..., 2, 2])
    rz = np.arctan2(R[..., 1, 0], R[..., 0, 0])
    return np.stack([rx, ry, rz], axis=-1)


def task_coordinates(p_mm: np.ndarray, R: np.ndarray, coordinates: tuple[str, ...]) -> np.ndarray:
    """Task coordinates (N, C) of site positions ``p_mm`` (N, 3) and orientations ``R`` (N, 3, 3)."""
    p_mm, R = np.asarray(p_mm, float), np.asarray(R, float)
    cols = {}
    for k, c in enumerate(POSITION):
        cols[c] = p_mm[..., k]
    if {"rx_deg", "ry_deg", "rz_deg"} & set(coordinates):
        rpy = np.rad2deg(rpy_angles(R))
        cols.update(rx_deg=rpy[..., 0], ry_deg=rpy[..., 1], rz_deg=rpy[..., 2])
    if "phi_deg" in coordinates:
        phi, theta = tilt_torsion_angles(R)
        cols.update(phi_deg=np.rad2deg(phi), theta_deg=np.rad2deg(theta))
    return np.stack([cols[c] for c in coordinates], axis=-1)


def task_difference(a: np.ndarray, b: np.ndarray, coordinates: tuple[str, ...]) -> np.ndarray:
    """``a - b`` (..., C) with angle differences wrapped to (-180, 180] deg."""
    d = np.asarray(a, float) - np.asarray(b, float)
    ang = np.array([c in ANGLES for c in coordinates])
    d[..., ang] = (d[..., ang] + 180.0) % 360.0 - 180.0
    return d


def position_distance(d: np.ndarray, coordinates: tuple[str, ...]) -> np.ndarray:
    """Distance (...,) mm that task differences ``d`` (..., C) make over the position coordinates among
    ``coordinates`` (:data:`POSITION`); 0 for a machine without any."""
    d = np.asarray(d, float)
    idx = [i for i, c in enumerate(coordinates) if c in POSITION]
    return np.linalg.norm(d[..., idx], axis=-1) if idx else np.zeros(d.shape[:-1])



def rms(x) -> float:
    """Root mean square of errors ``x`` (any shape), in their unit."""
    return float(np.sqrt(np.mean(np.square(np.asarray(x, float)))))


def angle_distance(d: np.ndarray, coordinates: tuple[str, ...]) -> np.ndarray:
    """Size (...,) deg of task differences ``d`` (..., C) over the angle coordinates among ``coordinates``
    (:data:`ANGLES`): the Euclidean norm of their differences (for small rotations about x, y, z, the angle
    of the rotation); 0 for a machine without any."""
    d = np.asarray(d, float)
    idx = [i for i, c in enumerate(coordinates) if c in ANGLES]
    return np.linalg.norm(d[..., idx], axis=-1) if idx else np.zeros(d.shape[:-1])


#: the families of task error: name, unit, the coordinates it covers, and the size of a task difference
FAMILIES = (("position", "mm", POSITION, position_distance), ("orientation", "deg", ANGLES, angle_distance))


def error_families(coordinates: tuple[str, ...]) -> list[tuple]:
    """The entries of :data:`FAMILIES` a machine's task coordinates hold: position (mm) if it has any of
    :data:`POSITION`, orientation (deg) if any of :data:`ANGLES`; both for a mixed task. Figures of a task's
    error are given in each (an orientation machine's in deg)."""
    return [f for f in FAMILIES if any(c in f[2] for c in coordinates)]
