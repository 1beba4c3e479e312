"""The forward-model protocol of a closed-chain machine described as data (an MJCF + a machine.toml).

:mod:`pmcal.calib.closed_chain` (identification, identifiability, CRLB, compensation) reaches the physics
only through an object satisfying :class:`ChainModel`: the twin's
:class:`pmcal.twin.closed_chain.ClosedChainTwin`, or any other simulator of the machine (the tests use
closed forms). calib never imports the twin.

Conventions (every implementation):

- **commands** (N, M): one column per motor ``m1 .. mM``, deg (revolute) or mm (prismatic), as the CSV
  columns ``m1_cmd_deg`` / ``m1_cmd_mm``.
- **targets** (N, K, 3): tracker nest positions, mm, world (base) frame; NaN rows where the machine cannot
  assemble.
- **task** (N, C): task coordinates in the units of their names (``x_mm`` ... ``rz_deg``).
- **params**: a mapping ``{error key: value}`` in the key's unit (:meth:`ChainModel.error_units`: ``"mm"``
  or ``"deg"``); missing keys are 0 (the nominal machine); ``None`` is the nominal machine.
- **jacobian** (N, K, 3, P): d targets (mm) / d params (per the key's unit: mm/mm, mm/deg).
"""

from __future__ import annotations

from typing import Mapping, Protocol, runtime_checkable

import numpy as np

Params = Mapping[str, float] | None


@runtime_checkable
class ChainModel(Protocol):
    """Commands + geometric errors -> tracker targets, their exact derivatives, and inverse kinematics."""

    #: Every geometric error the model knows, in a fixed order (e.g. ``"rod1a.dx"``, ``"m1.dzero"``).
    error_keys: list[str]
    #: Tracker noise (1 sigma per coordinate, mm) of the machine's configuration.
    sigma_mm: float

    def error_units(self, keys: list[str] | None = None) -> list[str]:
        """Unit of each key (``"mm"`` or ``"deg"``), default every :attr:`error_keys`."""

    def prior_std(self, keys: list[str] | None = None) -> np.ndarray:
        """Prior size (1 sigma) of each key in its unit: the Tikhonov scale of identification."""

    def targets(self, commands: np.ndarray, params: Params = None) -> np.ndarray:
        """Nest positions (N, K, 3) mm for commands (N, M); NaN rows where the chain cannot assemble."""

    def jacobian(self, commands: np.ndarray, params: Params = None, keys: list[str] | None = None) -> np.ndarray:
        """d targets / d params (N, K, 3, P) mm per key unit, exact at the assembled configurations."""

    def inverse(self, task: np.ndarray, params: Params = None) -> np.ndarray:
        """Commands (N, M) that put the task site at the task coordinates (N, C); NaN where out of reach."""

    def forward(self, commands: np.ndarray, params: Params = None) -> np.ndarray:
        """Task coordinates (N, C) reached at commands (N, M); NaN where the chain cannot assemble."""
