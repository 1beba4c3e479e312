"""An effect's fitted parameters as one value at the interface: value, 95 % interval, plausibility.

Internal parameters (radians, 1/K, rad/(N m), rad/h) come from the diagnosis' fits with their
covariance; the value is in the unit of :data:`pmcal.mechanism.ocpm.effects.VOCABULARY` (compliance as a
stiffness K = 1/c), the interval by the delta method. Also the effects' prior standard deviations.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import stats

from pmcal.mechanism.ocpm.effects import (PART_RATE_RANGE, THERMAL_GROUP_STD, THERMAL_GROUPS, VOCABULARY,
                                          effect_of_key, member_maps, member_values)
from pmcal.calib.ocpm.fullchain import Priors
from pmcal.mechanism.ocpm.params import is_angular

Z95 = 1.959963984540054


def effect_prior_std(key: str, priors: Priors, time_unit: str = "h") -> float:
    """Prior std (internal units) of a candidate's parameter: passive geometry at the manufacturing
    tolerance, effect parameters weakly informative (3 times the plausible maximum)."""
    name = effect_of_key(key)
    if name == "overconstraint":
        return priors.std(key)
    info = VOCABULARY[name]
    hi = max(abs(info.plausible[0]), abs(info.plausible[1]))
    if name == "joint_compliance":
        return 3.0 / info.plausible[0]                      # c = 1/K up to 1/(1e3 N m/rad)
    if name == "thermal_expansion":   # the groups' deviations from the common rate: the ridge
        return 3.0 * hi if key.endswith(".alpha") else THERMAL_GROUP_STD
    if name == "frame_drift":       # mm/h and rad/h; per pose: over ~120 poses an hour
        per = 120.0 if time_unit == "pose" else 1.0
        return (3.0 * hi if key.split(".")[1][0] == "v" else np.deg2rad(0.1)) / per
    if name == "zero_offset_drift":
        quad = key[-2] == "q"
        if time_unit == "pose":     # deg per pose; the curvature weakly informative over ~100 poses
            return np.deg2rad(0.05) / (100.0 if quad else 1.0)
        return np.deg2rad(3.0 * hi)                        # deg/h and deg/h^2
    return np.deg2rad(3.0 * hi)


@dataclass
class EffectValue:
    """An effect's value (interface unit) with its 95 % interval, per-parameter values, and the checks."""

    name: str
    value: float
    interval: tuple[float | None, float | None]
    unit: str
    params: dict[str, tuple[float, float]]     # interface value and std per parameter
    plausible: bool
    big_enough: bool
    why: str = ""
    note: str = ""                        # e.g. unexpected sign: check a convention
    member: str = ""                      # the family member that fits best (:func:`select_member`)
    member_params: dict[str, tuple[float, float]] = field(default_factory=dict)   # its values and stds
    per_motor: list[dict] = field(default_factory=list)   # :func:`per_motor_values`
    parts: list[dict] = field(default_factory=list)       # thermal: :func:`separable_parts`
    motors: tuple[int, ...] = ()          # the motors that carry it (:func:`per_motor_values`)


def _interface(key: str, v: float) -> float:
    """An internal parameter value (or std) in its interface unit: angles to degrees."""
    name = effect_of_key(key)
    if name in ("joint_compliance", "thermal_expansion") or (name == "overconstraint" and not is_angular(key)) \
            or (name == "frame_drift" and key.split(".")[1][0] == "v"):
        return float(v)
    return float(np.rad2deg(v))


#: Per-motor effects: name -> the parameter indices of motor 1 and motor 2.
MOTOR_PARAMS = {"backlash": ((0,), (1,)), "encoder_eccentricity": ((0, 1), (2, 3)),
                "zero_offset_drift": ((0, 2), (1, 3))}


