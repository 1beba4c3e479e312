"""Compensation of the over-constrained PM: one type per calibration model, one protocol for both.

A :class:`Compensator` turns target orientations into the motor commands that bring the calibrated
machine there, and predicts where commands take it. Two implementations:

- :class:`PaperCompensation` — the paper's per-limb model (Sun et al. 2018): exact real inverse
  kinematics of the identified limbs 1 and 2, with the platform position from the fitted position map
  (or the paper's eq. 7 when no map was fitted).
- :class:`FullCompensation` — the whole closed chain with every limb, the SS limb and the closure
  stiffness ratio: the twin solves its equilibrium and the pointing together
  (:func:`pmcal.calib.ocpm.fullchain.chain_commands_deg`, :mod:`pmcal.twin.ocpm.aiming`).

Units: orientations (phi azimuth, theta tilt; tilt-torsion angles) and commands in degrees.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from pmcal.bridge.comptable import CompTable
from pmcal.calib.ocpm import compensation as comp
from pmcal.calib.ocpm.fullchain import chain_commands_deg
from pmcal.errors import InputError
from pmcal.mechanism.ocpm.config import Geometry
from pmcal.mechanism.ocpm.params import ErrorSet
from pmcal.mechanism.rigid import fit_pose
from pmcal.mechanism.rotations import tilt_torsion_angles
from pmcal.twin.ocpm.forward import FullChainModel

#: Default compensation-table grid: 5 deg in phi over 0..360, 2 deg in theta over 0..60.
DEFAULT_GRID = (73, 31)
MACHINE = "ocpm_2dof"


class Compensator(Protocol):
    """Commands for orientations and orientations for commands of a calibrated machine."""

    #: One line saying how the commands are computed (recorded in output files).
    description: str

    def commands_deg(self, phi_deg, theta_deg) -> np.ndarray:
        """Motor commands (N, 2) deg that point the machine at (phi, theta) deg; NaN where unreachable."""

    def orientation(self, m_cmd_deg) -> tuple[np.ndarray, np.ndarray]:
        """(phi, theta) rad the machine reaches for commands (N, 2) deg."""


class PaperCompensation:
    """The paper's model: real IK of the identified limbs; position from ``pmap`` (None: eq. 7)."""

    def __init__(self, errors: ErrorSet, pmap: comp.PositionMap | None, geom: Geometry):
        self.errors, self.pmap, self.geom = errors, pmap, geom
        self.description = "exact real IK, position: " + (
            "fitted map" if pmap is not None else "nominal (paper eq. 7)")

    def commands_deg(self, phi_deg, theta_deg) -> np.ndarray:
        phi, theta = np.deg2rad(np.atleast_1d(phi_deg)), np.deg2rad(np.atleast_1d(theta_deg))
        return np.rad2deg(comp.ik_commands_rad(phi, theta, self.errors, self.geom, self.pmap))

    def orientation(self, m_cmd_deg) -> tuple[np.ndarray, np.ndarray]:
        return comp.predict_orientation(np.deg2rad(m_cmd_deg), self.errors, self.geom, self.pmap)


