"""The effect vocabulary (docs/formats.md) as numerics: parameters, context functions and signatures.

An *effect* is a physical behaviour the geometric model leaves out. Each has a name from the vocabulary,
one value at the interface (:data:`VOCABULARY`, units there) and a few internal parameters (radians,
1/K, rad/(N m)) that enter the model linearly at first order:

=======================  ============  =================================================================
effect                   layer         model (per motor j = 1, 2; joint = command + dtheta + offset)
=======================  ============  =================================================================
``backlash``             joint angle   offset_j = -b_j s_j, s_j = approach sign (+1: final motion up)
``encoder_eccentricity`` joint angle   offset_j = s_j sin(theta_j) + c_j cos(theta_j) = a_j sin(theta_j + phi_j)
``zero_offset_drift``    joint angle   offset_j = r_j t + q_j t^2, t = time since the first pose in hours
                                       (pose index without time_s): members linear (q = 0), quadratic
``joint_compliance``     physics       a series spring K_j = 1/c_j behind each motor, loaded by gravity (the
                                       MJCF inertia + payload) and the internal over-constraint forces:
                                       to first order offset_j = -c_j tau_j (tau_j the motor torque)
``thermal_expansion``    geometry      lengths grow linearly with dT = temp_c - 20, each group g of
                                       :data:`THERMAL_GROUPS` at its own rate alpha + delta_g: the
                                       common rate alpha scales the whole machine about O, the part
                                       deviations delta_g (cranks, couplers, strut, base, platform with
                                       its nests) act to first order through the length sensitivities;
                                       members (:func:`member_maps`): uniform, links only, ..., per part
``overconstraint``       geometry      passive-limb (L3, L4) geometric errors, absent from the baseline
``frame_drift``          frame         the base (or the tracker) moves during the campaign: every target
                                       moves rigidly by t (v + w x p), v (mm/h) the translation rate of
                                       the base origin O, w (rad/h) the rotation rate, t as for the drift
=======================  ============  =================================================================

The twin (:mod:`pmcal.twin.ocpm.effects`) uses the same context functions to make data, with real MuJoCo physics
for compliance (motor springs under gravity) and thermal expansion (per-pose scaled models). The
diagnosis (:mod:`pmcal.calib.ocpm.diagnose`) uses them as signatures: d targets / d parameter at the baseline
fit. :class:`EffectChainModel` is the whole-chain forward model with these terms, fitted by
:func:`pmcal.calib.ocpm.fullchain.identify_full`. Units: mm, rad, hours, N m, kg, degrees Celsius.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pmcal.mechanism.ocpm.data import Measurements
from pmcal.mechanism.motion import approach_from_order  # noqa: F401 (the ocpm modules import it from here)
from pmcal.mechanism.ocpm.params import LIMB_FIELDS

REFERENCE_TEMP_C = 20.0
#: Passive-limb keys: the parameters of ``overconstraint`` (no motor on limbs 3, 4).
PASSIVE_KEYS: tuple[str, ...] = tuple(f"L{j}.{f}" for j in (3, 4) for f in LIMB_FIELDS if f != "dtheta")
#: Parts that may expand at their own rate (``thermal_expansion.<part>``: the part's deviation from the common
#: rate ``thermal_expansion.alpha``): the RSR cranks (l1 of every RSR limb), the RSR couplers (l2), the SS
#: strut (its length), the base (base-joint positions B_j about O), the platform with its target nests
#: (platform-joint positions A_j, the ball-joint offset and the target positions about the platform origin).
THERMAL_GROUPS: tuple[str, ...] = ("cranks", "couplers", "strut", "base", "platform")
#: Length keys of each part's lengths (the base and platform: their joint positions, :func:`thermal_group_weights`).
PART_LENGTH_KEYS: dict[str, tuple[str, ...]] = {
    "cranks": tuple(f"L{j}.dl1" for j in (1, 2, 3, 4)), "couplers": tuple(f"L{j}.dl2" for j in (1, 2, 3, 4)),
    "strut": ("SS.dh",)}
#: Prior std of a part's deviation from the common rate, 1/K: weak, about the spread of the expansion rates of
#: the metals machines are built from (aluminium 23e-6, steel 12e-6, cast iron 10e-6, invar 1e-6: materials
#: differ by 2x around a common rate of ~12e-6). It keeps the parts a campaign does not separate near the
#: common rate instead of letting them trade off without bound.
THERMAL_GROUP_STD = 1.2e-5
#: Plausible range of each part's own rate, 1/K: carbon-fibre tubes along the fibre (-1e-6 .. 0), invar
#: (~1e-6), steel (12e-6), aluminium and magnesium (23e-6 .. 26e-6); checked with a 3-std allowance.
PART_RATE_RANGE = (-2e-6, 25e-6)
#: Context column kept in ``Measurements.extra`` (see :func:`with_context`).
T_REL = "effect_t_rel"


@dataclass(frozen=True)
class EffectInfo:
    """One entry of the vocabulary; sizes in the interface unit ``unit``."""

    name: str
    layer: str                        # "joint angle", "physics" or "geometry"
    unit: str
    params: tuple[str, ...]           # internal parameter names (keys are "<name>.<param>")
    typical: float                    # a size real machines have
    plausible: tuple[float, float]    # range of a physically plausible value
    minimum: float                    # smallest value worth naming
    needs: str                        # the context that makes it visible
    fix: str                          # the measurement that makes it identifiable when it is not
    what: str

    @property
    def keys(self) -> list[str]:
        if self.name == "overconstraint":
            return list(PASSIVE_KEYS)
        return [f"{self.name}.{p}" for p in self.params]


VOCABULARY: dict[str, EffectInfo] = {e.name: e for e in (
    EffectInfo("joint_compliance", "physics", "N m/rad", ("c1", "c2"), 5.0e4, (1.0e3, 1.0e8), 0.0,
               "gravity torques that vary independently of the pose: several payloads (payload_kg)",
               "measure the same poses with two or more payloads (e.g. 0 and 10 kg): with one payload "
               "the deflection is a smooth function of the pose and hides in the geometry",
               "motor joints twist under the gravity load of platform, links and payload (series spring "
               "behind each motor, stiffness K)"),
    EffectInfo("backlash", "joint angle", "deg", ("b1", "b2"), 0.0125, (0.0, 0.2), 0.001,
               "both approach directions per motor (m1_approach, m2_approach)",
               "approach every pose from a random side per motor and record m1_approach/m2_approach: "
               "with one approach direction backlash is just a zero offset",
               "lost motion in the drives: the joint lags the command by the half-width b against the "
               "direction of the final approach"),
    EffectInfo("encoder_eccentricity", "joint angle", "deg", ("s1", "c1", "s2", "c2"), 0.01, (0.0, 0.1), 0.001,
               "a wide range of motor angles (tilts up to 80-85 deg) and many poses",
               "spread the motor angles as widely as the workspace allows (theta up to 85 deg, 100+ poses); "
               "over a narrow range a first harmonic looks like geometry. A full motor turn with the limb "
               "disconnected, or a second read head, separates it for certain",
               "first-harmonic error of the motor angle: a sin(theta + phi) per motor (encoder disc "
               "mounted off-centre)"),
    EffectInfo("thermal_expansion", "geometry", "1/K", ("alpha",) + THERMAL_GROUPS, 23e-6, (0.0, 5e-5), 1e-7,
               "poses at different temperatures (temp_c), or a temperature far from 20 degC",
               "record temp_c and measure over a temperature change of several kelvin (warm-up)",
               "lengths grow linearly with the temperature, each part (RSR cranks, RSR couplers, SS strut, base, "
               "platform with its nests) at its own rate around a common one (value: the fastest part's rate "
               "in the member that fits; members: uniform, links only, base and platform, links and the rest, "
               "RSR links and the rest, per part)"),
    EffectInfo("zero_offset_drift", "joint angle", "deg/h", ("r1", "r2", "q1", "q2"), 0.0125, (-1.0, 1.0), 0.001,
               "poses measured in an order that does not follow the pose (time_s or row order)",
               "measure the poses in random order (or revisit a reference pose) and record time_s: in "
               "tilt order a drift looks like geometry",
               "motor zero offsets creep smoothly in time during the campaign: rate r (value, deg/h at the "
               "first pose) and curvature q (deg/h^2); members: linear (q = 0), quadratic"),
    EffectInfo("overconstraint", "geometry", "mm", (), 0.5, (0.0, 5.0), 0.01,
               "always visible: the passive limbs hold the platform's third rotation",
               "more poses over a wider tilt range (the passive-limb geometry has combinations no pose "
               "set separates)",
               "geometric errors of the passive limbs 3, 4 that the baseline model leaves out load the "
               "closed chain and move the platform"),
    EffectInfo("frame_drift", "frame", "mm/h", ("vx", "vy", "vz", "wx", "wy", "wz"), 0.18, (0.0, 5.0), 0.001,
               "poses measured in an order that does not follow the pose (time_s or row order)",
               "measure the poses in random order and re-measure the reference nests (or a reference pose) "
               "during the campaign",
               "the machine's base or the tracker moves during the campaign (a floor slide, a settling stand): "
               "every target of a pose moves as one rigid body, growing with time (value: the translation "
               "rate of the base origin; params: vx, vy, vz mm/h and the rotation rates wx, wy, wz deg/h)"),
)}

EFFECT_NAMES: tuple[str, ...] = tuple(VOCABULARY)
#: The effects of the joint-angle layer (outside the physics).
DRIVE_EFFECTS = ("backlash", "encoder_eccentricity", "zero_offset_drift")


def effect_of_key(key: str) -> str | None:
    """The effect a parameter key belongs to (None for a baseline key)."""
    if key in PASSIVE_KEYS:
        return "overconstraint"
    name = key.split(".", 1)[0]
    return name if name in VOCABULARY else None


# ---------------------------------------------------------------------------------------- context
def relative_time(time_s: np.ndarray | None, n: int) -> tuple[np.ndarray, str]:
    """Time since the first pose, hours (``"h"``); the row index (``"pose"``) without time stamps."""
    if time_s is None or not np.all(np.isfinite(time_s)):
        return np.arange(n, dtype=float), "pose"
    t = np.asarray(time_s, float)
    return (t - t[0]) / 3600.0, "h"


def with_context(meas: Measurements) -> tuple[Measurements, str]:
    """A copy of ``meas`` carrying the effects' context in ``extra`` (kept by ``subset``): the time since
    the first row (:func:`relative_time`). Returns it and the time unit (``"h"`` or ``"pose"``)."""
    t, unit = relative_time(meas.time_s, len(meas))
    out = meas.subset(np.arange(len(meas)))
    out.extra = dict(meas.extra, **{T_REL: t})
    return out, unit


def drive_basis(name: str, cmd_deg: np.ndarray, approach: np.ndarray | None = None,
                t_rel: np.ndarray | None = None) -> np.ndarray | None:
    """Context functions of a joint-angle effect: ``B`` (N, 2, k) with offset (N, 2) rad = ``B @ x``.

    ``x`` are the effect's internal parameters (:attr:`EffectInfo.params`: rad, or rad per unit of
    ``t_rel``). Returns None when the context the effect needs is missing.
    """
    cmd = np.atleast_2d(np.asarray(cmd_deg, float))
    N = len(cmd)
    k = len(VOCABULARY[name].params)
    B = np.zeros((N, 2, k))
    if name == "backlash":
        if approach is None:
            return None
        a = np.asarray(approach, float)
        B[:, 0, 0], B[:, 1, 1] = -a[:, 0], -a[:, 1]
    elif name == "encoder_eccentricity":
        th = np.deg2rad(cmd)
        B[:, 0, 0], B[:, 0, 1] = np.sin(th[:, 0]), np.cos(th[:, 0])
        B[:, 1, 2], B[:, 1, 3] = np.sin(th[:, 1]), np.cos(th[:, 1])
    elif name == "zero_offset_drift":
        if t_rel is None:
            return None
        t = np.asarray(t_rel, float)
        B[:, 0, 0] = B[:, 1, 1] = t
        B[:, 0, 2] = B[:, 1, 3] = t * t
    else:
        raise KeyError(f"'{name}' is not a joint-angle effect")
    return B


def meas_basis(name: str, meas: Measurements) -> np.ndarray | None:
    """:func:`drive_basis` with the context a (:func:`with_context`) measurement set carries."""
    return drive_basis(name, meas.m_cmd_deg, meas.approach, meas.extra.get(T_REL))


def frame_motion(targets: np.ndarray, t_rel: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Displacement (N, k, 3) mm of the targets (N, k, 3) mm by the ``frame_drift`` parameters ``x`` =
    (vx, vy, vz mm per unit of ``t_rel``, wx, wy, wz rad per unit of ``t_rel``): t (v + w x p), first order
    in the rotation (w t below 1e-4 rad on real campaigns)."""
    t = np.asarray(t_rel, float)[:, None, None]
    return t * (np.asarray(x[:3], float) + np.cross(np.asarray(x[3:6], float), targets))