def _motor_value(name: str, x: np.ndarray, m: int, t_end: float = 0.0) -> float:
    """One motor's value (interface unit): backlash the full dead band 2 b (deg), eccentricity the
    amplitude (deg), drift the campaign-mean rate (deg per time unit): the drift from the first pose to
    the last (``t_end`` after it) over ``t_end``, r + q t_end (:func:`campaign_mean_rate`)."""
    i = MOTOR_PARAMS[name][m]
    if name == "backlash":
        return float(np.rad2deg(2.0 * x[i[0]]))
    if name == "encoder_eccentricity":
        return float(np.rad2deg(np.hypot(x[i[0]], x[i[1]])))
    return float(np.rad2deg(campaign_mean_rate(x, m, t_end)))


def campaign_mean_rate(x: np.ndarray, m: int, t_end: float) -> float:
    """Motor ``m``'s (0-based) mean drift rate over a campaign that lasts ``t_end`` (time unit of the fit)
    from the drift parameters ``x`` = (r1, r2[, q1, q2]) (rad per time unit, offset r t + q t^2): the drift
    between the first and the last pose over the duration, r + q t_end (internal units).

    Unlike the rate at the first pose r, it does not depend on the form the family gives the drift: over
    poses spread evenly in time a quadratic's r + q t_end is the slope of the straight line through the
    same offsets, so it is the same whether the campaign's drift is linear, quadratic or a creep that
    levels off (an exponential's rate at the first pose is not what a quadratic fits, docs/diagnose.md)."""
    return float(x[m] + (x[m + 2] * t_end if len(x) == 4 else 0.0))


#: The drift's curvature 2 q may change over the campaign by this multiple of itself (a third time
#: derivative up to ``DRIFT_CURVATURE_CHANGE * 2 |q| / t_end``): the smoothness :func:`drift_form_allowance`
#: assumes of a drift.
DRIFT_CURVATURE_CHANGE = 1.0


def drift_form_allowance(x: np.ndarray, m: int, t_end: float) -> float:
    """Model-form allowance (internal units, a std added in quadrature) on motor ``m``'s campaign-mean
    drift rate (:func:`campaign_mean_rate`) for the drift shapes a quadratic does not hold.

    Over poses spread evenly in time, a cubic term c t^3 moves the true mean rate by c t_end^2 and the
    quadratic's r + q t_end by 9/10 of it: the error is d3 t_end^2 / 60 for a third time derivative
    d3 = 6 c. The allowance takes d3 as large as a curvature 2 q changing by its own size over the
    campaign (:data:`DRIFT_CURVATURE_CHANGE`): |q| t_end / 30. An exponential creep over half its time
    constant is within it (error 0.45 % of the mean rate); a 3-h oscillation over a 64-min campaign
    (error 9 %, about one std at 0.01 deg) is about its size; a linear drift adds its fitted curvature's
    noise (about 1 % of the interval's width). Zero for a linear fit (``x`` of two rates)."""
    if len(x) != 4:
        return 0.0
    return float(DRIFT_CURVATURE_CHANGE * abs(x[m + 2]) * t_end / 30.0)


def _summary(name: str, keys: list[str], x: np.ndarray, motors: tuple[int, ...] = (1, 2),
             t_end: float = 0.0) -> float:
    """The effect's one value (interface unit) from its internal parameters; a per-motor effect's is the
    mean over the ``motors`` that carry it (backlash: the full dead band; drift: the RMS of the
    campaign-mean rates over a campaign of ``t_end``)."""
    if name == "joint_compliance":
        return float(np.mean(x))                                     # c; inverted by the caller
    if name in MOTOR_PARAMS:
        vals = [_motor_value(name, x, m - 1, t_end) for m in motors]
        if name == "zero_offset_drift":                             # the campaign-mean rates, RMS
            return float(np.sqrt(np.mean(np.square(vals))))
        return float(np.mean(vals))
    if name == "frame_drift":                                       # the base origin's translation rate
        return float(np.linalg.norm(x[:3]))
    if name == "thermal_expansion":                                 # the fastest group's rate
        rates = x[0] + x[1:]
        return float(rates[np.argmax(np.abs(rates))])
    lengths = [i for i, k in enumerate(keys) if not is_angular(k)]
    return float(np.sqrt(np.mean(x[lengths] ** 2)))


