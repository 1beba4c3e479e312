"""The twin as the whole-chain forward model: commands (deg) + parameters -> targets (mm) and derivatives.

This is the physics the whole-chain identification fits (:func:`pmcal.calib.ocpm.fullchain.identify_full`):
the twin's quasi-static solve (:class:`pmcal.twin.ocpm.machine.Twin`) with the candidate parameters,
differentiated analytically (:mod:`pmcal.twin.ocpm.sensitivity`). It satisfies the protocol
:class:`pmcal.calib.ocpm.forward_model.ForwardModel`, through which identification and compensation reach the
twin without importing it.
"""

from __future__ import annotations

import numpy as np

from pmcal.mechanism.ocpm.config import Geometry, default_geometry
from pmcal.mechanism.ocpm.data import Measurements
from pmcal.mechanism.ocpm.params import ErrorSet, errors_and_ratio
from pmcal.twin.ocpm.aiming import aim
from pmcal.twin.ocpm.assembly import integrate_pos
from pmcal.twin.ocpm.machine import Twin
from pmcal.twin.ocpm.sensitivity import target_sensitivity


class FullChainModel:
    """Forward model of the whole closed chain: commands (deg) + parameters → targets (mm)."""

    def __init__(self, geom: Geometry | None = None, stiffness_ratio: float | None = None):
        self.geom = geom or default_geometry()
        self.twin = Twin(None, self.geom, stiffness_ratio=stiffness_ratio)
        self._qpos: np.ndarray | None = None
        self._cmd: np.ndarray | None = None
        self._tangent: np.ndarray | None = None     # d qpos_free / d commands (rad/rad) of the last solve
        self._free: np.ndarray | None = None
        self._cmd_key: bytes | None = None

    @property
    def stiffness_ratio(self) -> float:
        k = self.twin.stiffness.closure
        return float(k.max() / k.min())

    def set(self, errors: ErrorSet, stiffness_ratio: float | None = None) -> None:
        self.twin.set_errors(errors)
        if stiffness_ratio is not None:
            self.twin.set_stiffness_ratio(stiffness_ratio)

    #: A pose starts from the last solve's equilibrium at the nearest command within this distance
    #: (deg, largest of the two motors); farther poses start from the closed-form guess.
    WARM_RADIUS_DEG = 2.0
    _MOTOR_KEYS = ("L1.dtheta", "L2.dtheta")          # act exactly like the commands

    def solve(self, m_cmd_deg: np.ndarray):
        """Equilibria for commands (N, 2) deg, each pose warm-started from the previous solve's equilibrium
        at the nearest command (the same command when a fit re-solves its campaign; the previous Newton
        iterate when compensation steps the commands) within :data:`WARM_RADIUS_DEG`. ``_cmd_key = None``
        forgets the previous solve."""
        m_cmd_deg = np.atleast_2d(np.asarray(m_cmd_deg, float))
        key = m_cmd_deg.tobytes()
        joint = np.deg2rad(m_cmd_deg) + self.twin.errors.dtheta[:2]
        state = self._reach(joint, self._warm_start(m_cmd_deg, key))
        ok = state.converged
        self._qpos, self._cmd, self._cmd_key = state.qpos[ok].copy(), m_cmd_deg[ok].copy(), key
        self._tangent = None                              # set by predict with the motor keys
        return state

    def _warm_start(self, m_cmd_deg: np.ndarray, key: bytes) -> np.ndarray | None:
        """Start configurations (N, nq) from the last solve (rows NaN: no neighbour), or None."""
        if self._cmd_key is None or self._qpos is None or not len(self._qpos):
            return None
        if key == self._cmd_key and len(self._cmd) == len(m_cmd_deg):
            return self._qpos
        from scipy.spatial import cKDTree

        dist, i = cKDTree(self._cmd).query(m_cmd_deg, p=np.inf, distance_upper_bound=self.WARM_RADIUS_DEG)
        near = np.isfinite(dist)
        if not near.any():
            return None
        warm = np.full((len(m_cmd_deg), self._qpos.shape[1]), np.nan)
        j = i[near]
        q = self._qpos[j].copy()
        if self._tangent is not None:                     # first-order predictor along the commands
            dv = np.zeros((len(j), self.twin.model.nv))
            dv[:, self._free] = np.einsum("nfc,nc->nf", self._tangent[j], np.deg2rad(m_cmd_deg[near] - self._cmd[j]))
            integrate_pos(self.twin.model, q, dv)
        warm[near] = q
        return warm

    def _reach(self, joint: np.ndarray, warm: np.ndarray | None):
        """Equilibria at true joint angles (N, 2) rad from the configurations ``warm`` (rows of NaN, or
        None: the closed-form start); warm-started poses left unconverged are redone from the closed form.
        Poses that still do not converge, or whose closed-form start lies outside the workspace, get NaN
        targets: a parameter set under which the model cannot assemble a measured pose predicts nothing
        there, so a fit rejects that step (scipy's trust region shrinks on non-finite residuals) instead
        of taking a half-solved pose at face value."""
        if warm is not None:
            warm = np.array(warm, dtype=float, copy=True)
            cold = ~np.isfinite(warm).all(axis=1)
            if cold.any():
                warm[cold] = self.twin.initial_qpos(joint[cold], outside="nan")
        state = self.twin.reach_joint(joint, qpos=warm, outside="nan")
        if warm is not None and not state.converged.all():
            redo = ~state.converged
            again = self.twin.reach_joint(joint[redo], outside="nan")
            self.twin.merge_state(state, again, redo)
        state.targets[~state.converged] = np.nan
        return state

    def aim_commands_deg(self, phi_deg, theta_deg) -> np.ndarray | None:
        """Commands (N, 2) deg whose equilibrium points the platform normal at (phi, theta) deg at the
        current parameters (:func:`pmcal.twin.ocpm.aiming.aim`: equilibrium and pointing solved together,
        estimated error below 1e-12 rad); NaN where out of reach. None while the twin carries gravity or motor
        springs (the caller then runs Newton on :meth:`predict`). The equilibria become the warm start
        of the next :meth:`solve`."""
        asm = self.twin.assembler
        if asm.gravity or asm.motor_stiffness is not None:
            return None
        phi, theta = np.deg2rad(np.atleast_1d(phi_deg)), np.deg2rad(np.atleast_1d(theta_deg))
        joint, qpos = aim(self.twin, phi, theta)
        cmd = np.rad2deg(joint - self.twin.errors.dtheta[:2])
        ok = np.isfinite(cmd).all(axis=1)
        self._qpos, self._cmd, self._cmd_key, self._tangent = qpos[ok], cmd[ok], cmd[ok].tobytes(), None
        return cmd

    def set_vector(self, keys: list[str], x: np.ndarray, ratio0: float) -> None:
        """Set the model from a parameter vector (internal units); ``ratio0`` if the ratio is not in it."""
        e, log_ratio = errors_and_ratio(keys, x)
        self.set(e, np.exp(log_ratio) if log_ratio is not None else ratio0)

    def predict_meas(self, meas: Measurements, keys: list[str]):
        """Targets of a campaign and their derivatives w.r.t. ``keys`` (the hook :func:`identify_full` calls;
        subclasses with context-dependent terms override it together with :meth:`set_vector`)."""
        return self.predict(meas.m_cmd_deg, keys)

    def predict(self, m_cmd_deg: np.ndarray, keys: list[str] | None = None):
        """Targets (N, k, 3) mm and, with ``keys``, their derivatives (N, k, 3, len(keys))."""
        state = self.solve(m_cmd_deg)
        if keys is None:
            return state.targets, None
        ok = np.isfinite(state.qpos).all(axis=1)           # poses outside the workspace: NaN
        dT = np.full(state.targets.shape + (len(keys),), np.nan)
        if ok.any():
            sens = target_sensitivity(self.twin, state.qpos if ok.all() else state.qpos[ok], keys)
            dT[ok] = sens.d_targets
            if all(k in keys for k in self._MOTOR_KEYS):  # keep the tangent along the commands
                tangent = np.full((len(ok), len(sens.free), 2), np.nan)
                tangent[ok] = sens.dq[..., [keys.index(k) for k in self._MOTOR_KEYS]]
                self._tangent, self._free = tangent[state.converged], sens.free
        return state.targets, dT