def frame_basis(targets: np.ndarray, t_rel: np.ndarray) -> np.ndarray:
    """d targets / d ``frame_drift`` parameters, (N, k, 3, 6): :func:`frame_motion` is linear in them."""
    return np.stack([frame_motion(targets, t_rel, e) for e in np.eye(6)], axis=-1)


def thermal_delta(temp_c: np.ndarray | None) -> np.ndarray | None:
    """Temperature above the 20 degC reference, K (None without temperatures)."""
    if temp_c is None or not np.all(np.isfinite(temp_c)):
        return None
    return np.asarray(temp_c, float) - REFERENCE_TEMP_C


# ---------------------------------------------------------------------------------------- families
def thermal_group_weights(geom, errors: dict[str, float] | None = None) -> dict[str, list[tuple[str, float]]]:
    """How a unit strain of each part moves the geometric keys: part -> [(key, mm per unit strain)] (the
    platform's target nests are not geometric keys: :class:`pmcal.twin.ocpm.effect_model.EffectChainModel`
    adds them). A part that expands by ``e`` changes every key ``k`` listed by ``e w_k``, ``w_k`` the
    length's current value, nominal plus ``errors`` (mm, interface keys): cranks l1, couplers l2, strut
    the SS length; base: the components of B_j about O; platform: those of A_j and of the ball-joint
    offset C_E in the platform frame. ``geom`` is the nominal
    :class:`pmcal.mechanism.ocpm.config.Geometry`."""
    e = errors or {}
    B, A = geom.base_points(), geom.platform_points()
    out = {p: [(k, (geom.h if k == "SS.dh" else geom.l) + e.get(k, 0.0)) for k in ks]
           for p, ks in PART_LENGTH_KEYS.items()}
    out.update({"base": [], "platform": [(f"SS.dc{a}", e.get(f"SS.dc{a}", 0.0)) for a in "xyz"]})
    for j in range(geom.n_limbs):
        for c, axis in enumerate("xyz"):
            kb, ka = f"L{j + 1}.db{axis}", f"L{j + 1}.da{axis}"
            out["base"].append((kb, float(B[j, c]) + e.get(kb, 0.0)))
            out["platform"].append((ka, float(A[j, c]) + e.get(ka, 0.0)))
    return {g: [(k, float(w)) for k, w in ws if w != 0.0] for g, ws in out.items()}