def effect_value(name: str, keys: list[str], x: np.ndarray, cov: np.ndarray, time_unit: str = "h",
                 t_rel: np.ndarray | None = None, dtemp: np.ndarray | None = None,
                 motors: tuple[int, ...] | None = None) -> EffectValue:
    """Value, 95 % interval (delta method), plausibility and size of an effect's fitted parameters
    (internal units, covariance ``cov``). ``t_rel`` (N,): each pose's time since the first in ``time_unit``
    (needed by the drift: its campaign-mean rate and the check :func:`drift_reversal`) and ``dtemp`` (N,) K
    its temperature above 20 degC (None: not recorded). ``motors``, if given, are the motors that carry a
    per-motor effect (the diagnosis' own per-motor test) instead of those of :func:`per_motor_values`."""
    info = VOCABULARY[name]
    std = np.sqrt(np.clip(np.diag(cov), 0, None))
    params = {k: (_interface(k, v), _interface(k, s)) for k, v, s in zip(keys, x, std)}
    if name == "zero_offset_drift" and t_rel is None:
        raise ValueError("zero_offset_drift: its value needs each pose's time since the first (t_rel)")
    t_end = float(np.max(t_rel)) if t_rel is not None and np.size(t_rel) else 0.0
    per_motor, carry = per_motor_values(name, x, cov, t_end) if len(keys) == len(info.keys) else ([], ())
    motors = tuple(motors) if motors is not None and per_motor else carry
    f0, s_f = _delta(lambda v: _summary(name, keys, v, motors or (1, 2), t_end), x, cov)
    if name == "zero_offset_drift" and per_motor and f0 > 0:    # each motor's allowance through the RMS
        on = [per_motor[m - 1] for m in (motors or (1, 2))]
        s_f = float(np.hypot(s_f, np.linalg.norm([p["value"] * p["form_allowance"] for p in on]) / (len(on) * f0)))
    lo_p, hi_p = info.plausible
    unit = {"zero_offset_drift": f"deg/{time_unit}", "frame_drift": f"mm/{time_unit}"}.get(name, info.unit)
    why = ""
    if name == "joint_compliance":
        c, sc = f0, s_f
        value = 1.0 / c if c > 0 else float("inf")
        interval = (1.0 / (c + Z95 * sc) if c + Z95 * sc > 0 else None, 1.0 / (c - Z95 * sc) if c - Z95 * sc > 0 else None)
        plausible = bool(np.all(x > -3 * std)) and c + 3 * sc >= 1.0 / hi_p and c - 3 * sc <= 1.0 / lo_p
        big = c > 1.0 / hi_p
        params = {k: (1.0 / v if v > 0 else float("inf"), s / v**2 if v > 0 else float("inf"))
                  for k, v, s in zip(keys, x, std)}
        unit = info.unit
        if not plausible:
            why = "stiffness outside 1e3 .. 1e8 N m/rad or negative"
    else:
        value, interval = f0, (f0 - Z95 * s_f, f0 + Z95 * s_f)
        plausible = lo_p - 3 * s_f <= f0 <= hi_p + 3 * s_f
        if name == "thermal_expansion":
            plausible &= f0 > -3 * s_f
        big = abs(f0) >= info.minimum if unit == info.unit else True   # the minimum is in info.unit only
        if not plausible:
            why = f"value {f0:.3g} {unit} outside the plausible range {lo_p:g} .. {hi_p:g}"
        elif name == "zero_offset_drift" and t_rel is not None and len(keys) == 4:
            why = drift_reversal(x, cov, np.asarray(t_rel, float), unit, dtemp)
            plausible = not why
    note = ""
    if name == "backlash" and np.any(x < -3 * std):
        note = ("backlash: negative lost motion fitted (the drive leads its command): check the approach sign "
                "convention (+1 = last move upwards) and the encoder side")
    if not big:
        note = (note + "; " if note else "") + f"{name}: smaller than {info.minimum:g} {unit} (named all the same)"
    ev = EffectValue(name, float(value), interval, unit, params, bool(plausible), bool(big), why, note,
                     per_motor=per_motor, motors=motors)
    maps = member_maps(name)
    if maps and len(keys) == maps[next(iter(maps))].shape[0]:
        member, z, cov_z = select_member(x, cov, maps)
        A = maps[member]
        ev.member = member
        s_z = np.sqrt(np.clip(np.diag(cov_z), 0, None))
        v, sv = member_values(name, member, z), member_values(name, member, s_z)
        if name == "thermal_expansion":
            G = A[1:, 1:]
            # std of each group's rate G z_y (the rates share the member's parameters)
            cov_r = G @ cov_z[1:, 1:] @ G.T
            sv = dict(zip(v, np.sqrt(np.clip(np.diag(cov_r)[G.any(axis=1)], 0, None))))
            ev.member_params = {g: (float(v[g]), float(sv[g])) for g in v}
            g = max(v, key=lambda k: abs(v[k]))                   # the value: the member's fastest part
            ev.value, ev.interval = v[g], (v[g] - Z95 * sv[g], v[g] + Z95 * sv[g])
            ev.parts = separable_parts(x, cov)
            # every rate must be a material's: the member's, and each single part the campaign determines on
            # its own (a simpler member can hide a part fitted at a rate no material has; the merged sets
            # are left out: a merge of parts that truly differ biases the others)
            lo, hi = PART_RATE_RANGE
            single = [p for p in separable_parts(x, cov, np.inf) if p["std"] <= SEPARABLE_STD]
            rates = [(k, v[k], sv[k]) for k in v] + [(p["parts"][0], p["rate"], p["std"]) for p in single]
            bad = [r for r in rates if not lo - 3 * r[2] <= r[1] <= hi + 3 * r[2]]
            if bad and ev.plausible:
                ev.plausible = False
                ev.why = (f"{bad[0][0]} expands at {bad[0][1]:.3g} +- {bad[0][2]:.2g} 1/K, outside the plausible "
                          f"range of a part {lo:g} .. {hi:g} 1/K")
            ev.note = "; ".join(filter(None, [ev.note, parts_note(ev.parts)]))
        else:
            ev.member_params = {k: (float(np.rad2deg(v[k])), float(np.rad2deg(sv[k]))) for k in v}
    return ev


