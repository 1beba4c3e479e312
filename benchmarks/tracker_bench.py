"""Calibration from tracker-frame data with nest offsets, blocked targets and an outlier (issue 16).

For each random draw: every-limb errors (0.5 mm / 0.1 deg, uniform), a random tracker pose (1-3 m away,
any yaw, +-2 deg tilt), nests 0.3 mm off the drawing (1 sigma per coordinate, shape part: the rigid part
is platform geometry by definition, docs/tracker_frame.md), 5 % of rows with one target blocked, one 2 mm
outlier in one coordinate, 48 training poses, sigma 0.01 mm. Training poses: ``--design tracker``
(default) the campaign ``pmcal twin plan --frame tracker`` writes (D-optimal for the tracker fit, to
``--theta-max``, default 80 deg); ``--design uniform`` spread evenly over the cap. The same draw is also
measured in the base frame at the same poses with exact nests, no blocking and no outlier, and identified
with ``identify_full`` (today's path). Both compensations are judged on 24 held-out poses to 60 deg by
the twin's true platform orientation (pointing error = angle between platform normal and target normal);
the tracker-frame fit also as seen by the same tracker (target carried by the identified registration).

The draws hold L1.dalpha, L1.dgamma, L2.dalpha at zero: they fix the base frame to the motor axes (the
gauge), so the twin's base frame is the frame the tracker fit recovers and the two pointing errors are
measured in the same frame. A draw with those angles non-zero is the same machine in a rotated base frame,
i.e. a different (equally random) tracker pose.

Run: python benchmarks/tracker_bench.py [--draws 10] [--poses 48] [--theta-max 80] [--design tracker|uniform]
[--json PATH]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import print_table, write_json  # noqa: E402
from pmcal.calib.ocpm.fullchain import identify_full, chain_commands_deg  # noqa: E402
from pmcal.calib.ocpm.registration import GAUGE_KEYS  # noqa: E402
from pmcal.calib.ocpm.tracker_design import tracker_campaign  # noqa: E402
from pmcal.calib.ocpm.tracker_fit import identify_tracker  # noqa: E402
from pmcal.mechanism.ocpm.params import errors_and_ratio, random_errors  # noqa: E402
from pmcal.mechanism.rotations import pointing_error, tilt_torsion  # noqa: E402
from pmcal.twin.ocpm.campaign import CampaignPlan, MeasurementFaults, plan_campaign, run_campaign  # noqa: E402
from pmcal.twin.ocpm.forward import FullChainModel  # noqa: E402
from pmcal.twin.ocpm.machine import Twin  # noqa: E402
from pmcal.twin.tracker import LaserTracker, random_tracker_pose  # noqa: E402

SIGMA = 0.01


def held_out_pointing(twin: Twin, model: FullChainModel, res, test, pose=None) -> tuple[float, float]:
    """Mean true pointing error (deg) of the compensated held-out poses, (base frame, tracker frame).

    Base frame: the machine's (motor axes), the twin's own frame. Tracker frame: what an engineer
    verifying with the same tracker sees: the target orientation carried into the tracker frame by the
    identified registration against the platform's true orientation in the tracker frame (``pose``:
    the true registration; for a base-frame fit both registrations are the identity)."""
    e, _ = errors_and_ratio(res.names, res.x)
    cmd = chain_commands_deg(model, e, test.phi_deg, test.theta_deg, stiffness_ratio=res.info["stiffness_ratio"])
    st = twin.reach(cmd)
    Rt = tilt_torsion(np.deg2rad(test.phi_deg), np.deg2rad(test.theta_deg))
    base = float(np.rad2deg(pointing_error(st.R, Rt)).mean())
    if pose is None:
        return base, base
    Rg = res.info["registration"]["R"]
    return base, float(np.rad2deg(pointing_error(pose[0] @ st.R, Rg @ Rt)).mean())


def training_plan(design: str, n_poses: int, theta_max: float, d: int, model: FullChainModel) -> CampaignPlan:
    """The draw's training campaign: ``tracker``: D-optimal for the tracker fit (what ``pmcal twin plan
    --frame tracker`` writes; candidates seeded by the draw); ``uniform``: spread evenly over the cap."""
    plan = plan_campaign(n_poses, theta_max, seed=d)
    if design == "tracker":
        plan.phi_deg, plan.theta_deg = tracker_campaign(model, n_poses, theta_max, seed=d, sigma_mm=SIGMA)
    return plan


def run_draw(d: int, n_poses: int, model: FullChainModel, theta_max: float = 80.0, design: str = "tracker") -> dict:
    rng = np.random.default_rng(2000 + d)
    params = random_errors(rng, 0.5, 0.1)
    params.update({k: 0.0 for k in GAUGE_KEYS})
    twin = Twin(params)
    pose = random_tracker_pose(rng)
    plan, test = training_plan(design, n_poses, theta_max, d, model), plan_campaign(24, 60, seed=500 + d)
    faults = MeasurementFaults(nest_error_mm=0.3, blocked=0.05, outliers=1, outlier_mm=2.0, seed=300 + d)
    meas = run_campaign(twin, plan, LaserTracker(SIGMA, np.random.default_rng(d), pose=pose), faults=faults)
    t = time.perf_counter()
    res = identify_tracker(meas, model)
    t_tracker = time.perf_counter() - t
    truth_out = {(int(i) + 1, int(k) + 1) for i, k, _ in np.argwhere(meas.extra["outlier"] != 0)}
    named = {(r["row"], r["target"]) for r in res.info["rejected"]}
    reg = res.info["registration"]
    rot_err = Rotation.from_matrix(reg["R"] @ pose[0].T).as_rotvec(degrees=True)
    nests = res.info["nests"]
    nest_z = np.abs(nests["offsets_mm"] - meas.extra["nest_offsets"][0])[:, :2] / nests["std_mm"][:, :2]
    base = run_campaign(twin, plan, LaserTracker(SIGMA, np.random.default_rng(d)))
    t = time.perf_counter()
    res_base = identify_full(base, model)
    t_base = time.perf_counter() - t
    g = [res_base.names.index(k) for k in GAUGE_KEYS]
    tracker_deg, tracker_in_tracker_deg = held_out_pointing(twin, model, res, test, pose)
    return {"tracker_deg": tracker_deg, "tracker_in_tracker_frame_deg": tracker_in_tracker_deg,
            # how well the base-frame fit itself knows the motor axes (the tracker frame's definition)
            "base_fit_motor_axes_std_deg": float(np.rad2deg(np.linalg.norm(res_base.std[g]))),
            "base_deg": held_out_pointing(twin, model, res_base, test)[0],
            "outlier_named": truth_out <= named, "false_rejections": len(named - truth_out),
            "blocked_targets": res.info["n_targets_blocked"],
            "reg_rot_err_deg": float(np.linalg.norm(rot_err)),
            "reg_rot_std_deg": float(np.linalg.norm(reg["std_rot_deg"])),
            "reg_t_err_mm": float(np.linalg.norm(reg["t_mm"] - pose[1])),
            "reg_t_std_mm": float(np.linalg.norm(reg["std_t_mm"])),
            "nest_max_z": float(nest_z.max()), "chi2_per_dof": res.info["chi2_per_dof"],
            "tracker_distance_m": float(np.linalg.norm(pose[1]) / 1000),
            "tracker_s": t_tracker, "base_s": t_base}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--draws", type=int, default=10)
    ap.add_argument("--poses", type=int, default=48)
    ap.add_argument("--theta-max", type=float, default=80.0, help="largest tilt of the training poses, deg")
    ap.add_argument("--design", choices=("tracker", "uniform"), default="tracker",
                    help="training poses: D-optimal for the tracker fit (default) or spread evenly")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    model = FullChainModel()
    draws, rows = [], []
    for d in range(args.draws):
        r = run_draw(d, args.poses, model, args.theta_max, args.design)
        draws.append(r)
        rows.append([d, r["tracker_distance_m"], r["tracker_deg"], r["tracker_in_tracker_frame_deg"], r["base_deg"],
                     r["tracker_deg"] / r["base_deg"],
                     "yes" if r["outlier_named"] else "NO", r["false_rejections"], r["blocked_targets"],
                     r["reg_rot_err_deg"], r["reg_rot_std_deg"], r["base_fit_motor_axes_std_deg"],
                     r["reg_t_err_mm"], r["reg_t_std_mm"],
                     r["nest_max_z"], r["tracker_s"], r["base_s"]])
        print(f"draw {d} done", file=sys.stderr)
    mean_t = float(np.mean([r["tracker_deg"] for r in draws]))
    mean_b = float(np.mean([r["base_deg"] for r in draws]))
    mean_seen = float(np.mean([r["tracker_in_tracker_frame_deg"] for r in draws]))
    named = sum(r["outlier_named"] for r in draws)
    print_table(f"Tracker-frame calibration, {args.draws} draws, {args.poses} poses ({args.design} design) "
                f"to {args.theta_max:g} deg, "
                f"sigma {SIGMA} mm, "
                "24 held-out poses (true pointing, deg); timings under shared-machine load",
                ["draw", "tracker m", "tracker-frame fit deg", "seen by tracker deg", "base-frame fit deg", "ratio",
                 "outlier named",
                 "false rej", "blocked", "reg rot err deg", "reg rot std deg", "axes std (base fit) deg",
                 "reg t err mm", "reg t std mm",
                 "nest max |z|", "tracker fit s", "base fit s"], rows)
    ok = mean_t <= 0.005 and mean_t <= 1.5 * mean_b and named == len(draws)
    print(f"\ntarget: mean held-out pointing <= 0.005 deg and <= 1.5x base frame, outlier named every draw: "
          f"{mean_t:.5f} deg tracker frame, {mean_b:.5f} deg base frame (ratio {mean_t / mean_b:.2f}), "
          f"outlier named {named}/{len(draws)} -> {'met' if ok else 'MISSED'}; seen in the tracker frame "
          f"{mean_seen:.5f} deg")
    write_json("tracker_bench", {"draws": args.draws, "poses": args.poses, "theta_max_deg": args.theta_max,
                                 "design": args.design, "sigma_mm": SIGMA,
                                 "mean_tracker_deg": mean_t, "mean_base_deg": mean_b,
                                 "mean_tracker_seen_in_tracker_frame_deg": mean_seen,
                                 "outlier_named": named, "per_draw": draws, "target_met": ok}, args.json)


if __name__ == "__main__":
    main()
