"""The nominal closed-form inverse kinematics the PLC computes in ST (``F_CompTableNominalIk``).

A version-2 compensation table stores *corrections* relative to this reference: the motor command
for a target orientation is ``nominal_ik(phi, theta) + bilinear(corrections)``. The nominal part
carries the strongly curved kinematics exactly; the table only has to carry the calibration's small,
smooth correction, so bilinear interpolation on the default 5 deg x 2 deg grid loses ~1/150 of what
interpolating absolute commands loses (docs/compensation_table.md, "Choice of the interpolant").

Geometry (seed eq. 4, 7, 12-13 with every error zero; docs/ocpm_2dof.md): base and platform points of
limb j at azimuth psi_j on a circle of radius ``a``; platform centre at ``h`` above the base centre
at home; both links of an RSR limb ``l`` long. Orientation by tilt-torsion angles (phi, theta),
``R = Rz(phi) Ry(theta) Rz(-phi)``, ``r = h (cos phi sin(theta/2), sin phi sin(theta/2), cos(theta/2))``.
Per limb, in this order (the ST function performs the same IEEE-754 double operations)::

    d  = r + R a_j - b_j                    (base frame, mm)
    px = cos(psi) dx + sin(psi) dy;  pz = dz;  py = -sin(psi) dx + cos(psi) dy
    K  = (px*px + py*py + pz*pz) / (2 l);   rho = SQRT(px*px + pz*pz)
    beta = ACOS(K / rho) - atan2_st(pz, px) (rad, wrapped to [-pi, pi)); command = beta * 180/pi deg

``atan2_st`` is F_CompTableAtan2 (TwinCAT 3 has no ATAN2): ATAN of the quotient of magnitude <= 1 with
the quadrant cases. A pose is out of reach (NaN here, FALSE on the PLC) if rho < RHO_MIN_MM or K/rho lies
outside [-1, 1]; angles that are not finite or larger than ANGLE_ABS_MAX_DEG give NaN for both motors.

Units: angles in degrees at the interface, mm for lengths.
"""

from __future__ import annotations

import math
import struct
import zlib
from dataclasses import dataclass

import numpy as np

from pmcal.plc import constant as plc_constant

#: nReference codes of ST_CompTableHeader
REFERENCE_NONE = 0
REFERENCE_NOMINAL_IK = 1
#: the values are corrections to the motion controller's own nominal IK (not computed by the PLC's table code)
REFERENCE_CONTROLLER = 2
_PACK = struct.Struct("<5d")
DEG = math.pi / 180.0          # the ST constants: PI / 180 and 180 / PI as LREAL
RAD = 180.0 / math.pi
HALF_PI = 1.5707963267948966   # the ST constant (math.pi / 2)
#: GVL_CompTableParam.ANGLE_ABS_MAX (deg) and RHO_MIN_MM (mm)
ANGLE_ABS_MAX_DEG = 1.0e6
RHO_MIN_MM = 1.0e-6


def atan2_st(y: float, x: float) -> float:
    """F_CompTableAtan2: the angle of (x, y) in rad from ATAN, the same IEEE operations in the same order.

    Agrees with :func:`math.atan2` to a few ulp (exactly at the axes); (0, 0) gives 0. Finite arguments.
    """
    if x == 0.0 and y == 0.0:
        return 0.0
    if abs(x) >= abs(y):
        a = math.atan(y / x)
        if x < 0.0:
            a = a + math.pi if y >= 0.0 else a - math.pi
        return a
    if y > 0.0:
        return HALF_PI - math.atan(x / y)
    return -HALF_PI - math.atan(x / y)