def _delta(f, x: np.ndarray, cov: np.ndarray) -> tuple[float, float]:
    """``f(x)`` and its standard deviation by the delta method (forward-difference gradient)."""
    std = np.sqrt(np.clip(np.diag(cov), 0, None))
    f0 = f(x)
    g = np.zeros(len(x))
    for i in range(len(x)):
        h = 1e-6 * max(std[i], abs(x[i]), 1e-12)
        xp = x.copy()
        xp[i] += h
        g[i] = (f(xp) - f0) / h
    return float(f0), float(np.sqrt(max(g @ cov @ g, 0.0)))


def _confidence_ring(v: np.ndarray, cov: np.ndarray, level: float) -> tuple[np.ndarray | None, bool]:
    """Points (2, 721) on the boundary of the ``level`` confidence ellipse of a 2-D estimate ``v`` with
    covariance ``cov``, and whether the ellipse holds the origin (None when ``cov`` is not finite)."""
    if not np.all(np.isfinite(cov)):
        return None, True
    r2 = stats.chi2.ppf(level, 2)
    try:
        inside = float(v @ np.linalg.solve(cov, v)) <= r2
    except np.linalg.LinAlgError:
        inside = False
    w, U = np.linalg.eigh(0.5 * (cov + cov.T))
    t = np.linspace(0.0, 2.0 * np.pi, 721)
    return v[:, None] + U @ (np.sqrt(np.clip(w, 0.0, None) * r2)[:, None] * np.stack([np.cos(t), np.sin(t)])), inside


