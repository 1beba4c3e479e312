"""``pmcal twin plan --for-diagnosis``: the campaign a diagnosis needs, as a command list to measure.

The list is a CSV, one row per pose in measurement order: target orientation (deg), the motor commands
(deg) the controller sends, the approach each motor makes when the rows are driven in this order (the
diagnosis infers it from the order again), the payload to mount (kg), and the planned time (s) and
machine temperature (degC) of a warm-up then cool-down. Comment lines (``#``) state what to record.
With ``--from DIAG.json`` the effects that diagnosis could not identify are listed with their fix.
"""

from __future__ import annotations

import json

import numpy as np

from pmcal.errors import InputError
from pmcal.fileio import atomic_write
from pmcal.mechanism.ocpm.effects import VOCABULARY, approach_from_order

HEADER = ["step", "phi_deg", "theta_deg", "m1_cmd_deg", "m2_cmd_deg", "m1_approach", "m2_approach",
          "payload_kg", "time_s", "temp_c_planned"]


def diagnosis_campaign(n: int, theta_max_deg: float, seed: int, seconds_per_pose: float = 30.0,
                       temps=(18.0, 28.0), payloads=(0.0, 10.0), block: int = 32) -> dict[str, np.ndarray]:
    """Poses uniform on the spherical cap theta <= theta_max in random order (every motor moves both ways:
    backlash and drift visible, drift not aligned with the pose), payloads changed in blocks of ``block``
    rows, a warm-up then cool-down (temperature not monotone in time: drift and thermal separable)."""
    from pmcal.twin.campaign import nominal_commands

    rng = np.random.default_rng(seed)
    phi = rng.uniform(0.0, 360.0, n)
    theta = np.rad2deg(np.arccos(rng.uniform(np.cos(np.deg2rad(theta_max_deg)), 1.0, n)))
    cmd = nominal_commands(phi, theta)
    t = np.arange(n) * seconds_per_pose
    temp = temps[0] + (temps[1] - temps[0]) * np.sin(np.pi * t / max(t[-1], 1.0))
    pay = np.array([payloads[(i // block) % len(payloads)] for i in range(n)], float)
    appr = approach_from_order(np.vstack([[-39.351, -39.351], cmd]))[1:]   # from home
    return dict(phi_deg=phi, theta_deg=theta, m1_cmd_deg=cmd[:, 0], m2_cmd_deg=cmd[:, 1], m1_approach=appr[:, 0],
                m2_approach=appr[:, 1], payload_kg=pay, time_s=t, temp_c_planned=temp)


def unidentified(path: str) -> list[tuple[str, str]]:
    """(effect, fix) for every candidate a diagnosis JSON marks as not identifiable or not confirmed."""
    try:
        with open(path, encoding="utf-8") as fh:
            doc = json.load(fh)
        cands = doc["candidates"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise InputError(f"not a diagnosis JSON ({exc})", file=path) from None
    out = []
    for c in cands:
        if c.get("verdict", "").startswith("not identifiable") or not c.get("available", True):
            out.append((c["name"], c.get("fix") or VOCABULARY[c["name"]].fix))
    return out


def twin_plan(args) -> int:
    """Write the diagnosis campaign's command list (module docstring)."""
    if getattr(args, "frame", "base") == "tracker":
        from pmcal.apps.ocpm_tracker_plan import tracker_plan

        return tracker_plan(args)
    if not args.for_diagnosis:
        raise InputError("give --for-diagnosis or --frame tracker (the two kinds of plan)", field="--for-diagnosis")
    if not 24 <= args.poses <= 10000:
        raise InputError(f"poses must be 24 .. 10000, got {args.poses}", field="--poses")
    if not 10.0 <= args.theta_max <= 85.0:
        raise InputError(f"theta max must be 10 .. 85 deg, got {args.theta_max:g}", field="--theta-max")
    fixes = unidentified(args.from_diagnosis) if args.from_diagnosis else []
    c = diagnosis_campaign(args.poses, args.theta_max, args.seed)
    with atomic_write(args.output) as fh:
        fh.write(f"# diagnosis campaign: {args.poses} poses to {args.theta_max:g} deg tilt, seed {args.seed}\n"
                 "# drive the rows in this order (the approach columns are what that order gives); record\n"
                 "# time_s and temp_c at every pose (warm the machine up and let it cool: temp_c_planned);\n"
                 "# mount payload_kg at the platform centre; log m1_cmd_deg, m2_cmd_deg and t1_x .. t3_z\n")
        for name, fix in fixes:
            fh.write(f"# not identifiable in the last campaign: {name}: {fix}\n")
        fh.write(",".join(HEADER) + "\n")
        for i in range(args.poses):
            vals = [c[k][i] for k in HEADER[1:]]
            fh.write(f"{i + 1}," + ",".join(f"{v:.6g}" for v in vals) + "\n")
    return 0
