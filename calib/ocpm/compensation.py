"""Compensation of the over-constrained PM: corrected motor commands for target orientations.

The identified real inverse kinematics (paper eq. 12-13) gives the motor commands that put the
actuated limbs' closures exactly at a target pose: ``m = beta(r, R; errors) - dtheta``
(:func:`pmcal.mechanism.ocpm.kinematics.real_ik_commands`). It needs the platform *position* r at the target
orientation R, which the per-limb model does not determine (the SS and passive limbs do). Two options:

- ``position_map=None``: the nominal position of paper eq. 7 (the paper's choice);
- a :class:`PositionMap` fitted to the measured platform positions of the calibration campaign:
  ``r(p) = r_eq7(p) + sum_k c_k b_k(p)`` with a polynomial basis ``b_k`` in the pointing coordinates
  ``p = theta (cos phi, sin phi)``, degree chosen by leave-one-out cross-validation.

:func:`ik_commands_rad` is the exact compensation (commands in rad, from orientations in rad);
:func:`linear_commands_rad` is the paper's first-order compensation (eq. 15) for comparison.
:func:`predict_orientation` is the forward kinematics of the calibrated model (where commands take the
platform), used to evaluate a parameter set against measurements.

Units: angles in rad, positions in mm (the application converts to degrees).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pmcal.mechanism.ocpm.config import Geometry, default_geometry
from pmcal.mechanism.ocpm.kinematics import (invert_in_pointing_coords, nominal_fk, nominal_pose, pointing_coords,
                                   real_ik_commands)
from pmcal.calib.ocpm.paper_model import param_names, pose_sensitivity
from pmcal.mechanism.ocpm.params import ErrorSet
from pmcal.mechanism.rotations import tilt_torsion, tilt_torsion_angles


def poly_basis(p: np.ndarray, degree: int) -> np.ndarray:
    """Monomials ``px^a py^b`` with ``a + b <= degree`` of pointing coordinates p (N, 2) rad: (N, K)."""
    px, py = p[..., 0], p[..., 1]
    cols = [px ** (d - i) * py ** i for d in range(degree + 1) for i in range(d + 1)]
    return np.stack(cols, axis=-1)


def n_terms(degree: int) -> int:
    return (degree + 1) * (degree + 2) // 2


@dataclass
class PositionMap:
    """Platform position correction over orientation: ``r(p) = r_eq7(p) + basis(p) @ coef`` (mm).

    coef : (K, 3) mm; degree : polynomial degree; loo_rms : leave-one-out RMS of the fit, mm.
    """

    degree: int
    coef: np.ndarray
    loo_rms: float = float("nan")

    def position(self, phi: np.ndarray, theta: np.ndarray, geom: Geometry | None = None) -> np.ndarray:
        """Platform position (N, 3) mm at orientations (phi, theta) rad."""
        geom = geom or default_geometry()
        r, _ = nominal_pose(phi, theta, geom)
        return r + poly_basis(pointing_coords(phi, theta), self.degree) @ self.coef

    def to_dict(self) -> dict:
        return {"basis": "monomials of theta*(cos phi, sin phi) [rad]", "degree": self.degree,
                "coef_mm": np.asarray(self.coef).tolist(), "loo_rms_mm": self.loo_rms}

    @classmethod
    def from_dict(cls, d: dict) -> "PositionMap":
        degree = int(d["degree"])
        coef = np.asarray(d["coef_mm"], float)
        if coef.shape != (n_terms(degree), 3) or not np.all(np.isfinite(coef)):
            raise ValueError(f"position map of degree {degree} needs {n_terms(degree)}x3 finite coefficients")
        return cls(degree=degree, coef=coef, loo_rms=float(d.get("loo_rms_mm", float("nan"))))


def fit_position_map(r: np.ndarray, R: np.ndarray, geom: Geometry | None = None,
                     max_degree: int = 4) -> PositionMap:
    """Fit :class:`PositionMap` to measured poses (r (N, 3) mm, R (N, 3, 3)).

    Degrees 0..max_degree with at most N/2 terms are tried; the one with the smallest leave-one-out
    (PRESS) residual wins. Closed form: ``e_loo = e / (1 - h_ii)`` with the hat-matrix diagonal.
    """
    geom = geom or default_geometry()
    phi, theta = tilt_torsion_angles(R)
    d = r - nominal_pose(phi, theta, geom)[0]
    p = pointing_coords(phi, theta)
    best = None
    for degree in range(max_degree + 1):
        if n_terms(degree) > len(r) // 2:
            break
        B = poly_basis(p, degree)
        coef, *_ = np.linalg.lstsq(B, d, rcond=None)
        Q, _ = np.linalg.qr(B)
        h = np.sum(Q * Q, axis=1)
        loo = (d - B @ coef) / np.maximum(1.0 - h, 1e-9)[:, None]
        rms = float(np.sqrt(np.mean(np.sum(loo**2, axis=1))))
        if best is None or rms < best.loo_rms:
            best = PositionMap(degree=degree, coef=coef, loo_rms=rms)
    if best is None:
        raise ValueError(f"need at least 2 poses to fit a position map, got {len(r)}")
    return best


def target_pose(phi: np.ndarray, theta: np.ndarray, geom: Geometry | None = None,
                position_map: PositionMap | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Pose (r mm, R) the compensation aims at for target orientations (phi, theta) rad."""
    geom = geom or default_geometry()
    phi, theta = np.atleast_1d(phi).astype(float), np.atleast_1d(theta).astype(float)
    if position_map is None:
        r, _ = nominal_pose(phi, theta, geom)
    else:
        r = position_map.position(phi, theta, geom)
    return r, tilt_torsion(phi, theta)