def amplitude_interval(v: np.ndarray, cov: np.ndarray, level: float = 0.95) -> tuple[float, float]:
    """Interval of the amplitude ``|v|`` (units of ``v``) of a 2-D estimate: the distances from the origin
    the ``level`` confidence ellipse spans (from 0 when it holds the origin). Near zero amplitude ``|v|``
    is biased up and far from Gaussian (a Rice distribution), where the delta method's interval misses."""
    ring, inside = _confidence_ring(v, cov, level)
    if ring is None:
        return 0.0, float("inf")
    r = np.hypot(ring[0], ring[1])
    return (0.0 if inside else float(r.min())), float(r.max())


def phase_interval(v: np.ndarray, cov: np.ndarray, level: float = 0.95) -> tuple[float, float]:
    """Interval (deg, ``lo <= phase <= hi``, ``hi - lo <= 360``) of the phase ``atan2(v[1], v[0])`` of a 2-D
    estimate ``v`` with covariance ``cov``: the angles the ``level`` confidence ellipse of ``v`` spans seen
    from the origin (the whole circle when it holds the origin). The delta method's ``+-1.96 std`` is too
    narrow when the amplitude is small against its uncertainty (the phase is then far from Gaussian); this
    projection of the 2-D region covers at least ``level``."""
    ph = float(np.rad2deg(np.arctan2(v[1], v[0])))
    ring, inside = _confidence_ring(v, cov, level)
    if inside:
        return ph - 180.0, ph + 180.0
    d = (np.rad2deg(np.arctan2(ring[1], ring[0])) - ph + 180.0) % 360.0 - 180.0
    return ph + float(d.min()), ph + float(d.max())