@dataclass(frozen=True)
class NominalReference:
    """Nominal geometry of the two actuated limbs: radius ``a_mm``, height ``h_mm``, link ``l_mm``,
    limb azimuths ``psi1_deg``, ``psi2_deg``. Must equal ``GVL_CompTableParam.REF_*`` on the PLC
    (the header carries :meth:`crc32` of these five values and the PLC refuses a mismatch)."""

    a_mm: float
    h_mm: float
    l_mm: float
    psi1_deg: float
    psi2_deg: float

    KEYS = ("a_mm", "h_mm", "l_mm", "psi1_deg", "psi2_deg")

    @classmethod
    def default(cls) -> "NominalReference":
        """The shipped PLC project's reference geometry: ``GVL_CompTableParam.REF_*`` of ``plc/`` (the other
        side of the contract; equal to ocpm_2dof's nominal geometry of ``mjcf/ocpm_2dof/machine.toml``,
        which tests/test_comptable.py checks)."""
        return cls(*(float(plc_constant(f"REF_{k.upper()}")) for k in cls.KEYS))

    def as_dict(self) -> dict:
        return {"kind": "nominal_ik", **{k: float(getattr(self, k)) for k in self.KEYS}}

    def pack(self) -> bytes:
        """The five LREALs as the PLC stores them (little-endian), the input of :meth:`crc32`."""
        return _PACK.pack(*(float(getattr(self, k)) for k in self.KEYS))

    def crc32(self) -> int:
        """CRC-32 (zlib) of :meth:`pack`: ``nReferenceCrc`` of the header."""
        return zlib.crc32(self.pack())

    def defect(self) -> str | None:
        vals = [float(getattr(self, k)) for k in self.KEYS]
        if not all(math.isfinite(v) for v in vals) or min(self.a_mm, self.h_mm, self.l_mm) <= 0.0:
            return "reference geometry must be finite with a_mm, h_mm, l_mm > 0"
        return None

    def commands_deg(self, phi_deg, theta_deg) -> np.ndarray:
        """Nominal motor commands (..., 2) in deg at orientations (deg), as ``F_CompTableNominalIk``.

        Element-wise IEEE arithmetic through :mod:`math` per point, so a single lookup on the PLC
        twin and a vectorised evaluation give the same bits. NaN where the pose is out of reach.
        """
        phi, theta = np.broadcast_arrays(np.asarray(phi_deg, dtype=np.float64),
                                         np.asarray(theta_deg, dtype=np.float64))
        out = np.empty(phi.shape + (2,))
        flat_p, flat_t, flat_o = phi.reshape(-1), theta.reshape(-1), out.reshape(-1, 2)
        for n in range(flat_p.size):
            flat_o[n] = self.point_deg(float(flat_p[n]), float(flat_t[n]))
        return out

    def point_deg(self, phi_deg: float, theta_deg: float) -> tuple[float, float]:
        """One orientation (deg) -> the two nominal motor commands (deg); the ST arithmetic."""
        if not (math.isfinite(phi_deg) and math.isfinite(theta_deg)) \
                or abs(phi_deg) > ANGLE_ABS_MAX_DEG or abs(theta_deg) > ANGLE_ABS_MAX_DEG:
            return math.nan, math.nan
        ph = phi_deg * DEG
        th = theta_deg * DEG
        cp, sp = math.cos(ph), math.sin(ph)
        ct, st = math.cos(th), math.sin(th)
        s2, c2 = math.sin(th * 0.5), math.cos(th * 0.5)
        rx, ry, rz = self.h_mm * cp * s2, self.h_mm * sp * s2, self.h_mm * c2
        res = []
        for psi_deg in (self.psi1_deg, self.psi2_deg):
            cs, ss = math.cos(psi_deg * DEG), math.sin(psi_deg * DEG)
            vx, vy = self.a_mm * cs, self.a_mm * ss
            wx = cp * vx + sp * vy                     # Rz(-phi) v
            wy = cp * vy - sp * vx
            ux = ct * wx                               # Ry(theta) w  (w_z = 0)
            uz = -(st * wx)
            ax = cp * ux - sp * wy                     # Rz(phi) u
            ay = sp * ux + cp * wy
            dx, dy, dz = rx + ax - vx, ry + ay - vy, rz + uz
            px = cs * dx + ss * dy
            py = cs * dy - ss * dx
            pz = dz
            k = (px * px + py * py + pz * pz) / (2.0 * self.l_mm)
            rho = math.sqrt(px * px + pz * pz)
            q = k / rho if rho >= RHO_MIN_MM else 2.0
            if not -1.0 <= q <= 1.0:
                res.append(math.nan)
                continue
            beta = math.acos(q) - atan2_st(pz, px)
            if beta >= math.pi:
                beta = beta - 2.0 * math.pi
            elif beta < -math.pi:
                beta = beta + 2.0 * math.pi
            res.append(beta * RAD)
        return res[0], res[1]
