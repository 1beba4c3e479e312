"""Measurement campaigns on the twin: plan poses, drive the machine, measure with the tracker.

The controller of a machine that is not yet calibrated believes the nominal model: the commanded motor
angles of a pose are the nominal inverse kinematics of the orientation it is meant to reach. The twin
goes where its real geometry takes it, and the tracker says where that is.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pmcal.mechanism.ocpm.config import Geometry, default_geometry
from pmcal.mechanism.ocpm.data import Measurements
from pmcal.mechanism.ocpm.kinematics import nominal_ik
from pmcal.mechanism.ocpm.nests import shape_part
from pmcal.mechanism.rigid import fit_pose
from pmcal.twin.ocpm.machine import Twin
from pmcal.twin.tracker import LaserTracker

#: Tilt beyond which the RSR limbs approach the stretched-link singularity (|K/rho| > 0.98 at 85 deg,
#: 1.0 at about 87.5 deg on the nominal machine): campaigns are refused beyond it.
THETA_LIMIT_DEG = 85.0
GOLDEN_ANGLE = np.pi * (3.0 - np.sqrt(5.0))


@dataclass
class CampaignPlan:
    """Poses of a campaign in measurement order (deg) and their context.

    approach : (N, 2) sign of the final motion into each pose per motor (+1: from below).
    """

    phi_deg: np.ndarray
    theta_deg: np.ndarray
    approach: np.ndarray
    time_s: np.ndarray
    temp_c: np.ndarray | None = None
    payload_kg: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.phi_deg)


def plan_orientations(n: int, theta_max_deg: float, rng: np.random.Generator,
                      theta_min_deg: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """``n`` orientations spread evenly over the cap of platform normals, jittered (deg).

    Equal-area strata in ``cos(theta)`` with a golden-angle azimuth spiral, a random jitter inside each
    stratum and a random azimuth offset: every campaign covers the workspace without repeating.
    """
    if n < 1:
        raise ValueError(f"number of poses must be at least 1, got {n}")
    if not 0 <= theta_min_deg < theta_max_deg <= THETA_LIMIT_DEG:
        raise ValueError(f"tilt range {theta_min_deg:g}..{theta_max_deg:g} deg is outside the workspace "
                         f"0..{THETA_LIMIT_DEG:g} deg (stretched-link singularity near 87.5 deg)")
    c0, c1 = np.cos(np.deg2rad(theta_min_deg)), np.cos(np.deg2rad(theta_max_deg))
    u = (np.arange(n) + rng.uniform(0.0, 1.0, n)) / n
    theta = np.rad2deg(np.arccos(c0 - u * (c0 - c1)))
    phi = np.rad2deg(np.mod(GOLDEN_ANGLE * np.arange(n) + rng.uniform(0, 2 * np.pi), 2 * np.pi))
    return phi, theta


def plan_campaign(n: int, theta_max_deg: float = 60.0, seed: int | None = 0, *,
                  randomize_approach: bool = True, seconds_per_pose: float = 30.0,
                  temp_c: np.ndarray | float | None = None,
                  payload_kg: np.ndarray | float | None = None) -> CampaignPlan:
    """A campaign of ``n`` poses up to ``theta_max_deg`` with random (or all positive) approach signs."""
    rng = np.random.default_rng(seed)
    phi, theta = plan_orientations(n, theta_max_deg, rng)
    approach = rng.choice([-1.0, 1.0], size=(n, 2)) if randomize_approach else np.ones((n, 2))
    bcast = lambda v: None if v is None else np.broadcast_to(np.asarray(v, float), (n,)).copy()  # noqa: E731
    return CampaignPlan(phi_deg=phi, theta_deg=theta, approach=approach,
                        time_s=np.arange(n) * float(seconds_per_pose),
                        temp_c=bcast(temp_c), payload_kg=bcast(payload_kg))


def nominal_commands(phi_deg: np.ndarray, theta_deg: np.ndarray, geom: Geometry | None = None) -> np.ndarray:
    """Motor commands (N, 2) deg the uncalibrated controller sends for target orientations."""
    m = np.rad2deg(nominal_ik(np.deg2rad(phi_deg), np.deg2rad(theta_deg), geom or default_geometry()))
    bad = np.flatnonzero(~np.isfinite(m).all(axis=1))
    if bad.size:
        i = int(bad[0])
        raise ValueError(f"pose {i + 1} (phi {phi_deg[i]:g} deg, theta {theta_deg[i]:g} deg) is unreachable")
    return m


@dataclass
class MeasurementFaults:
    """What a real tracker campaign adds to clean measurements (all optional, reproducible by ``seed``).

    nest_error_mm : size (1 sigma per coordinate) of the nests' offsets from the drawing; only their
        shape part is applied (the rigid part is by definition platform geometry, see
        :mod:`pmcal.mechanism.ocpm.nests`). nest_offsets : (k, 3) mm explicit offsets instead (shape part).
    blocked : probability that a row has one target blocked (line of sight; its cells are empty).
    outliers : number of rows with a gross error of ``outlier_mm`` in one coordinate of one target.
    """

    nest_error_mm: float = 0.0
    nest_offsets: np.ndarray | None = None
    blocked: float = 0.0
    outliers: int = 0
    outlier_mm: float = 2.0
    seed: int | None = 0

    def offsets(self, X: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        raw = self.nest_offsets if self.nest_offsets is not None else rng.normal(0, self.nest_error_mm, X.shape)
        return shape_part(raw, X)


def apply_faults(points: np.ndarray, X: np.ndarray, faults: MeasurementFaults, tracker: LaserTracker
                 ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Measure true platform points (N, k, 3) at drawing coordinates X through the faults; returns the
    measured targets (tracker frame, NaN where blocked) and the truth (``nest_offsets`` (k, 3),
    ``blocked`` (N, k) bool, ``outlier`` (N, k, 3) mm)."""
    rng = np.random.default_rng(faults.seed)
    n, k = points.shape[:2]
    dn = faults.offsets(X, rng)
    _, R, _ = fit_pose(points, X)
    nests = points + np.einsum("nij,kj->nki", R, dn)
    y = tracker.measure(nests)
    blocked = np.zeros((n, k), bool)
    rows = np.flatnonzero(rng.uniform(size=n) < faults.blocked)
    blocked[rows, rng.integers(0, k, len(rows))] = True
    outlier = np.zeros((n, k, 3))
    free = np.flatnonzero(~blocked.any(axis=1))
    for i in rng.choice(free, min(faults.outliers, len(free)), replace=False):
        outlier[i, rng.integers(0, k), rng.integers(0, 3)] = faults.outlier_mm * rng.choice([-1.0, 1.0])
    y = y + outlier
    y[blocked] = np.nan
    return y, {"nest_offsets": dn, "blocked": blocked, "outlier": outlier}