def per_motor_values(name: str, x: np.ndarray, cov: np.ndarray,
                     t_end: float = 0.0) -> tuple[list[dict], tuple[int, ...]]:
    """Each motor's value of a per-motor effect (:data:`MOTOR_PARAMS`) with its 95 % interval (delta
    method; the eccentricity's amplitude and phase from its 2-D confidence region, :func:`amplitude_interval`,
    :func:`phase_interval`),
    interface units: backlash the full dead band 2 b (deg: the lost motion between the two
    approach directions), eccentricity the amplitude (deg) and phase (deg, ``a sin(theta + phase)``), drift
    the campaign-mean rate (deg per time unit: the drift from the first pose to the last, ``t_end`` in the
    fit's time unit after it, over ``t_end``; :func:`campaign_mean_rate`; its interval adds the model-form
    allowance ``form_allowance``, :func:`drift_form_allowance`, in quadrature to ``std``) with its shape
    beside it, the rate at the first pose ``rate_first_pose`` and the curvature (each with its std). Also the motors that
    carry the effect: those whose own parameters differ from zero at 95 % (Wald test, 1 or 2 degrees of
    freedom: backlash b; eccentricity both components; drift r and q, a drift of any shape). Empty for
    other effects."""
    if name not in MOTOR_PARAMS:
        return [], ()
    out, carry = [], []
    for m, idx in enumerate(MOTOR_PARAMS[name]):
        idx = list(idx)
        v, sv = _delta(lambda z: _motor_value(name, z, m, t_end), x, cov)
        item = {"motor": m + 1, "value": v, "std": sv, "interval": (v - Z95 * sv, v + Z95 * sv)}
        if name == "encoder_eccentricity":
            ph, sph = _delta(lambda z: float(np.rad2deg(np.arctan2(z[idx[1]], z[idx[0]]))), x, cov)
            v2, c2 = x[idx[:2]], cov[np.ix_(idx[:2], idx[:2])]
            lo, hi = amplitude_interval(v2, c2)
            item.update(interval=(float(np.rad2deg(lo)), float(np.rad2deg(hi))), phase_deg=ph, phase_std=sph,
                        phase_interval=phase_interval(v2, c2))
        if name == "zero_offset_drift":
            sub = idx[:len(x) // 2]
            a = float(np.rad2deg(drift_form_allowance(x, m, t_end)))
            item.update(interval=(float(v - Z95 * np.hypot(sv, a)), float(v + Z95 * np.hypot(sv, a))), form_allowance=a,
                        duration=float(t_end), rate_first_pose=float(np.rad2deg(x[idx[0]])),
                        rate_first_pose_std=float(np.rad2deg(np.sqrt(max(cov[idx[0], idx[0]], 0.0)))))
            if len(x) == 4:
                q, sq = float(np.rad2deg(x[idx[1]])), float(np.rad2deg(np.sqrt(max(cov[idx[1], idx[1]], 0.0))))
                item.update(curvature=q, curvature_std=sq)
        else:
            sub = idx
        xi, ci = x[sub], cov[np.ix_(sub, sub)]
        wald = float(xi @ np.linalg.pinv(ci) @ xi) if np.any(ci) else float("inf")
        if wald > stats.chi2.ppf(0.95, len(sub)):
            carry.append(m + 1)
        out.append(item)
    return out, tuple(carry)


#: Correlation with the temperature above which a reversing drift's time course follows the temperature.
FOLLOWS_TEMPERATURE = 0.9


def drift_reversal(x: np.ndarray, cov: np.ndarray, t_rel: np.ndarray, unit: str,
                   dtemp: np.ndarray | None = None) -> str:
    """Why a fitted drift (r1, r2, q1, q2) is implausible: a motor whose rate at the first pose (r) and at
    the last (r + 2 q t_end) are both beyond 3 std and of opposite signs, and whose time course
    r t + q t^2 follows the temperature (|correlation| >= :data:`FOLLOWS_TEMPERATURE` with ``dtemp``),
    rises and falls back with a warm-up then cool-down: that is something following the temperature (a
    tracker stand, a thermal zero shift), not a creep of the drive. A reversal that does not follow the
    temperature (a climate cycle of the drive cabinet), or without temperatures, is kept. Empty string
    when the drift is plausible."""
    t_end = float(np.max(t_rel)) if t_rel.size else 0.0
    for m in range(2):
        g0, g1 = np.eye(4)[m], np.eye(4)[m] + 2.0 * t_end * np.eye(4)[m + 2]
        d0, d1 = g0 @ x, g1 @ x
        s0, s1 = np.sqrt(max(g0 @ cov @ g0, 0.0)), np.sqrt(max(g1 @ cov @ g1, 0.0))
        if not (d0 * d1 < 0 and abs(d0) > 3 * s0 and abs(d1) > 3 * s1) or dtemp is None or np.ptp(dtemp) == 0:
            continue
        rho = float(np.corrcoef(x[m] * t_rel + x[m + 2] * t_rel**2, dtemp)[0, 1])
        if abs(rho) >= FOLLOWS_TEMPERATURE:
            return (f"motor {m + 1}'s drift reverses within the campaign ({np.rad2deg(d0):.3g} then "
                    f"{np.rad2deg(d1):.3g} {unit}) in step with the temperature (correlation {rho:.2f}): "
                    "it follows the temperature, not the time")
    return ""


def _gls(x: np.ndarray, cov: np.ndarray, A: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Generalised least squares of ``x = A z`` (``x`` with covariance ``cov``): z, its covariance, and the
    misfit ``(x - A z)^T cov^-1 (x - A z)``."""
    W = np.linalg.pinv(cov)
    cov_z = np.linalg.pinv(A.T @ W @ A)
    z = cov_z @ A.T @ W @ x
    d = x - A @ z
    return z, cov_z, float(d @ W @ d)


#: A part's (or combination's) rate counts as determined by the campaign when its std is at most this, 1/K:
#: aluminium (23e-6) and steel (12e-6) then differ by more than 4 std.
SEPARABLE_STD = 2.5e-6


def separable_parts(x: np.ndarray, cov: np.ndarray, max_std: float = SEPARABLE_STD) -> list[dict]:
    """The parts of a thermal fit (``x`` = alpha and the part deviations, covariance ``cov``) whose rates the
    campaign determines, and the combinations it determines when single parts are not: each part starts
    on its own (GLS rates, 1/K); while a set's std exceeds ``max_std`` it is merged with another set (the
    parts then share one rate: what the campaign sees is their combination), the one whose common rate the
    fit rejects least (smallest GLS misfit: a poorly seen part joins a part it agrees with, so a merge does
    not bias the others). Returns [{"parts": [...], "rate", "std", "separable"}], ``separable`` False for
    a set still above ``max_std`` when nothing is left to merge it with (the campaign does not determine
    it)."""
    n = len(THERMAL_GROUPS)

    def rates(sets):
        G = np.zeros((n, len(sets)))
        for c, st in enumerate(sets):
            G[list(st), c] = 1.0
        A = np.zeros((1 + n, 1 + len(sets)))
        A[0, 0], A[1:, 0], A[1:, 1:] = 1.0, -1.0, G
        z, cov_z, misfit = _gls(x, cov, A)
        return z[1:], np.sqrt(np.clip(np.diag(cov_z)[1:], 0, None)), misfit

    sets = [(i,) for i in range(n)]
    r, s, _ = rates(sets)
    while len(sets) > 1 and s.max() > max_std:
        worst = int(np.argmax(s))
        trials = []
        for j in range(len(sets)):
            if j != worst:
                merged = [st for k, st in enumerate(sets) if k not in (worst, j)] + [tuple(sorted(sets[worst] + sets[j]))]
                trials.append((*rates(merged)[::-1], merged))
        _, s, r, sets = min(trials, key=lambda t: t[0])
    return [{"parts": [THERMAL_GROUPS[i] for i in st], "rate": float(rv), "std": float(sv),
             "separable": bool(sv <= max_std)} for st, rv, sv in sorted(zip(sets, r, s), key=lambda t: t[0])]


def parts_note(parts: list[dict]) -> str:
    """One line: the rates the campaign determines, by part or by combination of parts."""
    if not parts:
        return ""
    text = "; ".join(f"{'+'.join(p['parts'])} {p['rate']:.3g} +- {p['std']:.2g} 1/K"
                     + ("" if p["separable"] else " (not determined by this campaign)") for p in parts)
    joined = [p for p in parts if len(p["parts"]) > 1]
    tail = (" (" + "; ".join(f"{' and '.join(p['parts'])} not separable with this campaign" for p in joined) + ")"
            if joined else "")
    return f"thermal_expansion by part: {text}{tail}"


#: Level of the test that rejects a simpler member of a family against the whole family.
MEMBER_ALPHA = 0.01


def select_member(x: np.ndarray, cov: np.ndarray, maps: dict[str, np.ndarray]) -> tuple[str, np.ndarray, np.ndarray]:
    """The member of a family that fits: the simplest (fewest parameters, then smallest misfit) whose
    constraint ``x = A z`` the family fit (``x``, covariance ``cov``) does not reject at
    :data:`MEMBER_ALPHA` (Wald test, ``min_z (x - A z)^T cov^-1 (x - A z) ~ chi2(rank)`` with the rank
    the family has beyond the member); the whole family when every simpler member is rejected. Returns
    the member's name, its parameters z (generalised least squares) and their covariance."""
    n = len(x)
    best = None
    for name, A in maps.items():
        z, cov_z, chi2 = _gls(x, cov, A)
        k = n - np.linalg.matrix_rank(A)
        ok = k == 0 or stats.chi2.sf(chi2, k) >= MEMBER_ALPHA
        cand = (not ok, A.shape[1], chi2, name, z, cov_z)
        if best is None or cand[:3] < best[:3]:
            best = cand
    return best[3], best[4], best[5]
