"""Campaign design for tracker-frame calibration: which poses determine the base frame best.

From tracker data the base frame is the machine's motor axes (docs/tracker_frame.md), and how well a
campaign fixes it is the uncertainty of the registration rotation. That uncertainty falls roughly as the
inverse of the tilt range the poses cover (a motor axis is seen through the arc its limb sweeps) and
further when the poses are chosen for it. The design here is D-optimal (:func:`pmcal.calib.pose_selection.
select_poses`) over every unknown of the tracker fit: machine parameters without the gauge, the six
registration parameters and the nest shape, all whitened by the tracker noise and with the fit's priors,
from ``n_candidates`` orientations spread over the cap ``theta <= theta_max``. The chosen poses sit mostly
on the rim of the workspace with a few near home; they are returned in azimuth order (one sweep round
the rim).

The Fisher information is taken at the nominal machine and the identity registration: it does not depend
on where the tracker stands (a rotation of the tracker frame rotates every row of the Jacobian alike).
"""

from __future__ import annotations

import numpy as np

from pmcal.calib.ocpm.forward_model import ForwardModel
from pmcal.calib.ocpm.fullchain import FullChainOptions
from pmcal.calib.ocpm.tracker_fit import TrackerOptions, build_problem
from pmcal.calib.pose_selection import information, select_poses
from pmcal.mechanism.ocpm.data import Measurements
from pmcal.mechanism.ocpm.config import Geometry
from pmcal.mechanism.ocpm.kinematics import nominal_ik, passive_strained
from pmcal.mechanism.ocpm.params import ErrorSet

ROT_UNIT_DEG = np.rad2deg(1e-3)    # the registration rotation's unit in the fit's vector (tracker_fit)


def candidate_orientations(n: int, theta_max_deg: float, rng: np.random.Generator, geom: Geometry | None = None
                           ) -> tuple[np.ndarray, np.ndarray]:
    """``n`` orientations uniform on the cap of platform normals ``theta <= theta_max_deg`` (deg), outside
    the wedge where both passive limbs are strained at once (:func:`pmcal.mechanism.ocpm.kinematics.
    passive_strained`)."""
    phi, theta = np.empty(0), np.empty(0)
    while len(phi) < n:
        p = rng.uniform(0.0, 360.0, 2 * n)
        t = np.rad2deg(np.arccos(rng.uniform(np.cos(np.deg2rad(theta_max_deg)), 1.0, 2 * n)))
        ok = ~passive_strained(p, t, geom)
        phi, theta = np.r_[phi, p[ok]], np.r_[theta, t[ok]]
    return phi[:n], theta[:n]


def design_blocks(model: ForwardModel, phi_deg: np.ndarray, theta_deg: np.ndarray, sigma_mm: float,
                  frame: str = "tracker", options: FullChainOptions | None = None,
                  nest_std_mm: float = 0.5) -> tuple[np.ndarray, np.ndarray, int]:
    """Whitened Jacobian blocks (N, 3 k, n) of the poses at the nominal machine, the prior information
    matrix (n, n) and the index of the first registration parameter (-1 in the base frame)."""
    cmd = np.rad2deg(nominal_ik(np.deg2rad(phi_deg), np.deg2rad(theta_deg), model.geom))
    n, k = len(phi_deg), len(model.geom.targets)
    meas = Measurements(pose_id=[str(i) for i in range(n)], m_cmd_deg=cmd, targets=np.zeros((n, k, 3)))
    model.set(ErrorSet())
    topt = TrackerOptions(frame=frame, registration0=(np.eye(3), np.zeros(3)), nest_std_mm=nest_std_mm)
    prob = build_problem(meas, model, options or FullChainOptions(), topt)
    p, g, m = prob.sizes
    _, J = prob.evaluate(np.zeros(p + g + m))
    if not np.isfinite(J).all():
        raise ValueError("some candidate poses are outside the nominal machine's workspace")
    P = prob.prior_jac(p + g + m)
    return J.reshape(n, 3 * k, -1) / sigma_mm, P.T @ P, (p if g else -1)


def frame_std_deg(blocks: np.ndarray, prior: np.ndarray, reg: int, idx=None) -> np.ndarray:
    """Cramér-Rao standard deviation (deg) of the registration rotation about the three tracker axes for
    the poses ``idx`` (default all): how well the campaign fixes the base frame."""
    I = information(blocks if idx is None else blocks[np.asarray(idx)]).sum(axis=0) + prior
    C = np.linalg.inv(I)[reg:reg + 3, reg:reg + 3]
    return np.sqrt(np.diag(C)) * ROT_UNIT_DEG


def tracker_campaign(model: ForwardModel, n: int, theta_max_deg: float = 80.0, seed: int | None = 0,
                     sigma_mm: float = 0.01, n_candidates: int = 600, frame: str = "tracker"
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Orientations (phi, theta) deg of an ``n``-pose campaign designed for a tracker-frame fit (module
    docstring), in azimuth order."""
    if not 0 < n <= n_candidates:
        raise ValueError(f"number of poses must be 1..{n_candidates}, got {n}")
    phi, theta = candidate_orientations(n_candidates, theta_max_deg, np.random.default_rng(seed), model.geom)
    B, prior, _ = design_blocks(model, phi, theta, sigma_mm, frame)
    sel = select_poses(B, n, "D", prior=prior)
    sel = sel[np.argsort(phi[sel])]
    return phi[sel], theta[sel]
