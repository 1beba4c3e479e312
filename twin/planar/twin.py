"""The planar robot's digital twin: the MuJoCo model of the real machine placed at motor angles.

With the motors held, the four loops are closed exactly by Gauss-Newton on the site-based connect
residuals (:class:`pmcal.twin.assembly.BatchAssembler`: MuJoCo kinematics and site Jacobians, all poses at
once). The platform's reference point P and the linear scale (the slide joint ``scale_slide``) are then
read off the model. Interface units: mm and radians (seed plane, y up); SI inside MuJoCo.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np

from pmcal.mechanism.planar.geometry import Errors
from pmcal.mechanism.planar.kinematics import elbows, forward, mm_vector
from pmcal.twin.assembly import BatchAssembler, Stiffness
from pmcal.twin.planar.config import PlanarMachine, default_machine
from pmcal.twin.planar.model import CLOSURES, MM, build_model, scale_reference

#: largest closure gap (m) accepted as an assembled pose
CLOSURE_TOL_M = 1e-10


@dataclass
class PlanarPoses:
    """Assembled poses (N of them).

    r : (N, 2) position of P, mm (seed frame). length : (N,) |O1 O2|, mm. scale : (N,) slide joint
    reading, mm (length minus the nominal home length). motor : (N, 2) motor joint angles, rad.
    gap : (N,) largest closure gap, m. converged : (N,) bool. qpos : (N, nq) MuJoCo configurations.
    """

    r: np.ndarray
    length: np.ndarray
    scale: np.ndarray
    motor: np.ndarray
    gap: np.ndarray
    converged: np.ndarray
    qpos: np.ndarray


class PlanarTwin:
    """A real planar robot: nominal model + ``errors`` (zero offsets, geometric errors, MAEMM)."""

    def __init__(self, errors: Errors | None = None, machine: PlanarMachine | None = None,
                 nthread: int | None = None):
        self.machine = machine or default_machine()
        self.errors = errors if errors is not None else Errors()
        self.model, self.index = build_model(self.machine, self.errors)
        self.rho_ref = scale_reference(self.machine)
        self.z0 = self.machine.twin.base_height_m
        # A consistent mechanism: every closure closes; equal weights, no load on the scale's slide.
        stiffness = Stiffness(closure=np.ones(len(CLOSURES)), ss_axial=0.0)
        # The assembler switches constraints off in the model it is given: it gets its own copy, and
        # ``self.model`` stays a complete model for simulation and rendering.
        self.assembler = BatchAssembler(copy.deepcopy(self.model), self.index, stiffness,
                                        held_dofs=self.index.dadr_base, tol=1e-13, max_iter=40, nthread=nthread)

    def to_plane(self, xyz: np.ndarray) -> np.ndarray:
        """World points (..., 3) m -> seed plane (..., 2) mm."""
        xyz = np.asarray(xyz, dtype=float)
        return np.stack([xyz[..., 0] / MM, (xyz[..., 2] - self.z0) / MM], axis=-1)

    def initial_qpos(self, motor: np.ndarray) -> np.ndarray:
        """Starting configurations (N, nq) on the paper's assembly branch, from the nominal closed forms.

        Only the branch matters: Gauss-Newton then converges to the model's own closure.
        """
        motor = np.atleast_2d(np.asarray(motor, dtype=float))
        g = self.machine.geometry
        r = forward(g, motor)
        if not np.all(np.isfinite(r)):
            bad = int(np.flatnonzero(~np.all(np.isfinite(r), axis=1))[0])
            raise ValueError(f"motor angles {np.rad2deg(motor[bad])} deg are out of the robot's reach")
        w = r[:, None, :] - elbows(g, motor)
        phi = np.arctan2(w[..., 1], w[..., 0])
        lam = mm_vector(g, r)
        q = np.zeros((len(motor), self.model.nq))
        a = self.index.qadr
        q[:, a["right_motor"]], q[:, a["left_motor"]] = motor[:, 0], motor[:, 1]
        q[:, a["right_shaft"]] = -motor[:, 0]
        q[:, a["right_passive"]] = motor[:, 0]
        q[:, a["right_distal"]] = phi[:, 0]
        q[:, a["right_distal_b"]] = phi[:, 0]
        q[:, a["platform_pin"]] = -phi[:, 0]
        q[:, a["left_distal"]] = phi[:, 1] - motor[:, 1]
        q[:, a["scale_pivot"]] = np.arctan2(lam[:, 1], lam[:, 0])
        q[:, a["scale_slide"]] = (np.linalg.norm(lam, axis=1) - self.rho_ref) * MM
        return q

    def assemble(self, motor: np.ndarray) -> PlanarPoses:
        """Close the loops with the motor joints at ``motor`` (N, 2) rad (what the servos really hold) and
        read P and the linear scale."""
        motor = np.atleast_2d(np.asarray(motor, dtype=float))
        q = self.initial_qpos(motor)
        res = self.assembler.solve(q)
        n = len(motor)
        gap = np.linalg.norm(res.gaps, axis=-1).max(axis=1)
        P = self.assembler.sites(n, np.array([self.index.site_P]))[:, 0]
        scale = res.qpos[:, self.index.qadr_slide] / MM
        return PlanarPoses(r=self.to_plane(P), length=self.rho_ref + scale, scale=scale, motor=motor,
                           gap=gap, converged=res.converged & (gap < CLOSURE_TOL_M), qpos=res.qpos)
