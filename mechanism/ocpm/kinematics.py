"""Closed-form kinematics of the over-constrained PM (paper 000 eq. 4-13), vectorised over poses.

Frames and conventions: docs/formats.md and docs/ocpm_2dof.md. Base frame O-xyz; limb j at azimuth psi_j with local frame
x_j radial, y_j along the base revolute axis, z_j up; the error tilts turn it by Rz(dgamma)·Rx(dalpha).
The first link points along ``Q_j Ry(beta) e_1 = Q_j (cos beta, 0, -sin beta)``. Platform frame C_E-uvw
(the frame the tracker targets define); A_j and the platform revolute axes are given in it.

Units: mm and radians. Shapes: N poses → ``r (N, 3)``, ``R (N, 3, 3)``; results ``(N, n_limbs)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pmcal.mechanism.ocpm.config import Geometry, default_geometry
from pmcal.mechanism.ocpm.params import ErrorSet
from pmcal.mechanism.rotations import rot_x, rot_z, tilt_torsion

E_Y = np.array([0.0, 1.0, 0.0])


def nominal_position(phi, theta, h: float) -> np.ndarray:
    """C_E of the nominal machine (paper eq. 7): ``h (cos phi sin(theta/2), sin phi sin(theta/2), cos(theta/2))``."""
    phi, theta = np.broadcast_arrays(np.asarray(phi, float), np.asarray(theta, float))
    s = np.sin(theta / 2)
    return h * np.stack([np.cos(phi) * s, np.sin(phi) * s, np.cos(theta / 2)], axis=-1)


def nominal_pose(phi, theta, geom: Geometry | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Platform pose (r, R) of the nominal machine at tilt-torsion angles (paper eq. 4 and 7)."""
    geom = geom or default_geometry()
    return nominal_position(phi, theta, geom.h), tilt_torsion(phi, theta)


def limb_frames(psi: np.ndarray, tilt_x: np.ndarray, tilt_z: np.ndarray) -> np.ndarray:
    """Local limb frames ``Rz(psi_j) Rz(tilt_z) Rx(tilt_x)``; columns x_j, y_j (revolute axis), z_j."""
    return rot_z(psi) @ rot_z(tilt_z) @ rot_x(tilt_x)


@dataclass
class LimbIK:
    """Real inverse kinematics of RSR limbs at given platform poses.

    beta : (N, n) joint angle of the base revolute (rad); NaN where the pose is out of reach.
    S : (N, n, 3) centre of the spherical joint S_j from the base side, mm.
    A : (N, n, 3) centre A_j in the base frame, mm.
    planarity : (N, n) distance of S_j from the plane of the platform revolute at A_j, mm. Zero on a
        consistent machine; the closure defect that the paper's distance-only model cannot see.
    reach : (N, n) ``K / rho``: |reach| ≤ 1 is reachable; near ±1 is the singular boundary.
    """

    beta: np.ndarray
    S: np.ndarray
    A: np.ndarray
    planarity: np.ndarray
    reach: np.ndarray


