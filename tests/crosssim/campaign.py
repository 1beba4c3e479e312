"""Campaigns on the independent simulator: effects, time-ordered logging, the measurement CSV.

Effects are this simulator's own versions (not the twin's forms):
- ``thermal``: alpha (1/K) of the links only (l1, l2 of every RSR limb and the SS link) about 20 degC; the
  base and the platform (steel) do not expand; or, with ``thermal_body``, base and platform of another
  material at that rate (B_j about O, A_j and C_E about the platform origin) while the links expand at
  ``thermal`` (0 for invar links); the target nests never expand;
- ``backlash``: half-width b (deg) per motor; the drive lags its command by b against the direction of
  the motor's last move, read from the move order (the machine starts at home, beta = -39.351 deg);
- ``drift``: zero-offset creep with an initial rate (deg/h) per motor that relaxes exponentially with time
  constant ``drift_tau_s`` (linear for tau = inf), or (``drift_period_s``) oscillates as
  rate·P/(2π)·sin(2π t/P) (a drive cabinet's climate cycle);
- ``eccentricity``: amplitude (deg) and arbitrary phase (rad) per motor, a·sin(command + phase);
- ``compliance``: torsional stiffness K (N·m/rad) per motor in the closed-chain solve;
- passive-limb errors: any `L3.*`/`L4.*` keys in the geometric errors;
- ``thermal_parts``: each part at its own rate (1/K): ``cranks`` (l1 of every RSR limb), ``couplers`` (l2),
  ``strut`` (the SS length), ``base`` (B_j about O), ``platform`` (A_j, C_E and the target nests about the
  platform origin: the nests sit on the platform);
- ``frame_drift``: the tracker's frame moves against the machine's base during the campaign (the machine
  slides on its floor): the measured point is exp(s [w]x) p + s d, s = the fraction of the campaign's
  time elapsed, d (mm) and w (deg, rotation vector) the motion over the whole campaign;
Effects that no family of pmcal's vocabulary holds (to check nothing is falsely named):
- ``tracker_scale``: a range error growing with the distance from the tracker (at ``TRACKER_MM``): the
  measured point moves along the beam by eps d^2 / D0 (D0 = 2500 mm);
- ``stand_creep``: the tracker's stand expands with the temperature and moves the tracker along x by
  c (temp_c - 18) mm (a translation following the temperature: not a scale about the machine);
- ``nest_sag``: target nest 1 on a cantilever arm bends under gravity by delta (mm) times the component of
  gravity across its arm (pose dependent, not time or temperature dependent).
Rows are written in time order without approach columns, as a user logs them.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass, field

import numpy as np

from .machine import HOME_DEG, ClosedChain, Geometry, nominal_ik

KEYS_LIMB = ["dbx", "dby", "dbz", "dalpha", "dgamma", "dl1", "dl2", "dax", "day", "daz", "dtheta"]


@dataclass
class SimEffects:
    thermal: float = 0.0
    thermal_body: float = 0.0
    backlash: tuple = (0.0, 0.0)
    drift: tuple = (0.0, 0.0)
    drift_tau_s: float = 7200.0
    drift_period_s: float | None = None
    eccentricity: tuple = (0.0, 0.0)
    ecc_phase: tuple = (0.0, 0.0)
    compliance: tuple | None = None
    thermal_parts: dict | None = None
    frame_drift: tuple | None = None          # (dx, dy, dz mm, wx, wy, wz deg) over the campaign
    tracker_scale: float = 0.0                # eps, range error eps d^2 / D0
    nest_sag: float = 0.0                     # delta, mm
    stand_creep: float = 0.0                  # mm/K along x, about 18 degC


#: Parts of the per-part thermal expansion (``SimEffects.thermal_parts``).
PARTS = ("cranks", "couplers", "strut", "base", "platform")
#: Position of the tracker in the base frame, mm (``tracker_scale``), and the reference distance D0.
TRACKER_MM, D0_MM = np.array([2500.0, 800.0, 600.0]), 2500.0


@dataclass
class Campaign:
    """Poses in measurement (time) order: target orientation, commands (deg), context columns."""

    phi_deg: np.ndarray
    theta_deg: np.ndarray
    cmd_deg: np.ndarray
    time_s: np.ndarray
    temp_c: np.ndarray
    payload_kg: np.ndarray
    targets: np.ndarray = field(default=None)  # (n, 3, 3) mm, base frame


def random_errors(rng: np.random.Generator, size_mm: float = 0.5, limbs=(1, 2), ss: bool = True) -> dict:
    """Uniform errors ±size mm / ±0.2·size deg on the listed limbs (dtheta on motors only) and the SS limb."""
    e = {}
    for j in limbs:
        for k in KEYS_LIMB + ["dmu", "dnu"]:
            if k == "dtheta" and j > 2:
                continue
            ang = k in ("dalpha", "dgamma", "dmu", "dnu", "dtheta")
            e[f"L{j}.{k}"] = float(rng.uniform(-1, 1) * (0.2 * size_mm if ang else size_mm))
    if ss:
        for k in ("dh", "dcx", "dcy", "dcz"):
            e[f"SS.{k}"] = float(rng.uniform(-1, 1) * size_mm)
    return e


def plan(n: int, theta_max_deg: float, rng: np.random.Generator, seconds_per_pose: float = 30.0,
         temp_range=(18.0, 28.0), payloads=(0.0, 10.0), block: int = 32) -> Campaign:
    """n orientations uniform on the spherical cap theta <= theta_max, in random time order; temperature
    warms up from temp_range[0] to temp_range[1] and cools back (half sine over the campaign); payloads
    change in blocks of ``block`` rows."""
    phi = rng.uniform(0, 360, n)
    theta = np.rad2deg(np.arccos(rng.uniform(np.cos(np.deg2rad(theta_max_deg)), 1.0, n)))
    cmd = np.array([nominal_ik(p, t)[:2] for p, t in zip(phi, theta)])
    t = np.arange(n) * seconds_per_pose
    lo, hi = temp_range
    temp = lo + (hi - lo) * np.sin(np.pi * t / max(t[-1], 1.0))
    pay = np.array([payloads[(i // block) % len(payloads)] for i in range(n)], float)
    return Campaign(phi, theta, cmd, t, temp, pay)


def drive_angles(c: Campaign, geom: Geometry, fx: SimEffects) -> np.ndarray:
    """Angles (n, 2) rad the motors deliver: command + zero offset + drift + eccentricity − backlash lag."""
    cmd = np.deg2rad(c.cmd_deg)
    prev = np.vstack([np.deg2rad([HOME_DEG, HOME_DEG]), cmd[:-1]])
    move = np.sign(cmd - prev)
    for i in range(1, len(move)):  # no move: the last approach stays
        move[i] = np.where(move[i] == 0, move[i - 1], move[i])
    drift = drift_offsets(c.time_s, fx)
    out = cmd + [geom.limb(1)["dtheta"], geom.limb(2)["dtheta"]]
    for m in range(2):
        out[:, m] += np.deg2rad(drift[:, m]
                                + fx.eccentricity[m] * np.sin(cmd[:, m] + fx.ecc_phase[m])
                                - fx.backlash[m] * move[:, m])
    return out


def drift_offsets(time_s: np.ndarray, fx: SimEffects) -> np.ndarray:
    """Zero-offset drift (n, 2) deg of each motor at the times ``time_s`` (s), zero at the first: the
    initial rate ``fx.drift`` (deg/h) times the creep (s) of the form, exponential relaxation
    tau (1 - exp(-t/tau)), linear t (tau = inf) or oscillating sin(w t)/w."""
    dt = np.asarray(time_s, float) - time_s[0]
    tau = fx.drift_tau_s
    creep = dt if not np.isfinite(tau) else tau * (1 - np.exp(-dt / tau))
    if fx.drift_period_s is not None:
        w = 2 * np.pi / fx.drift_period_s
        creep = np.sin(w * dt) / w
    return np.stack([fx.drift[m] * creep / 3600.0 for m in range(2)], axis=1)


def simulate(c: Campaign, errors: dict, fx: SimEffects, sigma_mm: float = 0.01, rng=None,
             gravity: bool = True, max_energy: float = 1.25e4) -> Campaign:
    """Solve every pose, measure the targets (noise sigma per coordinate); poses whose chain does not
    close (strain energy > ``max_energy`` N·mm, default 1.25e4: a 5 mm gap at a passive closure) are
    skipped as an operator would (dropped from the plan, so the move order and the times are those of
    the poses actually driven to). Returns the campaign of the measured poses."""
    geom = Geometry(errors)
    drive = drive_angles(c, geom, fx)
    keep, tg = [], []
    for i in range(len(c.phi_deg)):
        dT = c.temp_c[i] - 20.0
        if fx.thermal_parts:
            s = {p: 1 + fx.thermal_parts.get(p, 0.0) * dT for p in PARTS}
            scales = dict(link_scale=s["cranks"], coupler_scale=s["couplers"], strut_scale=s["strut"],
                          base_scale=s["base"], platform_scale=s["platform"])
            nests = s["platform"]
        else:
            scales = dict(link_scale=1 + fx.thermal * dT, base_scale=1 + fx.thermal_body * dT,
                          platform_scale=1 + fx.thermal_body * dT)
            nests = 1.0
        chain = ClosedChain(geom, motor_stiffness=fx.compliance, payload_kg=c.payload_kg[i], gravity=gravity,
                            **scales)
        try:
            r, R, _, energy = chain.solve(drive[i], (c.phi_deg[i], c.theta_deg[i]))
        except np.linalg.LinAlgError:
            continue
        if not np.isfinite(energy) or energy > max_energy:
            continue
        keep.append(i)
        tg.append(r + nests * TARGETS_ROT(R) + sag(R, fx.nest_sag))
    keep = np.array(keep, int)
    if len(keep) < len(c.phi_deg):   # the operator drops those poses from the plan: the move order changes
        sub = Campaign(c.phi_deg[keep], c.theta_deg[keep], c.cmd_deg[keep], c.time_s[keep], c.temp_c[keep],
                       c.payload_kg[keep])
        return simulate(sub, errors, fx, sigma_mm, rng, gravity, max_energy)
    t = tracker_view(np.array(tg), c.time_s, fx)
    t[:, :, 0] += fx.stand_creep * (c.temp_c - 18.0)[:, None]
    if rng is not None and sigma_mm > 0:
        t = t + rng.normal(0, sigma_mm, t.shape)
    return Campaign(c.phi_deg, c.theta_deg, c.cmd_deg, c.time_s, c.temp_c, c.payload_kg, t)


def sag(R: np.ndarray, delta: float) -> np.ndarray:
    """Displacement (3, 3) mm of the targets when nest 1, on a cantilever arm along its radial direction,
    bends by ``delta`` times the component of gravity (unit, -z) across the arm; the other nests are stiff."""
    out = np.zeros((3, 3))
    if delta:
        from .machine import TARGETS
        arm = R @ np.array([TARGETS[0, 0], TARGETS[0, 1], 0.0])
        arm /= np.linalg.norm(arm)
        g = np.array([0.0, 0.0, -1.0])
        out[0] = delta * (g - (g @ arm) * arm)
    return out


def tracker_view(points: np.ndarray, time_s: np.ndarray, fx: SimEffects) -> np.ndarray:
    """Targets (n, 3, 3) mm as the tracker sees them: its frame moving against the base (``frame_drift``,
    linear in the campaign's elapsed time) and its range error (``tracker_scale``)."""
    from scipy.spatial.transform import Rotation

    out = points.copy()
    if fx.tracker_scale:
        v = out - TRACKER_MM
        d = np.linalg.norm(v, axis=-1, keepdims=True)
        out = out + v / d * fx.tracker_scale * d**2 / D0_MM
    if fx.frame_drift is not None:
        span = max(float(time_s[-1] - time_s[0]), 1.0)
        s = (np.asarray(time_s, float) - time_s[0]) / span
        d, w = np.asarray(fx.frame_drift[:3], float), np.deg2rad(np.asarray(fx.frame_drift[3:], float))
        for i in range(len(out)):
            out[i] = Rotation.from_rotvec(s[i] * w).apply(out[i]) + s[i] * d
    return out


def TARGETS_ROT(R: np.ndarray) -> np.ndarray:  # noqa: N802 - targets of the platform, (3, 3) mm
    from .machine import TARGETS
    return TARGETS @ R.T


def write_csv(path, c: Campaign, context: bool = True) -> None:
    """The measurement CSV (pose_id, m1_cmd_deg, m2_cmd_deg, t1_x..t3_z, [temp_c, time_s, payload_kg]),
    rows in time order, no approach columns."""
    head = ["pose_id", "m1_cmd_deg", "m2_cmd_deg"] + [f"t{k}_{a}" for k in (1, 2, 3) for a in "xyz"]
    if context:
        head += ["temp_c", "time_s", "payload_kg"]
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(head)
        for i in range(len(c.cmd_deg)):
            row = [f"X{i + 1:03d}", f"{c.cmd_deg[i, 0]:.6f}", f"{c.cmd_deg[i, 1]:.6f}"]
            row += [f"{v:.5f}" for v in c.targets[i].ravel()]
            if context:
                row += [f"{c.temp_c[i]:.3f}", f"{c.time_s[i]:.1f}", f"{c.payload_kg[i]:g}"]
            w.writerow(row)


#: realistic sizes of this simulator's effects (per motor where there are two)
REALISTIC = {"backlash": 0.02, "encoder_eccentricity": 0.01, "thermal_expansion": 23e-6,
             "zero_offset_drift": 0.0094, "joint_compliance": 5e4, "overconstraint": 0.5,
             "frame_drift": 0.19, "tracker_scale": 6e-5, "nest_sag": 0.1, "stand_creep": 0.004}
#: effects outside pmcal's vocabulary (``hidden_campaign`` names)
OUTSIDE = ("tracker_scale", "nest_sag", "stand_creep")


#: variants of an effect's form (``hidden_campaign(forms=)``): name -> form -> SimEffects fields set
FORMS = {"thermal_expansion": {"links": {}, "steel body": {"thermal_body": 12e-6},
                               "invar links": {"thermal_body": 12e-6, "thermal": 1.2e-6},
                               "per part": {"thermal_parts": {"cranks": 23e-6, "couplers": 23e-6, "strut": 12e-6,
                                                              "base": 12e-6, "platform": 17e-6}}},
         "zero_offset_drift": {"creep": {}, "sine": {"drift_period_s": 3 * 3600.0},
                               "one motor": {"only_motor": None}},
         "backlash": {"both": {}, "one motor": {"only_motor": None}}}


def hidden_campaign(names: list[str], seed: int, n: int = 128, theta_max_deg: float = 80.0,
                    sigma_mm: float = 0.01, context: bool = True, sizes: dict | None = None,
                    forms: dict | None = None, temp_range=(18.0, 28.0)) -> tuple[Campaign, dict, SimEffects]:
    """A campaign with random errors (0.5 mm / 0.1 deg in limbs 1-2 and SS) and the named effects (the
    pmcal vocabulary names) at their realistic sizes (or ``sizes[name]``) in their default form or
    ``forms[name]`` (:data:`FORMS`: thermal "steel body": aluminium links 23e-6 on a steel base and
    platform 12e-6/K, "invar links": links 1.2e-6 on a steel base and platform; drift "sine": a 3-hour
    oscillation); ``temp_range`` (start/peak, end) of the warm-up/cool-down, or a monotone ramp when given
    as ("ramp", start, end). Returns (measured campaign, errors, effects)."""
    rng = np.random.default_rng(seed)
    err = random_errors(rng)
    fx = SimEffects()
    for name in names:
        v = (sizes or {}).get(name, REALISTIC[name])
        if name == "backlash":
            fx.backlash = tuple(v * rng.uniform(0.8, 1.2, 2))
        elif name == "encoder_eccentricity":
            fx.eccentricity, fx.ecc_phase = (v, v), tuple(rng.uniform(0, 2 * np.pi, 2))
        elif name == "thermal_expansion":
            fx.thermal = v
        elif name == "zero_offset_drift":
            fx.drift = tuple(v * rng.choice([-1, 1], 2))
        elif name == "joint_compliance":
            fx.compliance = (v, v)
        elif name == "overconstraint":
            err.update(random_errors(rng, v, limbs=(3, 4), ss=False))
        elif name == "frame_drift":     # the floor slide, signs and the rotation drawn
            sgn = rng.choice([-1, 1], 6)
            fx.frame_drift = tuple(np.concatenate([np.array([0.15, 0.10, 0.05]) * v / 0.19,
                                                   np.array([0.002, 0.002, 0.003])]) * sgn)
        elif name in OUTSIDE:
            setattr(fx, name, v)
        form = (forms or {}).get(name)
        for field_, value in (FORMS[name][form] if form else {}).items():
            if field_ == "only_motor":          # the effect on one motor (drawn), the other free of it
                attr = "backlash" if name == "backlash" else "drift"
                keep = int(rng.integers(2))
                setattr(fx, attr, tuple(x if m == keep else 0.0 for m, x in enumerate(getattr(fx, attr))))
            else:
                setattr(fx, field_, value)
    c = plan(n, theta_max_deg, rng, temp_range=temp_range[-2:]) if context else plan(
        n, theta_max_deg, rng, temp_range=(20.0, 20.0), payloads=(0.0,))
    if context and temp_range[0] == "ramp":          # temperature rising (or falling) steadily with time
        c.temp_c = np.linspace(temp_range[1], temp_range[2], len(c.time_s))
    return simulate(c, err, fx, sigma_mm, rng), err, fx
