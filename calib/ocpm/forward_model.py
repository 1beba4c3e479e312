"""The forward-model protocol: how identification, compensation and diagnosis reach the physics.

The algorithms in :mod:`pmcal.calib` never import the MuJoCo twin. They are handed an object that
satisfies :class:`ForwardModel` (as figaroh's calibration reaches its backends): the whole-chain twin
:class:`pmcal.twin.ocpm.forward.FullChainModel`, the twin with effect terms
:class:`pmcal.twin.ocpm.effect_model.EffectChainModel`, or any other simulator of the machine (the tests use
a plain numpy one). The application (:mod:`pmcal.api`) chooses and builds it.

Units: commands in degrees, targets in mm (base frame), parameters in internal units (mm, rad; the key
``log_stiffness_ratio`` is the natural log of the closure stiffness ratio).
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

from pmcal.mechanism.ocpm.config import Geometry
from pmcal.mechanism.ocpm.data import Measurements
from pmcal.mechanism.ocpm.params import ErrorSet


@runtime_checkable
class ForwardModel(Protocol):
    """Commands (deg) + parameters -> target positions (mm) and their parameter derivatives."""

    #: Nominal geometry of the machine (target coordinates on the platform, tracker noise, ...).
    geom: Geometry

    @property
    def stiffness_ratio(self) -> float:
        """Current closure stiffness ratio (actuated and SS closures over passive closures)."""

    def set(self, errors: ErrorSet, stiffness_ratio: float | None = None) -> None:
        """Set the machine's parameters (internal units); the ratio unchanged when None."""

    def set_vector(self, keys: list[str], x: np.ndarray, ratio0: float) -> None:
        """Set the parameters from a vector over ``keys``; ``ratio0`` when the ratio is not among them."""

    def predict(self, m_cmd_deg: np.ndarray, keys: list[str] | None = None
                ) -> tuple[np.ndarray, np.ndarray | None]:
        """Targets (N, k, 3) mm for commands (N, 2) deg and, with ``keys``, d targets / d key
        (N, k, 3, len(keys)). Poses the model cannot assemble are NaN."""

    def predict_meas(self, meas: Measurements, keys: list[str]) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`predict` for a campaign; models with context-dependent terms (time, temperature,
        approach, payload) read them from ``meas``."""


@runtime_checkable
class AimingModel(ForwardModel, Protocol):
    """A :class:`ForwardModel` that solves compensation directly: the commands whose pose points the
    platform normal at target orientations, without an outer Newton on :meth:`predict`."""

    def aim_commands_deg(self, phi_deg: np.ndarray, theta_deg: np.ndarray) -> np.ndarray | None:
        """Commands (N, 2) deg at the current parameters that point the platform normal at the tilt-torsion
        orientations (phi, theta) deg, converged tighter than 1e-10 deg; NaN where out of reach. None when
        the model's current physics has no direct solve (the caller then runs Newton on :meth:`predict`)."""


@runtime_checkable
class EffectModel(ForwardModel, Protocol):
    """A :class:`ForwardModel` that also carries the effect terms of the vocabulary
    (:mod:`pmcal.mechanism.ocpm.effects`): parameter keys ``"<effect>.<param>"`` in internal units, context
    (time, temperature, approach, payload) read from the measurements."""

    def targets(self, meas: Measurements) -> np.ndarray:
        """Targets (N, k, 3) mm of a campaign at the current parameters (no derivatives)."""