def limb_ik(r: np.ndarray, R: np.ndarray, errors: ErrorSet | None = None,
            geom: Geometry | None = None, limbs: tuple[int, ...] = (1, 2)) -> LimbIK:
    """Real inverse kinematics of RSR limbs with every geometric error (paper eq. 12-13).

    The base revolute angle ``beta`` solves ``|B'_j + (l + dl1) w1(beta) - A'_j| = l + dl2`` (paper eq. 12,
    solved in closed form as in eq. 13) on the operating assembly branch (links up and outward,
    ``beta = -39.351 deg`` at home). ``A'_j = r + R (a_j + da_j)``, ``B'_j = b_j + db_j``, and
    ``w1 = Q_j Ry(beta) e_1`` with the tilted local frame ``Q_j``.

    ``r`` (N, 3) mm, ``R`` (N, 3, 3); error arrays may carry leading batch dimensions (P, ...) to score a
    population at once: the result then has shape (P, N, n).
    """
    geom = geom or default_geometry()
    e = errors if errors is not None else ErrorSet()
    idx = np.asarray(limbs) - 1
    psi = geom.psi[idx]
    batch = np.shape(e.dl1)[:-1]                       # population dims, () for one parameter set
    pre = batch + (1,)                                 # broadcast against the pose axis
    db = np.asarray(e.db)[..., idx, :].reshape(pre + (len(idx), 3))
    da = np.asarray(e.da)[..., idx, :].reshape(pre + (len(idx), 3))
    take = lambda a: np.asarray(a)[..., idx].reshape(pre + (len(idx),))  # noqa: E731
    L1 = geom.l + take(e.dl1)
    L2 = geom.l + take(e.dl2)
    Q1 = limb_frames(psi, take(e.dalpha), take(e.dgamma))          # pre + (n, 3, 3)
    Q2 = limb_frames(psi, take(e.dmu), take(e.dnu))
    B = geom.base_points()[idx] + db                                  # pre + (n, 3)
    a_plat = geom.platform_points()[idx] + da
    A = r[:, None, :] + _rotate(R, a_plat)                            # batch + (N, n, 3)
    p = np.einsum("...ji,...j->...i", Q1, A - B)                   # A - B in the local limb frame
    K = (L1**2 + np.sum(p * p, axis=-1) - L2**2) / (2.0 * L1)
    rho = np.hypot(p[..., 0], p[..., 2])
    reach = K / rho
    delta = np.arctan2(p[..., 2], p[..., 0])
    with np.errstate(invalid="ignore"):
        beta = -delta + np.arccos(np.where(np.abs(reach) <= 1.0, reach, np.nan))
    beta = np.mod(beta + np.pi, 2 * np.pi) - np.pi
    w1_local = np.stack([np.cos(beta), np.zeros_like(beta), -np.sin(beta)], axis=-1)
    S = B + L1[..., None] * np.einsum("...ij,...j->...i", Q1, w1_local)
    n2 = _rotate(R, Q2[..., :, 1])                                   # platform axes in base frame
    planarity = np.sum((S - A) * n2, axis=-1)
    return LimbIK(beta=beta, S=S, A=A, planarity=planarity, reach=reach)


