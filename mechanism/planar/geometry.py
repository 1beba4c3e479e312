"""Nominal geometry, source errors and parameter names of the planar 2-DOF robot (paper 003).

Frame (paper Fig. 4): O-xy in the plane of motion, O midway between the active joints A1 and A2, x
horizontal towards A1, y up; the platform hangs below the base (y < 0). Angles are measured from +x
towards +y (counter-clockwise). Units: mm and radians. Limb 1 is the one at ``e1 = (+80, 0)``.

Parameter keys at the interfaces (files, reports) are in mm and degrees: ``dtheta1``, ``dtheta2`` (deg)
and ``de1x``, ``de1y``, ``de2x``, ``de2y``, ``dL1``, ``dL2``, ``dl1``, ``dl2``, ``drMx``, ``drMy`` (mm).
Inside :mod:`pmcal.calib.planar` the zero offsets are radians.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Mapping

import numpy as np

#: every source error, in the order of paper Table 2
ERROR_KEYS: tuple[str, ...] = ("dtheta1", "dtheta2", "de1x", "de1y", "de2x", "de2y",
                               "dL1", "dL2", "dl1", "dl2", "drMx", "drMy")
#: keys whose interface unit is degrees (radians inside calib)
ANGLE_KEYS = frozenset({"dtheta1", "dtheta2"})
#: unknowns of the simplified identification model (eq. 28), order of ``Δp``
SIMPLIFIED_KEYS: tuple[str, ...] = ("dtheta1", "dtheta2", "drMx", "drMy")
#: unknowns of the full identification model (eq. 24-25), order of ``Δp' = (Δq1, Δq2, ΔrM)``
FULL_KEYS: tuple[str, ...] = ("dtheta1", "de1x", "de1y", "dL1", "dl1",
                              "dtheta2", "de2x", "de2y", "dL2", "dl2", "drMx", "drMy")


def interface_unit(key: str) -> str:
    """Unit of a parameter key at the interfaces (``"deg"`` or ``"mm"``)."""
    return "deg" if key in ANGLE_KEYS else "mm"


def internal_unit(key: str) -> str:
    """Unit of a parameter key inside :mod:`calib` (``"rad"`` or ``"mm"``)."""
    return "rad" if key in ANGLE_KEYS else "mm"


@dataclass(frozen=True)
class Geometry:
    """Kinematic parameters (mm) of the robot and its measuring mechanism.

    e : (2, 2) positions of A1, A2 (rotation centres of the active joints), rows = limbs.
    L, l : (2,) proximal and distal link lengths.
    c : (2,) vector O -> O1 (measuring mechanism's joint on the base).
    d : (2,) vector O2 -> P (measuring mechanism's joint on the platform to the reference point P).
    home : (2,) motor angles of the home position P0 (rad): theta1 = 0, theta2 = pi.
    """

    e: np.ndarray = field(default_factory=lambda: np.array([[80.0, 0.0], [-80.0, 0.0]]))
    L: np.ndarray = field(default_factory=lambda: np.array([375.0, 375.0]))
    l: np.ndarray = field(default_factory=lambda: np.array([825.0, 825.0]))
    c: np.ndarray = field(default_factory=lambda: np.array([0.0, -79.0]))
    d: np.ndarray = field(default_factory=lambda: np.array([0.0, -51.0]))
    home: np.ndarray = field(default_factory=lambda: np.array([0.0, np.pi]))

    def perturbed(self, err: "Errors") -> "Geometry":
        """The real machine's geometry: nominal plus the geometric errors and the MAEMM.

        The MAEMM ``ΔrM = Δc + Δd`` (eq. 17) only enters as a sum; it is carried by ``c`` here.
        Zero offsets are not geometry: they add to the commanded angles (see :func:`Errors.dtheta`).
        """
        return replace(self, e=self.e + err.de, L=self.L + err.dL, l=self.l + err.dl, c=self.c + err.drM)


@dataclass(frozen=True)
class Workspace:
    """The paper's task workspace W (Fig. 4): a rectangle of width b and height h whose upper edge lies H
    below O, centred on the y axis (mm)."""

    H: float = 632.0
    b: float = 480.0
    h: float = 150.0

    @property
    def y_upper(self) -> float:
        return -self.H

    @property
    def y_lower(self) -> float:
        return -(self.H + self.h)


@dataclass(frozen=True)
class Errors:
    """Source errors of paper Table 2 (mm, rad). Absent = zero.

    dtheta : (2,) zero offsets: the real active-link angle is the commanded angle plus ``dtheta``.
    de : (2, 2) errors of A1, A2; dL, dl : (2,) link-length errors; drM : (2,) MAEMM (eq. 17).
    """

    dtheta: np.ndarray = field(default_factory=lambda: np.zeros(2))
    de: np.ndarray = field(default_factory=lambda: np.zeros((2, 2)))
    dL: np.ndarray = field(default_factory=lambda: np.zeros(2))
    dl: np.ndarray = field(default_factory=lambda: np.zeros(2))
    drM: np.ndarray = field(default_factory=lambda: np.zeros(2))

    def as_internal(self) -> dict[str, float]:
        """``{key: value}`` in mm and radians."""
        v = dict(dtheta1=self.dtheta[0], dtheta2=self.dtheta[1], de1x=self.de[0, 0], de1y=self.de[0, 1],
                 de2x=self.de[1, 0], de2y=self.de[1, 1], dL1=self.dL[0], dL2=self.dL[1], dl1=self.dl[0],
                 dl2=self.dl[1], drMx=self.drM[0], drMy=self.drM[1])
        return {k: float(v[k]) for k in ERROR_KEYS}

    def as_interface(self) -> dict[str, float]:
        """``{key: value}`` in mm and degrees (files, reports)."""
        return {k: (float(np.rad2deg(v)) if k in ANGLE_KEYS else v) for k, v in self.as_internal().items()}

    @classmethod
    def from_internal(cls, values: Mapping[str, float]) -> "Errors":
        """From ``{key: value}`` in mm and radians; unknown keys raise ``KeyError``."""
        unknown = set(values) - set(ERROR_KEYS)
        if unknown:
            raise KeyError(f"unknown error key(s): {', '.join(sorted(unknown))}")
        g = lambda k: float(values.get(k, 0.0))  # noqa: E731
        return cls(dtheta=np.array([g("dtheta1"), g("dtheta2")]),
                   de=np.array([[g("de1x"), g("de1y")], [g("de2x"), g("de2y")]]),
                   dL=np.array([g("dL1"), g("dL2")]), dl=np.array([g("dl1"), g("dl2")]),
                   drM=np.array([g("drMx"), g("drMy")]))

    @classmethod
    def from_interface(cls, values: Mapping[str, float]) -> "Errors":
        """From ``{key: value}`` in mm and degrees."""
        return cls.from_internal({k: (np.deg2rad(float(v)) if k in ANGLE_KEYS else float(v))
                                  for k, v in values.items()})
