"""An effect's fitted parameters as one value at the interface: value, 95 % interval, plausibility.

Internal parameters (radians, 1/K, rad/(N m), rad/h) come from the diagnosis' fits with their
covariance; the value is in the unit of :data:`pmcal.mechanism.ocpm.effects.VOCABULARY` (compliance as a
stiffness K = 1/c), the interval by the delta method. Also the effects' prior standard deviations.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pmcal.mechanism.ocpm.effects import VOCABULARY, effect_of_key, thermal_member
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
    if name == "thermal_expansion":   # the links' extra rate regularised to the plausible size
        return hi if key.endswith(".links") else 3.0 * hi
    if name == "zero_offset_drift" and time_unit == "pose":
        return np.deg2rad(0.05)                            # deg per pose
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
    member: str = ""                      # the family member that fits (thermal: uniform / links only / two rates)


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
    if name == "zero_offset_drift":
        return float(np.rad2deg(np.sqrt(np.mean(x * x))))
    if name == "thermal_expansion":                                 # the links' rate
        return float(sum(v for k, v in zip(keys, x) if k in ("thermal_expansion.alpha", "thermal_expansion.links")))
    lengths = [i for i, k in enumerate(keys) if not is_angular(k)]
    return float(np.sqrt(np.mean(x[lengths] ** 2)))


def effect_value(name: str, keys: list[str], x: np.ndarray, cov: np.ndarray, time_unit: str = "h") -> EffectValue:
    """Value, 95 % interval (delta method), plausibility and size of an effect's fitted parameters
    (internal units, covariance ``cov``)."""
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
    note = ""
    if name == "backlash" and np.any(x < -3 * std):
        note = ("backlash: negative lost motion fitted (the drive leads its command): check the approach sign "
                "convention (+1 = last move upwards) and the encoder side")
    if not big:
        note = (note + "; " if note else "") + f"{name}: smaller than {info.minimum:g} {unit} (named all the same)"
    member = ""
    if name == "thermal_expansion" and len(keys) == 2:
        member = thermal_member(x[0], std[0], x[1], std[1])
    return EffectValue(name, float(value), interval, unit, params, bool(plausible), bool(big), why, note, member)


