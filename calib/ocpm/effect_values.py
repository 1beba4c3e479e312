"""An effect's fitted parameters as one value at the interface: value, 95 % interval, plausibility.

Internal parameters (radians, 1/K, rad/(N m), rad/h) come from the diagnosis' fits with their
covariance; the value is in the unit of :data:`pmcal.mechanism.ocpm.effects.VOCABULARY` (compliance as a
stiffness K = 1/c), the interval by the delta method. Also the effects' prior standard deviations.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import stats

from pmcal.mechanism.ocpm.effects import THERMAL_GROUP_STD, VOCABULARY, effect_of_key, member_maps, member_values
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


def _interface(key: str, v: float) -> float:
    """An internal parameter value (or std) in its interface unit: angles to degrees."""
    name = effect_of_key(key)
    if name in ("joint_compliance", "thermal_expansion") or (name == "overconstraint" and not is_angular(key)):
        return float(v)
    return float(np.rad2deg(v))


def _summary(name: str, keys: list[str], x: np.ndarray) -> float:
    """The effect's one value (interface unit) from its internal parameters."""
    if name == "joint_compliance":
        return float(np.mean(x))                                     # c; inverted by the caller
    if name in ("backlash",):
        return float(np.rad2deg(np.mean(x)))
    if name == "encoder_eccentricity":
        return float(np.rad2deg(np.mean(np.hypot(x[0::2], x[1::2]))))
    if name == "zero_offset_drift":                                 # the rates at the first pose
        return float(np.rad2deg(np.sqrt(np.mean(x[:2] ** 2))))
    if name == "thermal_expansion":                                 # the fastest group's rate
        rates = x[0] + x[1:]
        return float(rates[np.argmax(np.abs(rates))])
    lengths = [i for i, k in enumerate(keys) if not is_angular(k)]
    return float(np.sqrt(np.mean(x[lengths] ** 2)))


def effect_value(name: str, keys: list[str], x: np.ndarray, cov: np.ndarray, time_unit: str = "h",
                 t_rel: np.ndarray | None = None, dtemp: np.ndarray | None = None) -> EffectValue:
    """Value, 95 % interval (delta method), plausibility and size of an effect's fitted parameters
    (internal units, covariance ``cov``). ``t_rel`` (N,): each pose's time since the first in ``time_unit``
    and ``dtemp`` (N,) K its temperature above 20 degC (None: not recorded), for the drift's check
    :func:`drift_reversal`."""
    info = VOCABULARY[name]
    std = np.sqrt(np.clip(np.diag(cov), 0, None))
    params = {k: (_interface(k, v), _interface(k, s)) for k, v, s in zip(keys, x, std)}
    f0 = _summary(name, keys, x)
    g = np.zeros(len(x))
    for i in range(len(x)):
        h = 1e-6 * max(std[i], abs(x[i]), 1e-12)
        xp = x.copy()
        xp[i] += h
        g[i] = (_summary(name, keys, xp) - f0) / h
    s_f = float(np.sqrt(max(g @ cov @ g, 0.0)))
    lo_p, hi_p = info.plausible
    unit = info.unit if name != "zero_offset_drift" else f"deg/{time_unit}"
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
    ev = EffectValue(name, float(value), interval, unit, params, bool(plausible), bool(big), why, note)
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
            g = max(v, key=lambda k: abs(v[k]))                   # the value: the member's fastest group
            ev.value, ev.interval = v[g], (v[g] - Z95 * sv[g], v[g] + Z95 * sv[g])
        else:
            ev.member_params = {k: (float(np.rad2deg(v[k])), float(np.rad2deg(sv[k]))) for k in v}
    return ev


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


#: Level of the test that rejects a simpler member of a family against the whole family.
MEMBER_ALPHA = 0.01


def select_member(x: np.ndarray, cov: np.ndarray, maps: dict[str, np.ndarray]) -> tuple[str, np.ndarray, np.ndarray]:
    """The member of a family that fits: the simplest (fewest parameters, then smallest misfit) whose
    constraint ``x = A z`` the family fit (``x``, covariance ``cov``) does not reject at
    :data:`MEMBER_ALPHA` (Wald test, ``min_z (x - A z)^T cov^-1 (x - A z) ~ chi2(rank)`` with the rank
    the family has beyond the member); the whole family when every simpler member is rejected. Returns
    the member's name, its parameters z (generalised least squares) and their covariance."""
    W = np.linalg.pinv(cov)
    n = len(x)
    best = None
    for name, A in maps.items():
        M = A.T @ W @ A
        cov_z = np.linalg.pinv(M)
        z = cov_z @ A.T @ W @ x
        d = x - A @ z
        chi2 = float(d @ W @ d)
        k = n - np.linalg.matrix_rank(A)
        ok = k == 0 or stats.chi2.sf(chi2, k) >= MEMBER_ALPHA
        cand = (not ok, A.shape[1], chi2, name, z, cov_z)
        if best is None or cand[:3] < best[:3]:
            best = cand
    return best[3], best[4], best[5]