def _thermal_members() -> dict[str, np.ndarray]:
    """Members of the thermal family as part-rate structures G (5, k): part rates = G y (a part outside
    the member does not expand)."""
    g = {n: i for i, n in enumerate(THERMAL_GROUPS)}

    def cols(*sets):
        G = np.zeros((len(THERMAL_GROUPS), len(sets)))
        for c, s in enumerate(sets):
            G[[g[n] for n in s], c] = 1.0
        return G

    links, rsr = ("cranks", "couplers", "strut"), ("cranks", "couplers")
    return {"uniform": cols(THERMAL_GROUPS), "links only": cols(links),
            "base and platform": cols(("base", "platform")),
            "links and the rest": cols(links, ("base", "platform")),
            "RSR links and the rest": cols(rsr, ("strut", "base", "platform")),
            "links, base and platform": cols(links + ("base", "platform")),
            "per part": np.eye(len(THERMAL_GROUPS))}


def member_maps(name: str) -> dict[str, np.ndarray]:
    """The members of an effect family as linear maps A (params, m) from a member's own parameters to the
    family's internal parameters (x = A z), in the order simplest first. Thermal: z = (alpha, group
    rates y) with deviations G y - alpha (alpha is free: a uniform shift of the rates is the common rate);
    drift: z = the rates (linear) or rates and curvatures (quadratic). Empty for effects without members."""
    if name == "thermal_expansion":
        out = {}
        for m, G in _thermal_members().items():
            A = np.zeros((1 + len(THERMAL_GROUPS), 1 + G.shape[1]))
            A[0, 0], A[1:, 0], A[1:, 1:] = 1.0, -1.0, G
            out[m] = A
        return out
    if name == "zero_offset_drift":
        return {"linear": np.eye(4)[:, :2], "quadratic": np.eye(4)}
    return {}


def member_values(name: str, member: str, z: np.ndarray) -> dict[str, float]:
    """A member's own parameters ``z`` (internal units) as named values: thermal part rates (1/K, the
    parts the member moves), drift rates and curvatures (rad/h, rad/h^2)."""
    if name == "thermal_expansion":
        G = _thermal_members()[member]
        rates = G @ z[1:]
        return {g: float(r) for g, r, used in zip(THERMAL_GROUPS, rates, G.any(axis=1)) if used}
    return {k: float(v) for k, v in zip(VOCABULARY[name].params, z)}
