"""Physical effects in the twin: a "real" machine with drive, thermal and over-constraint effects.

Each effect of the vocabulary (docs/formats.md, docs/effects.md; models and units in :mod:`pmcal.mechanism.ocpm.effects`
and docs/effects.md) is switchable and lives in one of three places:

- **physics** (MuJoCo): gravity always acts (qfrc_bias of the MJCF model's inertia, mjcf/ocpm_2dof) with each pose's payload
  added to the platform at the centre of its top surface (per-pose models); ``joint_compliance`` frees
  the motor joints and ties each to its command with a torsional spring of stiffness K (N m/rad) in
  series (:class:`pmcal.twin.ocpm.assembly.BatchAssembler` motor springs), loaded by gravity and by the internal
  over-constraint forces.
- **geometry per pose** (MuJoCo): ``thermal_expansion`` scales every length of the compiled model (body,
  joint and site positions: links, radii, SS limb, target nests) by ``1 + alpha (temp_c - 20)``, or
  each part (cranks, couplers, strut, base, platform, nests) at its own rate, one model per pose; ``overconstraint`` inserts random passive-limb (L3, L4) errors into the model.
- **joint-angle layer** (outside the physics, where MuJoCo's soft limits model badly): ``backlash``,
  ``encoder_eccentricity`` and ``zero_offset_drift`` shift the joint angle the drive delivers:
  joint = command + dtheta + offset(context).

:class:`EffectTwin` drives such a machine with the context of every pose (approach sign, time,
temperature, payload); :func:`plan_effect_campaign` makes campaigns that vary that context.
Interface units: mm, degrees, degC, kg, s; effect values as in :data:`VOCABULARY`.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import mujoco
import numpy as np

from pmcal.mechanism.ocpm.config import Geometry, default_geometry
from pmcal.mechanism.ocpm.data import Measurements
from pmcal.mechanism.ocpm.effects import (EFFECT_NAMES, THERMAL_GROUPS, drive_basis, frame_motion,
                                          relative_time, thermal_delta)
from pmcal.mechanism.ocpm.params import ErrorSet, random_errors
from pmcal.twin.ocpm.campaign import (CampaignPlan, MeasurementFaults, measure_targets, nominal_commands,
                                  plan_campaign)
from pmcal.twin.ocpm.machine import Twin, TwinState
from pmcal.twin.ocpm.model import MM
from pmcal.twin.tracker import LaserTracker

#: Effects with one value per motor.
PER_MOTOR = ("joint_compliance", "backlash", "encoder_eccentricity", "zero_offset_drift")
#: Parts the twin expands at their own rates: the diagnosis' parts, and the target nests apart from the
#: platform (the diagnosis holds them together).
TWIN_GROUPS = THERMAL_GROUPS + ("nests",)
#: Direction of a ``frame_drift`` given as one rate: a floor slide of (0.15, -0.10, 0.05) mm.
SLIDE_DIRECTION = np.array([0.15, -0.10, 0.05]) / np.linalg.norm([0.15, -0.10, 0.05])
#: Gauss-Newton iteration limit of strained machines (springs, gravity, mm-size closure gaps).
MAX_ITER = 200
#: Angular size of the random passive-limb errors per mm of ``overconstraint`` (0.5 mm <-> 0.1 deg,
#: the tolerance pair of docs/effects.md, ``overconstraint``).
OVERCONSTRAINT_DEG_PER_MM = 0.2


@dataclass
class Effects:
    """Effects switched on in a twin, in interface units (None: off). Drive effects: one value per motor.

    joint_compliance : series spring stiffness K per motor, N m/rad (harmonic drives: 1e4 .. 1e5).
    backlash : half-width of the lost motion per motor, deg (1-2 arcmin of lost motion: 0.008 .. 0.017).
    encoder_eccentricity : first-harmonic amplitude per motor, deg; phase ``encoder_phase_deg``.
    thermal_expansion : linear expansion coefficient alpha, 1/K (steel 12e-6, aluminium 23e-6) of every
        length; or a dict of per-part rates {part: 1/K} over :data:`TWIN_GROUPS` (cranks, couplers,
        strut, base, platform, nests; ``links`` sets cranks, couplers and strut at once), a part left out
        does not expand, the nests take the platform's rate unless given (e.g. aluminium links on a steel
        base: ``{"links": 23e-6, "base": 12e-6, "platform": 12e-6}``).
    zero_offset_drift : zero-offset drift rate per motor at the first pose, deg/h.
    drift_curvature : per motor, deg/h^2: the drift is ``rate t + curvature t^2`` (None: linear).
    overconstraint : size of random passive-limb errors, mm (angles ``OVERCONSTRAINT_DEG_PER_MM`` deg/mm).
    frame_drift : the base moving against the tracker during the campaign: a translation rate of the base
        origin, mm/h, along :data:`SLIDE_DIRECTION`, or (vx, vy, vz mm/h, wx, wy, wz deg/h).
    """

    joint_compliance: tuple[float, float] | None = None
    backlash: tuple[float, float] | None = None
    encoder_eccentricity: tuple[float, float] | None = None
    encoder_phase_deg: tuple[float, float] = (0.0, 0.0)
    thermal_expansion: float | dict[str, float] | None = None
    zero_offset_drift: tuple[float, float] | None = None
    drift_curvature: tuple[float, float] | None = None
    overconstraint: float | None = None
    frame_drift: float | tuple | None = None

    def frame_params(self) -> np.ndarray | None:
        """``frame_drift`` as (vx, vy, vz mm/h, wx, wy, wz rad/h) (None: off)."""
        f = self.frame_drift
        if f is None:
            return None
        if np.ndim(f) == 0:
            return np.concatenate([float(f) * SLIDE_DIRECTION, np.zeros(3)])
        f = np.asarray(f, float)
        return np.concatenate([f[:3], np.deg2rad(f[3:6])])

    def active(self) -> list[str]:
        return [n for n in EFFECT_NAMES if getattr(self, n) is not None]

    def values(self) -> dict[str, float | list[float]]:
        """Interface values of the active effects (JSON-ready)."""
        out = {}
        for n in self.active():
            v = getattr(self, n)
            if isinstance(v, dict):
                out[n] = {k: float(x) for k, x in v.items()}
            else:
                out[n] = [float(x) for x in v] if isinstance(v, tuple) else float(v)
        if self.zero_offset_drift is not None and self.drift_curvature is not None:
            out["drift_curvature"] = [float(x) for x in self.drift_curvature]
        return out

    def group_rates(self) -> dict[str, float] | None:
        """Expansion rate of every part of :data:`TWIN_GROUPS`, 1/K (None without thermal expansion)."""
        t = self.thermal_expansion
        if t is None:
            return None
        if isinstance(t, dict):
            unknown = set(t) - set(TWIN_GROUPS) - {"links"}
            if unknown:
                raise ValueError(f"unknown thermal parts {sorted(unknown)} (known: {', '.join(TWIN_GROUPS)}, links)")
            t = {**{p: t["links"] for p in ("cranks", "couplers", "strut") if "links" in t}, **t}
            out = {g: float(t.get(g, 0.0)) for g in THERMAL_GROUPS}
            return {**out, "nests": float(t.get("nests", out["platform"]))}
        return {g: float(t) for g in TWIN_GROUPS}

    @classmethod
    def from_named(cls, named: list[dict]) -> "Effects":
        """The effects a diagnosis named (its JSON ``named`` list: per-parameter values in interface
        units), for a twin of the diagnosed machine. ``overconstraint`` is geometry (its passive-limb
        keys are in the diagnosed parameters); a drift fitted per pose (no time stamps) is left out."""
        e = cls()
        for item in named:
            name, p = item["name"], {k.split(".", 1)[-1]: v["value"] for k, v in item["params"].items()}
            if name == "joint_compliance":
                e.joint_compliance = (p["c1"], p["c2"])
            elif name == "backlash":
                e.backlash = (p["b1"], p["b2"])
            elif name == "encoder_eccentricity":
                e.encoder_eccentricity = (float(np.hypot(p["s1"], p["c1"])), float(np.hypot(p["s2"], p["c2"])))
                e.encoder_phase_deg = (float(np.rad2deg(np.arctan2(p["c1"], p["s1"]))),
                                       float(np.rad2deg(np.arctan2(p["c2"], p["s2"]))))
            elif name == "thermal_expansion":                      # each group's rate
                e.thermal_expansion = {g: p["alpha"] + p.get(g, 0.0) for g in THERMAL_GROUPS}
            elif name == "frame_drift" and item["unit"] == "mm/h":
                e.frame_drift = tuple(p[k] for k in ("vx", "vy", "vz", "wx", "wy", "wz"))
            elif name == "zero_offset_drift" and item["unit"] == "deg/h":
                e.zero_offset_drift = (p["r1"], p["r2"])
                if "q1" in p:
                    e.drift_curvature = (p["q1"], p["q2"])
        return e


def passive_errors(size_mm: float, seed: int | None) -> dict[str, float]:
    """Random passive-limb errors of the ``overconstraint`` effect: ±size mm, ±0.2 size deg (uniform)."""
    rng = np.random.default_rng(None if seed is None else [seed, 6])
    return random_errors(rng, size_mm, OVERCONSTRAINT_DEG_PER_MM * size_mm, limbs=(3, 4), ss=False,
                         zero_offsets=False)


# ---------------------------------------------------------------------------------------- models
def scale_model(m: mujoco.MjModel, s: float) -> None:
    """Scale every length of a compiled model about the world origin O by ``s`` (in place; call
    ``mj_setConst`` after): body, inertial, joint, site and geom positions, inertias by s^2."""
    m.body_pos[:] *= s
    m.body_ipos[:] *= s
    m.jnt_pos[:] *= s
    m.site_pos[:] *= s
    m.geom_pos[:] *= s
    m.body_inertia[:] *= s * s


def add_payload(m: mujoco.MjModel, body: int, mass_kg: float, point_m: np.ndarray) -> None:
    """Add a point mass to ``body`` at ``point_m`` (body frame): mass, centre of mass and (diagonal)
    inertia by the parallel-axis theorem; the body's inertial frame must be aligned with the body."""
    if mass_kg == 0.0:
        return
    m0, c0 = float(m.body_mass[body]), m.body_ipos[body].copy()
    mt = m0 + mass_kg
    c = (m0 * c0 + mass_kg * point_m) / mt
    d0, dp = c0 - c, point_m - c
    para = lambda mass, d: mass * (np.dot(d, d) - d * d)  # noqa: E731  (diagonal of m (|d|^2 I - d d^T))
    m.body_inertia[body] = m.body_inertia[body] + para(m0, d0) + para(mass_kg, dp)
    m.body_mass[body] = mt
    m.body_ipos[body] = c


