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
from pmcal.mechanism.ocpm.config import Geometry
from pmcal.mechanism.ocpm.kinematics import HOME_BETA, passive_strained
from pmcal.twin.ocpm.campaign import nominal_commands

HEADER = ["step", "phi_deg", "theta_deg", "m1_cmd_deg", "m2_cmd_deg", "m1_approach", "m2_approach",
          "payload_kg", "time_s", "temp_c_planned"]


#: Share of a diagnosis campaign's poses on the rim band and the band's width (deg below the tilt limit).
RIM_SHARE, RIM_BAND_DEG = 0.5, 12.0


def diagnosis_orientations(n: int, theta_max_deg: float, rng: np.random.Generator, geom: Geometry | None = None,
                           rim_share: float = RIM_SHARE, rim_band_deg: float = RIM_BAND_DEG
                           ) -> tuple[np.ndarray, np.ndarray]:
    """Orientations (phi, theta) deg of an ``n``-pose diagnosis campaign, in no particular order.

    Half the poses (``rim_share``) lie evenly spaced in azimuth on the band ``theta_max - rim_band ..
    theta_max`` (tilt uniform in area within it), the others on a golden-angle spiral over the whole cap;
    both leave out the wedge where the passive limbs are strained (:func:`pmcal.mechanism.ocpm.kinematics.
    passive_strained`).

    Why: a first harmonic of the motor angle (encoder eccentricity) is told from what the geometry absorbs
    only where the motors reach their widest angles, on the rim; the spiral covers the cap without the
    clusters and holes of random draws. Why not into the wedge: there the machine strains, ~1 % of such
    poses do not assemble, and the twin and the diagnosis model's over-constraint compromise disagree
    under load; its edge would carry more of the eccentricity (power at 0.01 deg 0.96 -> 0.98; uniform
    random draws over the whole cap: 0.95). Measured in docs/diagnose.md "Decisions".

    Not :func:`pmcal.twin.ocpm.campaign.plan_orientations` (jittered equal-area strata) for the cap: with it
    the thermal family's 95 % intervals held the truth in 34 of 40 twin seeds (RMS z 1.22) against 38 of
    40 (RMS z 0.99) with this unjittered spiral; for the rim it made no difference.
    """
    k_rim = int(round(rim_share * n))
    lo = max(theta_max_deg - rim_band_deg, 0.5 * theta_max_deg)
    c_max, c_lo = np.cos(np.deg2rad(theta_max_deg)), np.cos(np.deg2rad(lo))

    def spiral(m):
        i = np.arange(m) + 0.5
        return (np.rad2deg(i * np.pi * (3.0 - np.sqrt(5.0))) + offset[0]) % 360.0, \
            np.rad2deg(np.arccos(1.0 - (1.0 - c_max) * i / m))

    def rim(m):
        return (np.arange(m) * 360.0 / m + offset[1]) % 360.0, \
            np.rad2deg(np.arccos(rng.uniform(c_max, c_lo, m)))

    offset = rng.uniform(0.0, 360.0, 2)
    out = []
    for make, k in ((spiral, n - k_rim), (rim, k_rim)):
        m = k
        while True:                                  # add candidates until k lie outside the strained wedge
            phi, theta = make(m)
            ok = np.flatnonzero(~passive_strained(phi, theta, geom))
            if len(ok) >= k:
                break
            m += max(1, k - len(ok))
        keep = np.sort(rng.choice(ok, k, replace=False))
        out.append((phi[keep], theta[keep]))
    return np.concatenate([o[0] for o in out]), np.concatenate([o[1] for o in out])


def diagnosis_campaign(n: int, theta_max_deg: float, seed: int, seconds_per_pose: float = 30.0,
                       temps=(18.0, 28.0), payloads=(0.0, 10.0), block: int = 32, rim_share: float = RIM_SHARE,
                       rim_band_deg: float = RIM_BAND_DEG) -> dict[str, np.ndarray]:
    """The poses of :func:`diagnosis_orientations` (``rim_share``, ``rim_band_deg`` as there) in random order
    (every motor moves both ways: backlash and drift visible, drift not aligned with the pose), payloads
    changed in blocks of ``block`` rows, a warm-up then cool-down (temperature not monotone in time: drift and
    thermal separable)."""
    rng = np.random.default_rng(seed)
    phi, theta = diagnosis_orientations(n, theta_max_deg, rng, rim_share=rim_share, rim_band_deg=rim_band_deg)
    order = rng.permutation(n)
    phi, theta = phi[order], theta[order]
    cmd = nominal_commands(phi, theta)
    t = np.arange(n) * seconds_per_pose
    temp = temps[0] + (temps[1] - temps[0]) * np.sin(np.pi * t / max(t[-1], 1.0))
    pay = np.array([payloads[(i // block) % len(payloads)] for i in range(n)], float)
    appr = approach_from_order(np.vstack([[HOME_BETA, HOME_BETA], cmd]))[1:]   # from home
    return dict(phi_deg=phi, theta_deg=theta, m1_cmd_deg=cmd[:, 0], m2_cmd_deg=cmd[:, 1], m1_approach=appr[:, 0],
                m2_approach=appr[:, 1], payload_kg=pay, time_s=t, temp_c_planned=temp)


def unidentified(path: str) -> list[tuple[str, str]]:
    """(effect, fix) for every candidate a diagnosis JSON marks as not identifiable or not confirmed."""
    try:
        with open(path, encoding="utf-8") as fh:
            doc = json.load(fh)
        cands = doc["candidates"]
    except (OSError, ValueError, KeyError, TypeError, RecursionError) as exc:
        raise InputError(f"not a diagnosis JSON ({exc})", file=path) from None
    out = []
    for c in cands:
        if c.get("verdict", "").startswith("not identifiable") or not c.get("available", True):
            out.append((c["name"], c.get("fix") or VOCABULARY[c["name"]].fix))
    return out


def twin_plan(args) -> int:
    """Write the diagnosis campaign's command list (module docstring)."""
    if getattr(args, "frame", "base") == "tracker":
        from pmcal.apps.ocpm.tracker_plan import tracker_plan

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
