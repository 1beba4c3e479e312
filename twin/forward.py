"""The twin as the whole-chain forward model: commands (deg) + parameters -> targets (mm) and derivatives.

This is the physics the whole-chain identification fits (:func:`pmcal.calib.ocpm.fullchain.identify_full`):
the twin's quasi-static solve (:class:`pmcal.twin.machine.Twin`) with the candidate parameters,
differentiated analytically (:mod:`pmcal.twin.sensitivity`). It satisfies the protocol
:class:`pmcal.calib.forward_model.ForwardModel`, through which identification and compensation reach the
twin without importing it.
"""

from __future__ import annotations

import numpy as np

from pmcal.mechanism.ocpm.config import Geometry, default_geometry
from pmcal.mechanism.ocpm.data import Measurements
from pmcal.mechanism.ocpm.params import ErrorSet, errors_and_ratio
from pmcal.twin.machine import Twin
from pmcal.twin.sensitivity import target_sensitivity


class FullChainModel:
    """Forward model of the whole closed chain: commands (deg) + parameters → targets (mm)."""

    def __init__(self, geom: Geometry | None = None, stiffness_ratio: float | None = None):
        self.geom = geom or default_geometry()
        self.twin = Twin(None, self.geom, stiffness_ratio=stiffness_ratio)
        self._qpos: np.ndarray | None = None
        self._cmd_key: bytes | None = None

    @property
    def stiffness_ratio(self) -> float:
        k = self.twin.stiffness.closure
        return float(k.max() / k.min())

    def set(self, errors: ErrorSet, stiffness_ratio: float | None = None) -> None:
        self.twin.set_errors(errors)
        if stiffness_ratio is not None:
            self.twin.set_stiffness_ratio(stiffness_ratio)

    def solve(self, m_cmd_deg: np.ndarray):
        """Equilibria for commands (N, 2) deg, warm-started from the previous solve of the same commands."""
        m_cmd_deg = np.atleast_2d(np.asarray(m_cmd_deg, float))
        key = m_cmd_deg.tobytes()
        joint = np.deg2rad(m_cmd_deg) + self.twin.errors.dtheta[:2]
        state = self._reach(joint, self._qpos if key == self._cmd_key else None)
        self._qpos, self._cmd_key = state.qpos.copy(), key
        return state

    def _reach(self, joint: np.ndarray, warm: np.ndarray | None):
        """Equilibria at true joint angles (N, 2) rad from the configurations ``warm`` (or the closed-form
        start); a warm start that leaves poses unconverged is redone from the closed form. Poses that still
        do not converge get NaN targets: a parameter set under which the model cannot assemble a measured
        pose predicts nothing there, so a fit rejects that step (scipy's trust region shrinks on non-finite
        residuals) instead of taking a half-solved pose at face value."""
        state = self.twin.reach_joint(joint, qpos=warm)
        if warm is not None and not state.converged.all():
            state = self.twin.reach_joint(joint)
        state.targets[~state.converged] = np.nan
        return state

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
        return state.targets, target_sensitivity(self.twin, state.qpos, keys).d_targets