def scale_groups(m: mujoco.MjModel, idx, s: np.ndarray) -> None:
    """Scale the parts of a compiled model (in place; call ``mj_setConst`` after) by the factors ``s`` (6,)
    of :data:`TWIN_GROUPS`: cranks (the closure sites S1 at the cranks' ends, the cranks' centres of mass
    and geoms), couplers (the sites S2, the couplers' centres of mass and geoms), strut (the SS length and
    link), base (base-joint positions B_j about O), platform (platform-joint positions A_j, the ball-joint
    offset, the platform's centre of mass and geoms, about the platform origin), nests (target sites about
    the platform origin). Equal factors equal :func:`scale_model`'s positions (inertias are left as they
    are: a 1e-4 change of a gravity load of 0.01 mm)."""
    cranks, couplers, strut, base, plat, nests = (float(v) for v in s)
    ball = m.jnt_pos[idx.jnt_ball].copy()                   # ball-joint offset dc in the platform frame
    ss_tip = m.body_pos[idx.platform] + ball                # (0, 0, h + dh): the SS length
    m.site_pos[idx.site_s1] *= cranks
    m.site_pos[idx.site_s2] *= couplers
    for bodies, f in ((idx.link1, cranks), (idx.link2, couplers), ((idx.ss_link,), strut)):
        for b in bodies:
            m.body_ipos[b] *= f
            m.geom_pos[m.geom_bodyid == b] *= f
    m.body_pos[idx.link1] *= base
    m.body_pos[idx.link2] *= plat
    m.jnt_pos[idx.jnt_ball] = ball * plat
    m.body_ipos[idx.platform] *= plat
    m.geom_pos[m.geom_bodyid == idx.platform] *= plat
    m.site_pos[idx.site_ce] *= plat
    m.body_pos[idx.platform] = ss_tip * strut - ball * plat
    m.site_pos[idx.site_targets] *= nests


