"""``pmcal twin plan --frame tracker``: the campaign a tracker-frame calibration should measure.

From tracker data the machine's base frame is its motor axes, and how well a campaign fixes them is most
of what a tracker-frame calibration loses against one in a known frame (docs/tracker_frame.md). The plan
is D-optimal for every unknown of the tracker fit (:func:`pmcal.calib.ocpm.tracker_design.tracker_campaign`):
mostly poses on the rim of the workspace, a few near home, in azimuth order. The list is a CSV, one row per
pose in measurement order: target orientation (deg) and the nominal motor commands (deg); ``pmcal twin
measure --targets PLAN.csv`` measures it on the twin.
"""

from __future__ import annotations

import numpy as np

from pmcal import progress
from pmcal.errors import InputError
from pmcal.fileio import atomic_write

HEADER = ["step", "phi_deg", "theta_deg", "m1_cmd_deg", "m2_cmd_deg"]


def tracker_plan(args) -> int:
    """Write the designed tracker-frame campaign (module docstring)."""
    from pmcal.calib.ocpm.tracker_design import frame_std_deg, design_blocks, tracker_campaign
    from pmcal.mechanism.ocpm.config import default_geometry
    from pmcal.twin.ocpm.campaign import nominal_commands
    from pmcal.twin.ocpm.forward import FullChainModel

    if args.for_diagnosis:
        raise InputError("a plan is either --for-diagnosis or --frame tracker, not both", field="--frame")
    if not 24 <= args.poses <= 300:
        raise InputError(f"poses must be 24 .. 300, got {args.poses}", field="--poses")
    if not 30.0 <= args.theta_max <= 85.0:
        raise InputError(f"theta max must be 30 .. 85 deg, got {args.theta_max:g}", field="--theta-max")
    geom = default_geometry()
    model = FullChainModel(geom)
    progress.status(f"choosing {args.poses} poses to {args.theta_max:g} deg for a tracker-frame fit")
    phi, theta = tracker_campaign(model, args.poses, args.theta_max, args.seed, geom.sigma_mm,
                                  n_candidates=max(600, 2 * args.poses))
    cmd = nominal_commands(phi, theta, geom)
    B, prior, reg = design_blocks(model, phi, theta, geom.sigma_mm)
    std = float(np.linalg.norm(frame_std_deg(B, prior, reg)))
    with atomic_write(args.output) as fh:
        fh.write(f"# tracker-frame campaign: {args.poses} poses to {args.theta_max:g} deg tilt, D-optimal for the "
                 f"machine, registration and nest unknowns, seed {args.seed}\n"
                 f"# predicted base-frame (motor axes) uncertainty at {geom.sigma_mm:g} mm tracker noise: "
                 f"{std:.4f} deg (1 sigma, norm of the three rotations)\n"
                 "# drive the rows in this order; log m1_cmd_deg, m2_cmd_deg and t1_x .. t3_z (tracker frame); "
                 "identify with pmcal identify --frame tracker\n")
        fh.write(",".join(HEADER) + "\n")
        for i in range(len(phi)):
            fh.write(f"{i + 1},{phi[i]:.6f},{theta[i]:.6f},{cmd[i, 0]:.6f},{cmd[i, 1]:.6f}\n")
    print(f"predicted base-frame uncertainty {std:.4f} deg (1 sigma)", flush=True)
    return 0
