"""The whole-chain forward model with the effect terms of the vocabulary (:mod:`pmcal.mechanism.ocpm.effects`).

It implements :class:`pmcal.calib.ocpm.forward_model.ForwardModel` with effect parameters; the diagnosis
(:mod:`pmcal.calib.ocpm.diagnose`) fits it. Units: mm, rad, hours, N m, kg, degrees Celsius.
"""

from __future__ import annotations

import numpy as np

from pmcal.mechanism.ocpm.data import Measurements
from pmcal.mechanism.ocpm.effects import (DRIVE_EFFECTS, T_REL, THERMAL_GROUPS, VOCABULARY, effect_of_key,
                                          frame_basis, frame_motion, meas_basis, thermal_delta,
                                          thermal_group_weights)
from pmcal.mechanism.rigid import fit_pose
from pmcal.twin.ocpm.forward import FullChainModel


class EffectChainModel(FullChainModel):
    """The whole-chain model with effect terms, for :func:`pmcal.calib.ocpm.fullchain.identify_full`.

    Effect parameters are keys ``"<effect>.<param>"`` (internal units); the passive-limb keys of
    ``overconstraint`` are ordinary geometric keys. With ``gravity`` (default) the machine carries the
    gravity load of the MJCF model's inertia plus each pose's payload (per-pose models), as a real machine
    does: at the reference closure stiffness that moves the targets by up to ~0.013 mm (0.025 mm with
    10 kg) at tilts near 80 deg. Joint-angle effects shift the joint angles (analytic derivatives through
    the motor-angle sensitivities); ``joint_compliance`` adds series springs K = 1/c behind the motors
    (d/dc by a forward difference; for c < 0 the tangent at c = 0 continued linearly);
    ``thermal_expansion`` scales the targets about O by ``1 + alpha dT`` (exact for a uniform expansion
    without gravity: a scaled machine reaches the same joint angles; with gravity the difference is
    ~1e-4 of the gravity deflection) and expands each part g (cranks, couplers, strut, base, platform) by a
    further ``delta_g dT`` through the targets' sensitivities to the keys the group's lengths change
    (first order: 23e-6/K over 10 K is 0.07 mm on a 317 mm link, the second-order term ~1e-6 mm); the
    nests move by ``delta dT R t_k`` about the platform origin. With ``gravity=False`` and no effect keys it is
    :class:`FullChainModel`. Measurements must carry their context (:func:`with_context`).
    """

    #: Relative forward-difference step of the compliance derivative (of max(c, typical c)).
    FD_REL = 1e-2
    #: Stiffness standing in for a rigid drive when the other motor has a spring, N m/rad.
    RIGID = 1e12

    def __init__(self, geom=None, stiffness_ratio: float | None = None, gravity: bool = True):
        from pmcal.twin.ocpm.effects import MAX_ITER

        super().__init__(geom, stiffness_ratio)
        self.twin.assembler.max_iter = MAX_ITER
        self.twin.assembler.secant_steps = True     # reproduce the strained poses another machine measured
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
        groups = self._thermal_groups(keys)
        weights = thermal_group_weights(self.geom, self.twin.errors.to_dict()) if groups else {}
        extra = list(dict.fromkeys(k for g in groups for k, _ in weights[g]
                                   if k not in base_keys and k not in motor))
        sens = base_keys + motor + extra
        want = derivatives or bool(groups)
        cmd = meas.m_cmd_deg + np.rad2deg(offset)
        if self.gravity or self.uses("joint_compliance", keys):
            T, dT, d_c = self._physical(meas, cmd, sens, self.uses("joint_compliance", keys), want)
        else:
            (T, dT), d_c = self.predict(cmd, sens if want else None), None
        dtemp = None
        if self.uses("thermal_expansion", keys):
            dtemp = thermal_delta(meas.temp_c)
            if dtemp is None:
                raise ValueError(f"effect 'thermal_expansion' needs {VOCABULARY['thermal_expansion'].needs}")
        d_group = {g: self._group_signature(g, T, dT, sens, weights) * dtemp[:, None, None] for g in groups}
        T = T + sum((self.effect_x.get(f"thermal_expansion.{g}", 0.0) * d for g, d in d_group.items()),
                    np.zeros_like(T))
        scale = 1.0 if dtemp is None else (1.0 + self.effect_x.get("thermal_expansion.alpha", 0.0) * dtemp)[:, None, None]
        frame = self.uses("frame_drift", keys)
        x_frame = np.array([self.effect_x.get(k, 0.0) for k in VOCABULARY["frame_drift"].keys])
        if frame and T_REL not in meas.extra:
            raise ValueError(f"effect 'frame_drift' needs {VOCABULARY['frame_drift'].needs}")
        if not derivatives:
            T = T * scale
            return (T + frame_motion(T, meas.extra[T_REL], x_frame) if frame else T), None
        d_motor = dT[..., len(base_keys):len(base_keys) + 2]
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
            elif k.split(".", 1)[1] in d_group:
                dT_all[..., c] = d_group[k.split(".", 1)[1]]
        if dtemp is not None:
            dT_all = dT_all * scale[..., None]
            if "thermal_expansion.alpha" in keys:
                dT_all[..., keys.index("thermal_expansion.alpha")] = dtemp[:, None, None] * T
            T = T * scale
        if frame:        # a rigid motion of the frame; its first-order effect on the other columns is dropped
            B = frame_basis(T, meas.extra[T_REL])
            for p, k in enumerate(VOCABULARY["frame_drift"].keys):
                if k in keys:
                    dT_all[..., keys.index(k)] = B[..., p]
            T = T + frame_motion(T, meas.extra[T_REL], x_frame)
        return T, dT_all

    def _thermal_groups(self, keys: list[str]) -> list[str]:
        """The length groups whose own expansion rate is fitted (in ``keys``) or set (non-zero)."""
        return [g for g in THERMAL_GROUPS if f"thermal_expansion.{g}" in keys
                or self.effect_x.get(f"thermal_expansion.{g}", 0.0) != 0.0]

    def _group_signature(self, group: str, T: np.ndarray, dT: np.ndarray, sens: list[str],
                         weights: dict[str, list[tuple[str, float]]]) -> np.ndarray:
        """d targets / d (strain of ``group``), (N, k, 3) mm: the keys' sensitivities weighted by the lengths
        they change (first order); the platform's also carries its nests: each target's position about
        the platform origin, R t_k."""
        out = sum(w * dT[..., sens.index(k)] for k, w in weights[group])
        if group == "platform":
            X = self.geom.targets[: T.shape[1]]
            _, R, _ = fit_pose(T, X)
            out = out + np.einsum("nij,kj->nki", R, X)
        return out

    # ------------------------------------------------------------------ gravity, payload, springs
    def _physical(self, meas: Measurements, cmd_deg: np.ndarray, keys: list[str], compliant: bool,
                  derivatives: bool = True):
        """Targets and d targets/d keys of the machine under gravity and the poses' payloads; with
        ``compliant`` series springs and d targets/d (c1, c2) (else None). Without ``derivatives`` only
        the targets (and the tangent for c < 0)."""
        from pmcal.twin.ocpm.effects import pose_models
        from pmcal.twin.ocpm.sensitivity import target_sensitivity

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