def pose_models(twin: Twin, n: int, scale: np.ndarray | None = None,
                payload_kg: np.ndarray | None = None) -> list[mujoco.MjModel] | None:
    """Per-pose copies of ``pmcal.twin.ocpm.model``: lengths scaled by ``scale`` about O ((N,): every length; (N, 4):
    each part of :data:`TWIN_GROUPS`, :func:`scale_groups`) and ``payload_kg`` (N,) added at the
    centre of the platform's top surface. None when every pose would get the twin's own model. Equal
    contexts share one copy."""
    scale = np.ones(n) if scale is None else np.asarray(scale, float)
    scale = scale.reshape(n, -1) if scale.size >= n else np.broadcast_to(scale, (n,)).reshape(n, 1)
    pay = np.zeros(n) if payload_kg is None else np.broadcast_to(np.asarray(payload_kg, float), (n,))
    if np.all(scale == 1.0) and not np.any(pay):
        return None
    base, idx, cache, out = twin.model, twin.index, {}, []
    top = np.array([0.0, 0.0, twin.geom.hs]) * MM
    for s, p in zip(scale, pay):
        key = (tuple(s.tolist()), float(p))
        if key not in cache:
            m = copy.copy(base)
            if s.size == 1:
                scale_model(m, s[0])
            else:
                scale_groups(m, idx, s)
            add_payload(m, idx.platform, p, top * s[4 if s.size > 1 else 0])
            mujoco.mj_setConst(m, twin._scratch)
            cache[key] = m
        out.append(cache[key])
    return out