class FullCompensation:
    """The whole closed chain with parameters ``params`` (mm, deg) and closure stiffness ratio."""

    description = "whole closed chain, equilibrium and pointing solved together on the twin"

    def __init__(self, params: dict[str, float], stiffness_ratio: float | None, geom: Geometry):
        self.errors = ErrorSet.from_dict(params, geom.n_limbs, geom.actuated)
        self.model = FullChainModel(geom, stiffness_ratio)
        self.ratio = self.model.stiffness_ratio
        self.geom = geom
        self.unreachable = np.zeros(0, int)
        self._last_targets = (np.zeros(0), np.zeros(0))

    def commands_deg(self, phi_deg, theta_deg) -> np.ndarray:
        """Commands (N, 2) deg; rows out of reach (theta < 0, outside the workspace, not assembled or not
        converged) are NaN, listed (0-based) in :attr:`unreachable` and named by
        :meth:`unreachable_message` after each call."""
        phi_deg, theta_deg = np.atleast_1d(phi_deg), np.atleast_1d(theta_deg)
        out = np.full((len(phi_deg), 2), np.nan)
        ok = theta_deg >= 0
        out[ok] = chain_commands_deg(self.model, self.errors, phi_deg[ok], theta_deg[ok], self.ratio)
        self.unreachable = np.flatnonzero(~np.isfinite(out).all(axis=1))
        self._last_targets = (phi_deg, theta_deg)
        return out

    def unreachable_message(self) -> str:
        """One line naming the targets of the last :meth:`commands_deg` call left NaN (empty if none)."""
        if not len(self.unreachable):
            return ""
        phi, theta = self._last_targets
        rows = ", ".join(f"{i + 1} (phi {phi[i]:g}, theta {theta[i]:g})" for i in self.unreachable[:5])
        more = f" and {len(self.unreachable) - 5} more" if len(self.unreachable) > 5 else ""
        return (f"{len(self.unreachable)} target orientation(s) out of reach of the calibrated machine, "
                f"commands NaN: row {rows}{more} (deg)")

    def orientation(self, m_cmd_deg) -> tuple[np.ndarray, np.ndarray]:
        self.model.set(self.errors, self.ratio)
        T, _ = self.model.predict(m_cmd_deg)
        _, R, _ = fit_pose(T, self.geom.targets)
        return tilt_torsion_angles(R)


def deg(rad: float) -> float:
    """Degrees of a configured angle, rounded to 1e-9 deg (60 stays 60, not 59.99999999999999)."""
    return round(float(np.rad2deg(rad)), 9)


def checked_commands(comp_: Compensator, phi_deg, theta_deg, geom: Geometry, path: str | None = None,
                     field: str = "theta_deg") -> np.ndarray:
    """Motor commands (N, 2) deg; InputError naming the first unreachable / out-of-limits row."""
    m = comp_.commands_deg(phi_deg, theta_deg)
    lo, hi = deg(geom.motor_min), deg(geom.motor_max)
    bad = np.flatnonzero(~np.all(np.isfinite(m) & (m >= lo) & (m <= hi), axis=1))
    if bad.size:
        i = int(bad[0])
        what = "is out of reach of the calibrated machine" if not np.all(np.isfinite(m[i])) else \
            f"needs motor commands {m[i].round(3)} deg outside the limits [{lo:g}, {hi:g}] deg"
        raise InputError(f"orientation (phi {phi_deg[i]:g}, theta {theta_deg[i]:g}) deg {what}",
                         file=path, row=i + 1, field=field)
    return m


def check_grid(grid) -> tuple[int, int]:
    """A table grid (n_phi, n_theta) within the PLC's array size, else InputError naming ``--grid``."""
    try:
        n_phi, n_theta = (int(v) for v in grid)
    except (TypeError, ValueError):
        raise InputError(f"expected a grid NPHI,NTHETA (two integers), got {grid!r}", field="--grid") from None
    if not (2 <= n_phi <= 100 and 2 <= n_theta <= 100):
        raise InputError(f"grid {n_phi}x{n_theta} outside 2x2..100x100 (PLC array size)", field="--grid")
    return n_phi, n_theta


def build_table(comp_: Compensator, geom: Geometry, grid: tuple[int, int], version: int) -> CompTable:
    """The validated 2-D compensation table over phi 0..360 and theta 0..theta_max (deg)."""
    if not 1 <= int(version) <= 2**32 - 1:
        raise InputError(f"table version {version} outside 1..4294967295", field="--table-version")
    n_phi, n_theta = check_grid(grid)

    def fill(phi_deg, theta_deg):
        return checked_commands(comp_, phi_deg, theta_deg, geom, field="grid")

    table = CompTable.from_setpoints(fill, machine=MACHINE, version=int(version), n_phi=n_phi, n_theta=n_theta,
                                     theta_range_deg=(0.0, deg(geom.theta_max)),
                                     motor_limits_deg=(deg(geom.motor_min), deg(geom.motor_max)))
    return table.validate()