def _rotate(R: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``R_N v`` for poses R (N, 3, 3) and vectors v (batch..., 1, n, 3) -> (batch..., N, n, 3)."""
    return np.einsum("Nij,...nj->...Nni", R, v[..., 0, :, :])


def nominal_ik(phi, theta, geom: Geometry | None = None, limbs: tuple[int, ...] = (1, 2)) -> np.ndarray:
    """Motor angles (rad) of the nominal machine at tilt-torsion angles: ``(N, len(limbs))``."""
    geom = geom or default_geometry()
    r, R = nominal_pose(np.atleast_1d(phi), np.atleast_1d(theta), geom)
    return limb_ik(r, R, None, geom, limbs).beta


def real_ik_commands(r: np.ndarray, R: np.ndarray, errors: ErrorSet, geom: Geometry | None = None,
                     limbs: tuple[int, ...] = (1, 2)) -> np.ndarray:
    """Motor commands (rad) that put a machine with ``errors`` at pose (r, R): joint angle minus zero offset.

    This is the paper's compensation through the real IK, exact for the actuated limbs' closures.
    """
    ik = limb_ik(r, R, errors, geom, limbs)
    idx = np.asarray(limbs) - 1
    dtheta = np.asarray(errors.dtheta)[..., idx]
    return ik.beta - dtheta[..., None, :]


HOME_BETA = float(np.rad2deg(nominal_ik(0.0, 0.0)[0, 0]))


def pointing_coords(phi, theta) -> np.ndarray:
    """Singularity-free orientation coordinates ``p = theta (cos phi, sin phi)`` (rad), shape (..., 2)."""
    phi, theta = np.broadcast_arrays(np.asarray(phi, float), np.asarray(theta, float))
    return np.stack([theta * np.cos(phi), theta * np.sin(phi)], axis=-1)


def from_pointing_coords(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`pointing_coords`: ``(phi in [0, 2 pi), theta >= 0)``."""
    p = np.asarray(p, float)
    return np.mod(np.arctan2(p[..., 1], p[..., 0]), 2 * np.pi), np.hypot(p[..., 0], p[..., 1])


def invert_in_pointing_coords(ik, target: np.ndarray, p0: np.ndarray | None = None, tol: float = 1e-13,
                              max_iter: int = 50, max_step: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """Orientations (phi, theta) rad at which ``ik(phi, theta)`` (N, 2) equals ``target`` (N, 2).

    Newton's method in the singularity-free coordinates ``theta (cos phi, sin phi)`` with a
    forward-difference Jacobian and steps limited to ``max_step`` rad, started at ``p0`` (default home);
    vectorised, converged rows leave the active set. Rows that do not converge come back as NaN.
    """
    target = np.atleast_2d(np.asarray(target, float)).reshape(-1, 2)
    p = np.zeros((target.shape[0], 2)) if p0 is None else np.array(p0, dtype=float).reshape(-1, 2)
    active = np.flatnonzero(np.isfinite(p).all(axis=1))
    p[np.setdiff1d(np.arange(len(p)), active)] = np.nan
    h = 1e-7
    f = lambda q: ik(*from_pointing_coords(q))  # noqa: E731
    for _ in range(max_iter):
        pa = p[active]
        g = f(pa) - target[active]
        conv = np.max(np.abs(g), axis=-1) < tol
        bad = ~np.isfinite(g).all(-1)
        p[active[bad]] = np.nan
        keep = ~(conv | bad)
        active, pa, g = active[keep], pa[keep], g[keep]
        if active.size == 0:
            break
        J = np.stack([(f(pa + dp) - g - target[active]) / h for dp in np.eye(2) * h], axis=-1)
        step = -np.linalg.solve(J, g[..., None])[..., 0]
        norm = np.linalg.norm(step, axis=-1, keepdims=True)
        p[active] = pa + np.where(norm > max_step, step * max_step / np.maximum(norm, 1e-300), step)
    p[active] = np.nan
    return from_pointing_coords(p)


def nominal_fk(beta: np.ndarray, geom: Geometry | None = None, tol: float = 1e-13,
               max_iter: int = 50) -> tuple[np.ndarray, np.ndarray]:
    """Forward kinematics of the nominal machine: motor angles (N, 2) rad → (phi, theta) rad.

    :func:`invert_in_pointing_coords` on the nominal IK, started at home. Poses that do not converge
    (out of the workspace) come back as NaN.
    """
    geom = geom or default_geometry()
    return invert_in_pointing_coords(lambda phi, theta: nominal_ik(phi, theta, geom), beta, tol=tol,
                                     max_iter=max_iter)


#: Largest nominal |K / rho| both passive limbs may have at once in a campaign (:func:`passive_strained`):
#: on the twin with 0.5 mm / 0.1 deg errors (10 machines x 3000 poses at 60..82 deg tilt) none of the 27060
#: pose-machine pairs outside the wedge failed to assemble and 295 of the 2940 inside it did.
PASSIVE_REACH = 0.88


def passive_strained(phi_deg, theta_deg, geom: Geometry | None = None) -> np.ndarray:
    """True where both passive limbs are near their stretched-link singularity at once (nominal
    ``|K / rho| >`` :data:`PASSIVE_REACH` for each: tilts beyond ~68 deg towards azimuth 25..60 deg). There the
    closure is ill-conditioned: a machine with errors of a few tenths of a millimetre strains by
    millimetres or does not assemble, so a campaign stays out of it. Angles in deg, any matching shape."""
    geom = geom or default_geometry()
    passive = tuple(j + 1 for j in range(geom.n_limbs) if j + 1 not in geom.actuated)
    r, R = nominal_pose(np.deg2rad(phi_deg), np.deg2rad(theta_deg), geom)
    return np.abs(limb_ik(r, R, None, geom, passive).reach).min(axis=1) > PASSIVE_REACH