class EffectTwin:
    """A twin with effects: geometric errors + :class:`Effects`, driven with per-pose context.

    ``errors`` are interface keys (mm, deg) or an ErrorSet; the ``overconstraint`` effect adds random
    passive-limb errors drawn from ``seed`` (kept in :attr:`passive_errors`). ``gravity`` (default on, as
    on a real machine; off only to compare with the geometric :class:`pmcal.twin.ocpm.machine.Twin`).
    """

    def __init__(self, errors: ErrorSet | dict | None = None, effects: Effects | None = None,
                 geom: Geometry | None = None, stiffness_ratio: float | None = None, seed: int | None = 0,
                 gravity: bool = True):
        self.geom = geom or default_geometry()
        self.effects = effects or Effects()
        if isinstance(errors, ErrorSet):
            errors = errors.to_dict()
        params = dict(errors or {})
        self.passive_errors: dict[str, float] = {}
        if self.effects.overconstraint is not None:
            self.passive_errors = passive_errors(self.effects.overconstraint, seed)
            for k, v in self.passive_errors.items():
                params[k] = params.get(k, 0.0) + v
        self.params = params
        self.gravity = gravity or self.effects.joint_compliance is not None
        self.twin = Twin(params, self.geom, stiffness_ratio=stiffness_ratio, gravity=self.gravity)
        # Near the edge of the workspace a strained machine (mm-size gaps at the passive closures) needs
        # more Gauss-Newton iterations than the geometric twin's default, most with gravity and springs.
        self.twin.assembler.max_iter = MAX_ITER
        if self.effects.joint_compliance is not None:
            self.twin.assembler.set_motor_stiffness(self.effects.joint_compliance)

    # ------------------------------------------------------------------ joint-angle layer
    def joint_offsets(self, m_cmd_deg: np.ndarray, approach=None, time_s=None) -> np.ndarray:
        """Offsets (N, 2) rad of the joint-angle layer (backlash, eccentricity, drift) at these poses."""
        e, cmd = self.effects, np.atleast_2d(np.asarray(m_cmd_deg, float))
        off = np.zeros((len(cmd), 2))
        if e.backlash is not None:
            if approach is None:
                raise ValueError("backlash needs the approach direction of every pose")
            off += drive_basis("backlash", cmd, approach=approach) @ np.deg2rad(e.backlash)
        if e.encoder_eccentricity is not None:
            a, ph = np.deg2rad(e.encoder_eccentricity), np.deg2rad(e.encoder_phase_deg)
            x = np.array([a[0] * np.cos(ph[0]), a[0] * np.sin(ph[0]), a[1] * np.cos(ph[1]), a[1] * np.sin(ph[1])])
            off += drive_basis("encoder_eccentricity", cmd) @ x
        if e.zero_offset_drift is not None:
            t, unit = relative_time(time_s, len(cmd))
            if unit != "h":
                raise ValueError("zero_offset_drift needs the time of every pose")
            q = e.drift_curvature or (0.0, 0.0)
            off += drive_basis("zero_offset_drift", cmd, t_rel=t) @ np.deg2rad([*e.zero_offset_drift, *q])
        return off

    # ------------------------------------------------------------------ per-pose models
    def pose_models(self, n: int, temp_c=None, payload_kg=None) -> list[mujoco.MjModel] | None:
        """One compiled model per pose when thermal expansion or payloads make poses differ (else None)."""
        scale = None
        if self.effects.thermal_expansion is not None:
            dtemp = thermal_delta(None if temp_c is None else np.broadcast_to(temp_c, (n,)))
            if dtemp is None:
                raise ValueError("thermal_expansion needs the temperature of every pose")
            t = self.effects.thermal_expansion
            rates = (np.array([self.effects.group_rates()[g] for g in TWIN_GROUPS]) if isinstance(t, dict)
                     else np.array([t]))
            scale = 1.0 + dtemp[:, None] * rates[None, :]
        return pose_models(self.twin, n, scale, payload_kg if self.gravity else None)

    # ------------------------------------------------------------------ driving
    def reach(self, m_cmd_deg: np.ndarray, approach=None, time_s=None, temp_c=None,
              payload_kg=None) -> TwinState:
        """Drive to commands (N, 2) deg with each pose's context; the state's ``joint`` are the true joint
        angles (after zero offsets, the joint-angle layer and the springs' deflection)."""
        cmd = np.atleast_2d(np.asarray(m_cmd_deg, float))
        joint = np.deg2rad(cmd) + self.twin.errors.dtheta[:2] + self.joint_offsets(cmd, approach, time_s)
        asm = self.twin.assembler
        asm.set_models(self.pose_models(len(cmd), temp_c, payload_kg))
        try:
            state = self.twin.reach_joint(joint)
        finally:
            asm.set_models(None)
        state.joint = state.qpos[:, self.twin.index.qadr_base[:2]].copy()
        return state

    def measure(self, plan: CampaignPlan, tracker: LaserTracker, m_cmd_deg: np.ndarray | None = None,
                id_prefix: str = "P", skip_unassembled: bool = False,
                faults: MeasurementFaults | None = None) -> Measurements:
        """Run a campaign (nominal commands unless given) and measure it with ``tracker`` (in its frame
        when it has a pose; with ``faults``: nest offsets, blocked targets and outliers as in
        :func:`pmcal.twin.ocpm.campaign.run_campaign`, their truth in ``extra``).

        A pose whose closed chain does not assemble (a strained machine at the edge of its workspace)
        raises RuntimeError, or with ``skip_unassembled`` is left out of the measurements, as an operator
        skips a pose where the machine binds.
        """
        cmd = nominal_commands(plan.phi_deg, plan.theta_deg, self.geom) if m_cmd_deg is None else m_cmd_deg
        state = self.reach(cmd, plan.approach, plan.time_s, plan.temp_c, plan.payload_kg)
        x_frame = self.effects.frame_params()
        if x_frame is not None:                      # the base moves against the tracker
            t, unit = relative_time(plan.time_s, len(plan))
            if unit != "h":
                raise ValueError("frame_drift needs the time of every pose")
            state.targets = state.targets + frame_motion(state.targets, t, x_frame)
        width = len(str(len(plan)))
        y, extra = measure_targets(state.targets, self.geom.targets, faults, tracker)
        meas = Measurements(
            pose_id=[f"{id_prefix}{i + 1:0{width}d}" for i in range(len(plan))],
            m_cmd_deg=np.asarray(cmd, float), targets=y,
            temp_c=plan.temp_c, time_s=plan.time_s, payload_kg=plan.payload_kg, approach=plan.approach,
            extra=extra)
        if not np.all(state.converged):
            if not skip_unassembled:
                i = int(np.flatnonzero(~state.converged)[0])
                raise RuntimeError(f"pose {i + 1}: the twin did not assemble (closure solve did not converge)")
            meas = meas.subset(np.flatnonzero(state.converged))
        return meas