def measure_targets(points: np.ndarray, X: np.ndarray, faults: MeasurementFaults | None,
                    tracker: LaserTracker) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The tracker's reading of the true target points (N, k, 3) mm, base frame, with ``faults`` applied
    when given (:func:`apply_faults`); returns the measured targets and the extra truth columns
    (``outlier`` (N, k, 3) mm, ``nest_offsets`` repeated per row), empty without faults."""
    if faults is None:
        return tracker.measure(points), {}
    y, truth = apply_faults(points, X[: points.shape[1]], faults, tracker)
    return y, {"outlier": truth["outlier"],
               "nest_offsets": np.broadcast_to(truth["nest_offsets"], y.shape).copy()}


def run_campaign(twin: Twin, plan: CampaignPlan, tracker: LaserTracker,
                 m_cmd_deg: np.ndarray | None = None, id_prefix: str = "P",
                 faults: MeasurementFaults | None = None) -> Measurements:
    """Drive ``twin`` through ``plan`` (nominal commands unless ``m_cmd_deg`` is given) and measure.

    With ``faults`` the measurement has nest offsets, blocked targets and outliers; the truth is in
    ``extra`` (``outlier`` (N, k, 3) mm; the nest offsets as ``nest_offsets`` rows repeated)."""
    if m_cmd_deg is None:
        m_cmd_deg = nominal_commands(plan.phi_deg, plan.theta_deg, twin.geom)
    state = twin.reach(m_cmd_deg)
    if not np.all(state.converged):
        i = int(np.flatnonzero(~state.converged)[0])
        raise RuntimeError(f"pose {i + 1}: the twin did not assemble (closure solve did not converge)")
    width = len(str(len(plan)))
    y, extra = measure_targets(state.targets, twin.geom.targets, faults, tracker)
    return Measurements(
        pose_id=[f"{id_prefix}{i + 1:0{width}d}" for i in range(len(plan))],
        m_cmd_deg=np.asarray(m_cmd_deg, float), targets=y,
        temp_c=plan.temp_c, time_s=plan.time_s, payload_kg=plan.payload_kg, approach=plan.approach,
        extra=extra)