def ik_commands_rad(phi_rad: np.ndarray, theta_rad: np.ndarray, errors: ErrorSet, geom: Geometry | None = None,
                    position_map: PositionMap | None = None) -> np.ndarray:
    """Exact compensation: motor commands (N, 2) rad that put the machine with ``errors`` (mm, rad) at the
    tilt-torsion orientations (``phi_rad``, ``theta_rad``), through the identified real IK at the
    platform position of ``position_map`` (None: paper eq. 7). NaN: out of reach."""
    r, R = target_pose(phi_rad, theta_rad, geom, position_map)
    return real_ik_commands(r, R, errors, geom)


def linear_commands_rad(phi_rad: np.ndarray, theta_rad: np.ndarray, errors: ErrorSet,
                        geom: Geometry | None = None) -> np.ndarray:
    """Paper eq. 15, first order: motor commands (N, 2) rad ``m = m_nominal + E eps`` (= ``m_nom - J_p^{-1}
    E_ac eps_ac - dtheta`` with the motor-side Jacobian), E the error coefficient matrix at the nominal
    pose (eq. 7), for orientations (``phi_rad``, ``theta_rad``)."""
    phi, theta = phi_rad, theta_rad
    geom = geom or default_geometry()
    names = param_names((1, 2), tilts=True)
    eps = np.array([errors.get(k) for k in names])
    p = pointing_coords(np.atleast_1d(phi), np.atleast_1d(theta))
    _, E = pose_sensitivity(p, names, geom)
    m_nom = ik_commands_rad(phi, theta, ErrorSet(), geom)
    return m_nom + E @ eps


def predict_orientation(m_cmd: np.ndarray, errors: ErrorSet, geom: Geometry | None = None,
                        position_map: PositionMap | None = None, tol: float = 1e-12,
                        max_iter: int = 30) -> tuple[np.ndarray, np.ndarray]:
    """Forward kinematics of the calibrated model: orientations (phi, theta) rad the commands
    ``m_cmd`` (N, 2) rad lead to, i.e. :func:`ik_commands_rad` solved for the orientation (Newton in pointing
    coordinates from the nominal forward kinematics). NaN where it does not converge."""
    geom = geom or default_geometry()
    m_cmd = np.atleast_2d(np.asarray(m_cmd, float))
    start = pointing_coords(*nominal_fk(m_cmd, geom))
    return invert_in_pointing_coords(lambda phi, theta: ik_commands_rad(phi, theta, errors, geom, position_map),
                                     m_cmd, start, tol=tol, max_iter=max_iter)


def position_map_blocks(phi: np.ndarray, theta: np.ndarray, degree: int = 3) -> np.ndarray:
    """Design rows (N, 3, 3K) of the position map's coefficients at orientations (phi, theta) rad: for
    pose selection jointly with the identification (:func:`pmcal.calib.pose_selection.join_blocks`)."""
    B = poly_basis(pointing_coords(phi, theta), degree)                  # (N, K)
    return np.einsum("ab,nk->nakb", np.eye(3), B).reshape(len(B), 3, -1)