def motor_torques(errors: ErrorSet, m_cmd_deg: np.ndarray, payload_kg=None, stiffness_ratio: float | None = None,
                  geom: Geometry | None = None) -> np.ndarray:
    """Torques (N, 2) N m the motors exert to hold each pose of a machine under gravity (MJCF
    inertia plus ``payload_kg`` on the platform) with the motors held: ``dE/dq_motor`` of the elastic and gravity
    energy at equilibrium. A series spring K deflects its joint by ``-tau / K`` (first order)."""
    et = EffectTwin(errors, Effects(joint_compliance=(1.0, 1.0)), geom, stiffness_ratio)
    tw = et.twin
    tw.assembler.set_motor_stiffness(None)          # held motors: the gravity-loaded geometric twin
    cmd = np.atleast_2d(np.asarray(m_cmd_deg, float))
    tw.assembler.set_models(et.pose_models(len(cmd), None, payload_kg))
    try:
        state = tw.reach(cmd)
        lin = tw.assembler.linearize(state.qpos)
    finally:
        tw.assembler.set_models(None)
    m = tw.index.dadr_base[:2]
    return np.einsum("nr,nrk->nk", lin.res, lin.J[:, :, m]) + lin.bias[:, m]


# ---------------------------------------------------------------------------------------- campaigns
def plan_effect_campaign(n: int, theta_max_deg: float = 80.0, seed: int | None = 0, *,
                         payloads: tuple[float, ...] = (0.0,), temp_c: tuple[float, ...] | float | None = None,
                         shuffle: bool = True, randomize_approach: bool = True,
                         seconds_per_pose: float = 30.0) -> CampaignPlan:
    """A campaign that shows effects: poses over the cap up to ``theta_max_deg`` in random order
    (``shuffle``), random approach per motor, payload levels spread over all tilts (each level gets every
    ``len(payloads)``-th stratum of tilt), temperature constant (one value) or ramping linearly from the
    first to the last value over the campaign (a warm-up). Times: ``seconds_per_pose`` apart."""
    plan = plan_campaign(n, theta_max_deg, seed, randomize_approach=randomize_approach,
                         seconds_per_pose=seconds_per_pose)
    rng = np.random.default_rng(None if seed is None else [seed, 7])
    levels = np.asarray(payloads, float)
    if levels.size == 0 or np.any(~np.isfinite(levels)) or np.any(levels < 0):
        raise ValueError(f"payloads must be non-negative kg, got {payloads}")
    payload = levels[np.arange(n) % levels.size]
    order = rng.permutation(n) if shuffle else np.arange(n)
    plan.phi_deg, plan.theta_deg = plan.phi_deg[order], plan.theta_deg[order]
    plan.payload_kg = payload[order] if levels.size > 1 or levels[0] != 0 else None
    if temp_c is not None:
        t = np.atleast_1d(np.asarray(temp_c, float))
        if t.size not in (1, 2) or not np.all(np.isfinite(t)):
            raise ValueError(f"temperature must be one value or a (start, end) pair, degC, got {temp_c}")
        plan.temp_c = np.full(n, t[0]) if t.size == 1 else np.linspace(t[0], t[1], n)
    return plan


@dataclass
class HeavyTailedTracker(LaserTracker):
    """A tracker with Student-t noise of ``nu`` degrees of freedom and standard deviation ``sigma_mm``
    (occasional large errors: reflections, a disturbed beam)."""

    nu: float = 3.0

    def measure(self, points_mm: np.ndarray) -> np.ndarray:
        points_mm = np.asarray(points_mm, dtype=float)
        scale = self.sigma_mm * np.sqrt((self.nu - 2.0) / self.nu)
        return points_mm + scale * self.rng.standard_t(self.nu, points_mm.shape)
