"""The effect vocabulary (INTERFACES.md) as numerics: parameters, context functions and signatures.

An *effect* is a physical behaviour the geometric model leaves out. Each has a name from the vocabulary,
one value at the interface (:data:`VOCABULARY`, units there) and a few internal parameters (radians,
1/K, rad/(N m)) that enter the model linearly at first order:

=======================  ============  =================================================================
effect                   layer         model (per motor j = 1, 2; joint = command + dtheta + offset)
=======================  ============  =================================================================
``backlash``             joint angle   offset_j = -b_j s_j, s_j = approach sign (+1: final motion up)
``encoder_eccentricity`` joint angle   offset_j = s_j sin(theta_j) + c_j cos(theta_j) = a_j sin(theta_j + phi_j)
``zero_offset_drift``    joint angle   offset_j = r_j (t - t_0), t in hours (or pose index without time_s)
``joint_compliance``     physics       a series spring K_j = 1/c_j behind each motor, loaded by gravity (the
                                       spec's inertia + payload) and the internal over-constraint forces:
                                       to first order offset_j = -c_j tau_j (tau_j the motor torque)
``thermal_expansion``    geometry      every length scales by 1 + alpha (temp_c - 20): targets scale about O
``overconstraint``       geometry      passive-limb (L3, L4) geometric errors, absent from the baseline
=======================  ============  =================================================================

The twin (:mod:`twin.effects`) uses the same context functions to make data, with real MuJoCo physics
for compliance (motor springs under gravity) and thermal expansion (per-pose scaled models). The
diagnosis (:mod:`calib.ocpm.diagnose`) uses them as signatures: d targets / d parameter at the baseline
fit. :class:`EffectChainModel` is the whole-chain forward model with these terms, fitted by
:func:`calib.ocpm.fullchain.identify_full`. Units: mm, rad, hours, N m, kg, degrees Celsius.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib.ocpm.data import Measurements
from calib.ocpm.fullchain import FullChainModel
from calib.ocpm.params import LIMB_FIELDS

REFERENCE_TEMP_C = 20.0
#: Passive-limb keys: the parameters of ``overconstraint`` (no motor on limbs 3, 4).
PASSIVE_KEYS: tuple[str, ...] = tuple(f"L{j}.{f}" for j in (3, 4) for f in LIMB_FIELDS if f != "dtheta")
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
    EffectInfo("thermal_expansion", "geometry", "1/K", ("alpha",), 23e-6, (0.0, 5e-5), 1e-7,
               "poses at different temperatures (temp_c), or a temperature far from 20 degC",
               "record temp_c and measure over a temperature change of several kelvin (warm-up)",
               "every length of the machine (links, radii, SS limb, target nests) grows by alpha (T - 20 degC)"),
    EffectInfo("zero_offset_drift", "joint angle", "deg/h", ("r1", "r2"), 0.0125, (-1.0, 1.0), 0.001,
               "poses measured in an order that does not follow the pose (time_s or row order)",
               "measure the poses in random order (or revisit a reference pose) and record time_s: in "
               "tilt order a drift looks like geometry",
               "motor zero offsets creep linearly in time during the campaign"),
    EffectInfo("overconstraint", "geometry", "mm", (), 0.5, (0.0, 5.0), 0.01,
               "always visible: the passive limbs hold the platform's third rotation",
               "more poses over a wider tilt range (the passive-limb geometry has combinations no pose "
               "set separates)",
               "geometric errors of the passive limbs 3, 4 that the baseline model leaves out load the "
               "closed chain and move the platform"),
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
        B[:, 0, 0] = B[:, 1, 1] = np.asarray(t_rel, float)
    else:
        raise KeyError(f"'{name}' is not a joint-angle effect")
    return B


def meas_basis(name: str, meas: Measurements) -> np.ndarray | None:
    """:func:`drive_basis` with the context a (:func:`with_context`) measurement set carries."""
    return drive_basis(name, meas.m_cmd_deg, meas.approach, meas.extra.get(T_REL))


def thermal_delta(temp_c: np.ndarray | None) -> np.ndarray | None:
    """Temperature above the 20 degC reference, K (None without temperatures)."""
    if temp_c is None or not np.all(np.isfinite(temp_c)):
        return None
    return np.asarray(temp_c, float) - REFERENCE_TEMP_C


# ---------------------------------------------------------------------------------------- model
class EffectChainModel(FullChainModel):
    """The whole-chain model with effect terms, for :func:`calib.ocpm.fullchain.identify_full`.

    Effect parameters are keys ``"<effect>.<param>"`` (internal units); the passive-limb keys of
    ``overconstraint`` are ordinary geometric keys. With ``gravity`` (default) the machine carries the
    gravity load of the spec's inertia plus each pose's payload (per-pose models), as a real machine
    does: at the reference closure stiffness that moves the targets by up to ~0.013 mm (0.025 mm with
    10 kg) at tilts near 80 deg. Joint-angle effects shift the joint angles (analytic derivatives through
    the motor-angle sensitivities); ``joint_compliance`` adds series springs K = 1/c behind the motors
    (d/dc by a forward difference; for c < 0 the tangent at c = 0 continued linearly);
    ``thermal_expansion`` scales the targets about O by ``1 + alpha dT`` (exact for a uniform expansion
    without gravity: a scaled machine reaches the same joint angles; with gravity the difference is
    ~1e-4 of the gravity deflection). With ``gravity=False`` and no effect keys it is
    :class:`FullChainModel`. Measurements must carry their context (:func:`with_context`).
    """

    #: Relative forward-difference step of the compliance derivative (of max(c, typical c)).
    FD_REL = 1e-2
    #: Stiffness standing in for a rigid drive when the other motor has a spring, N m/rad.
    RIGID = 1e12

    def __init__(self, geom=None, stiffness_ratio: float | None = None, gravity: bool = True):
        from twin.effects import MAX_ITER

        super().__init__(geom, stiffness_ratio)
        self.twin.assembler.max_iter = MAX_ITER
        self.gravity = gravity
        self.effect_x: dict[str, float] = {}
        self._warm: tuple[bytes, np.ndarray] | None = None

    def set_vector(self, keys: list[str], x: np.ndarray, ratio0: float) -> None:
        base = [i for i, k in enumerate(keys) if effect_of_key(k) in (None, "overconstraint")]
        self.effect_x = {k: float(v) for k, v in zip(keys, x) if effect_of_key(k) not in (None, "overconstraint")}
        super().set_vector([keys[i] for i in base], np.asarray(x)[base], ratio0)

    def uses(self, name: str, keys: list[str]) -> bool:
        return any(k in keys or self.effect_x.get(k, 0.0) != 0.0 for k in VOCABULARY[name].keys)

    def targets(self, meas: Measurements) -> np.ndarray:
        """The targets (N, k, 3) mm alone (no derivatives: one solve)."""
        return self.predict_meas(meas, [], derivatives=False)[0]

    def predict_meas(self, meas: Measurements, keys: list[str], derivatives: bool = True):
        N = len(meas)
        offset = np.zeros((N, 2))
        bases: dict[str, np.ndarray] = {}
        for name in DRIVE_EFFECTS:
            if not self.uses(name, keys):
                continue
            B = meas_basis(name, meas)
            if B is None:
                raise ValueError(f"effect '{name}' needs {VOCABULARY[name].needs}")
            bases[name] = B
            offset += B @ np.array([self.effect_x.get(k, 0.0) for k in VOCABULARY[name].keys])
        base_keys = [k for k in keys if effect_of_key(k) in (None, "overconstraint")]
        motor = ["L1.dtheta", "L2.dtheta"]
        cmd = meas.m_cmd_deg + np.rad2deg(offset)
        if self.gravity or self.uses("joint_compliance", keys):
            T, dT, d_c = self._physical(meas, cmd, base_keys + motor, self.uses("joint_compliance", keys),
                                        derivatives)
        else:
            (T, dT), d_c = self.predict(cmd, base_keys + motor if derivatives else None), None
        if not derivatives:
            dtemp = thermal_delta(meas.temp_c) if self.uses("thermal_expansion", keys) else None
            scale = 1.0 if dtemp is None else (1.0 + self.effect_x.get("thermal_expansion.alpha", 0.0) * dtemp)[:, None, None]
            return T * scale, None
        d_motor = dT[..., len(base_keys):]
        dT_all = np.zeros(T.shape + (len(keys),))
        for c, k in enumerate(keys):
            name = effect_of_key(k)
            if name in (None, "overconstraint"):
                dT_all[..., c] = dT[..., base_keys.index(k)]
            elif name in bases:
                p = VOCABULARY[name].keys.index(k)
                dT_all[..., c] = np.einsum("nkij,nj->nki", d_motor, bases[name][:, :, p])
            elif name == "joint_compliance":
                dT_all[..., c] = d_c[..., VOCABULARY[name].keys.index(k)]
        if self.uses("thermal_expansion", keys):
            dtemp = thermal_delta(meas.temp_c)
            if dtemp is None:
                raise ValueError(f"effect 'thermal_expansion' needs {VOCABULARY['thermal_expansion'].needs}")
            scale = (1.0 + self.effect_x.get("thermal_expansion.alpha", 0.0) * dtemp)[:, None, None]
            dT_all = dT_all * scale[..., None]
            if "thermal_expansion.alpha" in keys:
                dT_all[..., keys.index("thermal_expansion.alpha")] = dtemp[:, None, None] * T
            T = T * scale
        return T, dT_all

    # ------------------------------------------------------------------ gravity, payload, springs
    def _physical(self, meas: Measurements, cmd_deg: np.ndarray, keys: list[str], compliant: bool,
                  derivatives: bool = True):
        """Targets and d targets/d keys of the machine under gravity and the poses' payloads; with
        ``compliant`` series springs and d targets/d (c1, c2) (else None). Without ``derivatives`` only
        the targets (and the tangent for c < 0)."""
        from twin.effects import pose_models
        from twin.sensitivity import target_sensitivity

        tw, asm = self.twin, self.twin.assembler
        c = np.array([self.effect_x.get(k, 0.0) for k in VOCABULARY["joint_compliance"].keys])
        h = self.FD_REL * np.maximum(np.abs(c), 1.0 / VOCABULARY["joint_compliance"].typical)
        c0 = np.maximum(c, 0.0) if compliant else np.zeros(2)
        joint = np.deg2rad(cmd_deg) + tw.errors.dtheta[:2]
        asm.gravity = True
        asm.set_models(pose_models(tw, len(meas), payload_kg=meas.payload_kg))
        key = meas.m_cmd_deg.tobytes()                 # warm start across parameter changes
        try:
            state = self._spring_solve(joint, c0, key=key)
            T = state.targets
            dT = target_sensitivity(tw, state.qpos, keys).d_targets if derivatives else None
            d_c = None
            if compliant and (derivatives or np.any(c < 0)):
                d_c = np.stack([(self._spring_solve(joint, c0 + h * np.eye(2)[j], state.qpos).targets - T) / h[j]
                                for j in range(2)], axis=-1)
                T = T + np.einsum("nkip,p->nki", d_c, np.minimum(c, 0.0))   # c < 0: the tangent continued
        finally:
            asm.gravity = False
            asm.set_motor_stiffness(None)
            asm.set_models(None)
        return T, dT, d_c

    def _spring_solve(self, joint: np.ndarray, c: np.ndarray, qpos: np.ndarray | None = None,
                      key: bytes | None = None):
        """Equilibrium with springs K = 1/c (held motors where every c is 0), warm-started from ``qpos``
        or from the last solve of the same campaign (``key``)."""
        asm = self.twin.assembler
        asm.set_motor_stiffness(None if not np.any(c > 0) else np.where(c > 0, 1.0 / np.maximum(c, 1e-300), self.RIGID))
        warm = qpos is None and key is not None
        if warm and self._warm is not None and self._warm[0] == key:
            qpos = self._warm[1]
        state = self._reach(joint, qpos)
        if warm:
            self._warm = (key, state.qpos.copy())
        return state
