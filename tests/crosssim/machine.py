"""Closed-chain model of the over-constrained 2-DoF PM (SS + four RSR limbs), independent of pmcal.

Written from the mechanism description only (geometry, frames, error keys); nothing is imported from
pmcal. Units: mm, rad inside, degrees at the interface; N, N·mm.

Formulation (deliberately different from the twin's MuJoCo springs):
- unknowns per pose: platform position r (origin of the target-defined platform frame, base frame),
  a rotation vector w (R = exp(w)·R0, R0 the nominal guess), the passive base-joint angles beta3, beta4
  and, with joint compliance, the motor joint angles beta1, beta2;
- closure residuals, one scalar pair per RSR limb: |S_j − A_j| − l2 (link length) and (S_j − A_j)·u_j
  (distance of S_j from the plane of the platform revolute joint at A_j, axis u_j), and for the SS limb
  |C_E| − h; each weighted by sqrt(k) so that ½·Σ(residual²) is the strain energy in N·mm
  (passive limbs k = 1e3 N/mm, limbs 1, 2 and SS k·ratio, ratio 1000);
- the compromise is the minimum of that energy (scipy least_squares), then Gauss-Newton steps on
  energy + gravity potential (platform 6 kg at (0, 0, 40), payload at (0, 0, hs), 0.5 kg links as uniform
  rods) with the Gauss-Newton Hessian and a finite-difference gravity gradient;
- a compliant motor adds the residual sqrt(K)·(beta − beta_drive) (K in N·mm/rad).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

A_RADIUS, H_SS, L_LINK, H_TOP = 150.0, 402.0, 317.0, 80.0
PSI = np.deg2rad([0.0, 90.0, 180.0, 270.0])
TARGETS = np.array([[100.0, 0.0, 80.0], [-50.0, 86.6025, 80.0], [-50.0, -86.6025, 80.0]])
PLATFORM_KG, PLATFORM_COM, LINK_KG, SS_KG = 6.0, np.array([0.0, 0.0, 40.0]), 0.5, 0.5
GRAV = 9.81                       # N per kg; U = GRAV·m·z is in N·mm with z in mm
K_PASSIVE, RATIO = 1.0e3, 1000.0  # N/mm
HOME_DEG = -39.351


def rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def rot_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def tilt_torsion(phi: float, theta: float) -> np.ndarray:
    """R = Rz(phi)·Ry(theta)·Rz(−phi), angles in rad."""
    return rot_z(phi) @ rot_y(theta) @ rot_z(-phi)


@dataclass
class Geometry:
    """Machine geometry with errors (keys `L<j>.<name>`, `SS.<name>`, mm and deg) and a link scale.

    ``link_scale`` multiplies l1, l2 of every RSR limb and the SS length (thermal expansion of the links),
    ``base_scale`` the base points B_j (about the base origin O), ``platform_scale`` the platform points A_j
    and the SS joint centre C_E (about the platform origin); the tracker targets never expand here."""

    errors: dict = field(default_factory=dict)
    ratio: float = RATIO

    def e(self, key: str) -> float:
        return float(self.errors.get(key, 0.0))

    def limb(self, j: int, link_scale: float = 1.0, base_scale: float = 1.0, platform_scale: float = 1.0,
             coupler_scale: float | None = None) -> dict:
        """Limb j (1..4): base point B, turned local frame F, platform point Ap and axis up (platform
        coordinates), link lengths l1 (crank, ``link_scale``), l2 (coupler, ``coupler_scale``, default
        ``link_scale``), zero offset dtheta (rad)."""
        coupler_scale = link_scale if coupler_scale is None else coupler_scale
        p, k = PSI[j - 1], f"L{j}."
        frame = rot_z(p)  # columns x_j (radial), y_j (base revolute axis), z_j
        base = A_RADIUS * np.array([np.cos(p), np.sin(p), 0.0])
        F = frame @ rot_z(np.deg2rad(self.e(k + "dgamma"))) @ rot_x(np.deg2rad(self.e(k + "dalpha")))
        up = frame @ rot_z(np.deg2rad(self.e(k + "dnu"))) @ rot_x(np.deg2rad(self.e(k + "dmu"))) @ [0, 1, 0]
        return dict(B=(base + [self.e(k + "dbx"), self.e(k + "dby"), self.e(k + "dbz")]) * base_scale, F=F,
                    Ap=(base + [self.e(k + "dax"), self.e(k + "day"), self.e(k + "daz")]) * platform_scale, up=up,
                    l1=(L_LINK + self.e(k + "dl1")) * link_scale, l2=(L_LINK + self.e(k + "dl2")) * coupler_scale,
                    dtheta=np.deg2rad(self.e(k + "dtheta")))

    def ss(self, link_scale: float = 1.0, platform_scale: float = 1.0) -> tuple[float, np.ndarray]:
        """SS length h (mm) and the platform joint centre C_E in platform coordinates."""
        return (H_SS + self.e("SS.dh")) * link_scale, platform_scale * np.array(
            [self.e("SS.dcx"), self.e("SS.dcy"), self.e("SS.dcz")])


def link_dir(F: np.ndarray, beta: float) -> np.ndarray:
    """Direction of the first link, cos(beta)·x_j − sin(beta)·z_j of the (turned) local frame."""
    return F @ np.array([np.cos(beta), 0.0, -np.sin(beta)])


def nominal_ik(phi_deg: float, theta_deg: float) -> np.ndarray:
    """Base-joint angles (4,) deg of the nominal machine at orientation (phi, theta) (operating mode: the
    elbow S_j on the outer side of the line B_j→A_j); platform position from seed eq. 7."""
    phi, th = np.deg2rad(phi_deg), np.deg2rad(theta_deg)
    R = tilt_torsion(phi, th)
    r = H_SS * np.array([np.cos(phi) * np.sin(th / 2), np.sin(phi) * np.sin(th / 2), np.cos(th / 2)])
    out = np.empty(4)
    for j in range(1, 5):
        lb = Geometry().limb(j)
        D = lb["B"] - (r + R @ lb["Ap"])
        P, Q = D @ lb["F"][:, 0], -D @ lb["F"][:, 2]
        c = -(D @ D) / (2 * L_LINK)
        delta, rho = np.arctan2(Q, P), np.hypot(P, Q)
        if abs(c) > rho:
            return np.full(4, np.nan)
        best = None
        for sgn in (1, -1):
            b = delta + sgn * np.arccos(c / rho)
            s_dir = link_dir(lb["F"], b)
            if np.cross(s_dir, -D) @ lb["F"][:, 1] < 0:
                best = b
        out[j - 1] = np.rad2deg(np.angle(np.exp(1j * best)))
    return out


class ClosedChain:
    """Quasi-static pose of the machine for given motor drive angles (rad, zero offsets added here)."""

    def __init__(self, geom: Geometry, motor_stiffness=None, link_scale: float = 1.0, payload_kg: float = 0.0,
                 gravity: bool = True, base_scale: float = 1.0, platform_scale: float = 1.0,
                 coupler_scale: float | None = None, strut_scale: float | None = None):
        """``link_scale`` scales the cranks l1 and, unless given their own, the couplers l2
        (``coupler_scale``) and the SS strut (``strut_scale``)."""
        self.g = geom
        self.limbs = [geom.limb(j, link_scale, base_scale, platform_scale, coupler_scale) for j in range(1, 5)]
        self.h, self.dc = geom.ss(link_scale if strut_scale is None else strut_scale, platform_scale)
        self.k = np.array([K_PASSIVE * geom.ratio] * 2 + [K_PASSIVE] * 2)
        self.K = None if motor_stiffness is None else np.asarray(motor_stiffness, float) * 1e3  # N·mm/rad
        self.payload, self.gravity = payload_kg, gravity

    def unpack(self, x, R0, drive):
        r, R = x[:3], Rotation.from_rotvec(x[3:6]).as_matrix() @ R0
        beta = np.concatenate([x[6:8] if self.K is not None else drive, x[-2:]])
        return r, R, beta

    def residual(self, x, R0, drive):
        r, R, beta = self.unpack(x, R0, drive)
        out = [np.sqrt(self.k[0]) * (np.linalg.norm(r + R @ self.dc) - self.h)]
        for j, lb in enumerate(self.limbs):
            S = lb["B"] + lb["l1"] * link_dir(lb["F"], beta[j])
            g = S - (r + R @ lb["Ap"])
            w = np.sqrt(self.k[j])
            out += [w * (np.linalg.norm(g) - lb["l2"]), w * (g @ (R @ lb["up"]))]
        if self.K is not None:
            out += list(np.sqrt(self.K) * (beta[:2] - drive))
        return np.array(out)

    def potential(self, x, R0, drive) -> float:
        """Gravity potential (N·mm) of platform, payload, eight links and the SS link."""
        r, R, beta = self.unpack(x, R0, drive)
        z = PLATFORM_KG * (r + R @ PLATFORM_COM)[2] + self.payload * (r + R @ [0, 0, H_TOP])[2]
        for j, lb in enumerate(self.limbs):
            S = lb["B"] + lb["l1"] * link_dir(lb["F"], beta[j])
            z += LINK_KG * (lb["B"][2] + S[2]) / 2 + LINK_KG * (S[2] + (r + R @ lb["Ap"])[2]) / 2
        z += SS_KG * (r + R @ self.dc)[2] / 2
        return GRAV * z

    def solve(self, drive, guess_phi_theta_deg, gn_steps: int = 4):
        """Pose (r, R, beta (4,) rad, strain energy N·mm) for motor drive angles ``drive`` (2,) rad."""
        phi, th = np.deg2rad(guess_phi_theta_deg)
        R0 = tilt_torsion(phi, th)
        r0 = H_SS * np.array([np.cos(phi) * np.sin(th / 2), np.sin(phi) * np.sin(th / 2), np.cos(th / 2)])
        b0 = np.deg2rad(nominal_ik(*guess_phi_theta_deg))
        x = np.concatenate([r0 - R0 @ self.dc, np.zeros(3), (drive if self.K is not None else []), b0[2:]])
        sol = least_squares(self.residual, x, args=(R0, drive), method="lm", xtol=1e-14, ftol=1e-14)
        x = sol.x
        if self.gravity:
            for _ in range(gn_steps):
                J = self._jac(lambda v: self.residual(v, R0, drive), x)
                grad = J.T @ self.residual(x, R0, drive) + self._grad(lambda v: self.potential(v, R0, drive), x)
                dx = -np.linalg.solve(J.T @ J, grad)
                x = x + dx
                if np.abs(dx).max() < 1e-12:
                    break
        r, R, beta = self.unpack(x, R0, drive)
        return r, R, beta, 0.5 * float(np.sum(self.residual(x, R0, drive) ** 2))

    @staticmethod
    def _jac(f, x, h=1e-7):
        f0 = f(x)
        J = np.empty((f0.size, x.size))
        for i in range(x.size):
            d = np.zeros_like(x)
            d[i] = h
            J[:, i] = (f(x + d) - f(x - d)) / (2 * h)
        return J

    @staticmethod
    def _grad(f, x, h=1e-6):
        g = np.empty(x.size)
        for i in range(x.size):
            d = np.zeros_like(x)
            d[i] = h
            g[i] = (f(x + d) - f(x - d)) / (2 * h)
        return g
