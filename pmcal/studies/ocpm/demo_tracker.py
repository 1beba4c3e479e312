"""The demo's tracker-frame run (docs/tracker_frame.md): a designed campaign measured by a tracker in its
own frame with nest offsets, a blocked target and an outlier, identified with the registration, judged in
the motor axes' frame. :func:`tracker_run` is a worker-process entry point of ``pmcal demo``; units mm and
degrees.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from pmcal.ocpm.calibration import identify
from pmcal.mechanism.ocpm.config import Geometry
from pmcal.mechanism.rotations import pointing_error, tilt_torsion

#: Largest tilt of the demo's tracker-frame campaign, deg (the designed campaign's default).
TRACKER_THETA_MAX = 80.0


def tracker_run(truth: dict, plan, seed: int, geom: Geometry, test_phi, test_theta, params_path: Path) -> dict:
    """A tracker-frame campaign and its calibration (docs/tracker_frame.md): as many poses as ``plan``,
    designed for the tracker frame (D-optimal to 80 deg), the tracker somewhere around the machine, the
    nests 0.3 mm off the drawing, 5 % of the rows with a blocked target and one row with a 2 mm outlier;
    identified with ``frame="tracker"`` and saved to ``params_path``. Returns the params document, the
    truth (the registration of the motor axes' frame) and the held-out pointing (deg) in the base frame as
    the motor axes define it (about as costly as one whole-chain fit)."""
    from pmcal.calib.ocpm.registration import motor_axes_frame, rotation_error_deg
    from pmcal.calib.ocpm.tracker_design import tracker_campaign
    from pmcal.threads import apply_blas_policy
    from pmcal.twin.ocpm.campaign import CampaignPlan, MeasurementFaults, run_campaign
    from pmcal.twin.ocpm.forward import FullChainModel
    from pmcal.twin.ocpm.machine import Twin
    from pmcal.twin.tracker import LaserTracker, random_tracker_pose

    apply_blas_policy()
    t0 = time.perf_counter()
    twin = Twin(truth, geom)
    # the campaign a tracker-frame calibration is told to use (docs/tracker_frame.md), the demo's size;
    # a small candidate set keeps its design cheap (~0.6 s)
    phi, theta = tracker_campaign(FullChainModel(geom), len(plan), TRACKER_THETA_MAX, seed, geom.sigma_mm,
                                  n_candidates=150)
    plan = CampaignPlan(phi_deg=phi, theta_deg=theta, approach=plan.approach, time_s=plan.time_s)
    rng = np.random.default_rng(seed + 6000)
    pose = random_tracker_pose(rng)
    faults = MeasurementFaults(nest_error_mm=0.3, blocked=0.05, outliers=1, outlier_mm=2.0, seed=seed + 6001)
    meas = run_campaign(twin, plan, LaserTracker(geom.sigma_mm, rng, pose=pose), faults=faults)
    cal = identify(meas, frame="tracker", source="demo tracker-frame campaign")
    outliers = [(int(i) + 1, int(k) + 1) for i, k in np.argwhere(np.abs(meas.extra["outlier"]).max(axis=2) > 0)]
    # Table 2 tilts the motor axes (L2.dalpha, L1.dgamma): the base frame the tracker fit finds, and the
    # targets are meant in, is the motor axes' frame Q of the twin's frame
    Q = motor_axes_frame(twin.errors, geom)
    st = twin.reach(cal.compensator.commands_deg(test_phi, test_theta))
    target = Q @ tilt_torsion(np.deg2rad(test_phi), np.deg2rad(test_theta))
    pointing = np.rad2deg(pointing_error(st.R, target))
    cal.save(params_path)
    return {"document": cal.document, "pose": (pose[0] @ Q, pose[1]),
            "motor_axes_deg": rotation_error_deg(Q, np.eye(3)), "nest_offsets": meas.extra["nest_offsets"][0],
            "outliers": outliers, "blocked_rows": [int(i) + 1 for i in np.flatnonzero(~meas.visible.all(axis=1))],
            "pointing": pointing, "wall": time.perf_counter() - t0}


def summary(tr: dict) -> dict:
    """The tracker-frame run in figures (deg, mm): pointing, registration error and its std, the
    outliers planted and the targets the fit rejected (row, target)."""
    from pmcal.calib.ocpm.registration import rotation_error_deg

    reg = tr["document"]["registration"]
    R, t = np.asarray(reg["R"]), np.asarray(reg["t_mm"])
    rejected = [(r["row"], r["target"]) for r in tr["document"].get("rejected", [])]
    return {"after_mean_deg": float(tr["pointing"].mean()), "after_max_deg": float(tr["pointing"].max()),
            "registration_rotation_error_deg": rotation_error_deg(R, tr["pose"][0]),
            "registration_rotation_std_deg": float(np.linalg.norm(reg["std_rot_deg"])),
            "registration_translation_error_mm": float(np.linalg.norm(t - tr["pose"][1])),
            "registration_translation_std_mm": float(np.linalg.norm(reg["std_t_mm"])),
            "motor_axes_vs_twin_frame_deg": tr["motor_axes_deg"],
            "outliers_planted": tr["outliers"], "rejected": rejected,
            "outliers_named": set(tr["outliers"]) <= set(rejected), "blocked_rows": tr["blocked_rows"],
            "wall_time_s": tr["wall"]}
