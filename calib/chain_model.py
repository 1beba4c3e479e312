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

from pmcal.mechanism.machine_spec import expand_names

Params = Mapping[str, float] | None


@runtime_checkable
class ChainModel(Protocol):
    """Commands + geometric errors -> tracker targets, their exact derivatives, and inverse kinematics."""

    #: Every geometric error the model knows, in a fixed order (e.g. ``"rod1a.dx"``, ``"m1.dzero"``).
    error_keys: list[str]
    #: Tracker noise (1 sigma per coordinate, mm) of the machine's configuration.
    sigma_mm: float
    #: None when the tracker reads nest positions; ``"previous"`` / ``"first"`` when it reads one distance
    #: per pose relative to a reference pose (a scale): identification then fits the readings
    #: (:func:`pmcal.calib.closed_chain.reading_operator`).
    reading_reference: str | None

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

    def observe(self, commands: np.ndarray, params: Params = None) -> np.ndarray:
        """What the tracker reads of each pose before a reference is taken off, (N, R) mm: the nest
        coordinates (R = 3 K) or one distance (R = 1, :attr:`reading_reference` set). NaN rows where the chain
        cannot assemble."""

    def observation_jacobian(self, commands: np.ndarray, params: Params = None,
                             keys: list[str] | None = None) -> np.ndarray:
        """Exact d :meth:`observe` / d params (N, R, P), mm per key unit."""


class NamedModel:
    """A :class:`ChainModel` whose error keys are a machine's own names of its errors (a paper's, a file
    format's: ``[names]`` of the machine.toml), each moving one or more frame errors of ``model`` together by
    its value (a parallelogram's two bars displaced alike; ``dtheta1`` -> ``m1.dzero``).

    Parameters
    ----------
    model : the frame-error model (:class:`pmcal.twin.closed_chain.ClosedChainTwin`).
    names : name -> the frame-error keys it moves (all in one unit), e.g. ``{"de1x": ("right_proximal.dx",
        "right_passive.dx")}``.

    Every other attribute (``observe``, ``reading_reference``, ``spec``, ...) is the model's; the methods that
    take ``params`` take them by name and pass the frame errors on.

    Example
    -------
    >>> named = NamedModel(twin, twin.spec.names)                         # doctest: +SKIP
    >>> named.targets(cmd, {"dtheta1": 0.5})                              # doctest: +SKIP
    """

    def __init__(self, model: ChainModel, names: Mapping[str, tuple[str, ...]]):
        known = list(model.error_keys)
        self.model = model
        self.names = {n: tuple(ks) for n, ks in names.items()}
        for n, ks in self.names.items():
            missing = [k for k in ks if k not in known]
            if missing:
                raise ValueError(f"name {n!r}: {missing[0]!r} is not an error of the model (list its frame "
                                 f"under [errors] frames)")
            if len(set(model.error_units(list(ks)))) > 1:
                raise ValueError(f"name {n!r} moves errors of different units: {', '.join(ks)}")
        self.error_keys = list(self.names)
        self.sigma_mm = model.sigma_mm
        self._frame_keys = [k for k in known if any(k in ks for ks in self.names.values())]
        pos = {k: i for i, k in enumerate(self._frame_keys)}
        self._M = np.zeros((len(self._frame_keys), len(self.error_keys)))
        for j, ks in enumerate(self.names.values()):
            self._M[[pos[k] for k in ks], j] = 1.0

    def __getattr__(self, attr):
        return getattr(self.model, attr)

    def frame_params(self, params: Params) -> dict[str, float] | None:
        """The frame errors ``{frame key: value}`` of errors given by name (None stays None;
        :func:`pmcal.mechanism.machine_spec.expand_names`)."""
        return None if params is None else expand_names(self.names, params)

    def _columns(self, keys: list[str] | None) -> list[int]:
        return [self.error_keys.index(k) for k in (keys or self.error_keys)]

    def error_units(self, keys: list[str] | None = None) -> list[str]:
        return [self.model.error_units([self.names[k][0]])[0] for k in (keys or self.error_keys)]

    def prior_std(self, keys: list[str] | None = None) -> np.ndarray:
        return np.array([self.model.prior_std([self.names[k][0]])[0] for k in (keys or self.error_keys)])

    def targets(self, commands: np.ndarray, params: Params = None) -> np.ndarray:
        return self.model.targets(commands, self.frame_params(params))

    def observe(self, commands: np.ndarray, params: Params = None) -> np.ndarray:
        return self.model.observe(commands, self.frame_params(params))

    def jacobian(self, commands: np.ndarray, params: Params = None, keys: list[str] | None = None) -> np.ndarray:
        return self.model.jacobian(commands, self.frame_params(params), self._frame_keys) @ \
            self._M[:, self._columns(keys)]

    def observation_jacobian(self, commands: np.ndarray, params: Params = None,
                             keys: list[str] | None = None) -> np.ndarray:
        return self.model.observation_jacobian(commands, self.frame_params(params), self._frame_keys) @ \
            self._M[:, self._columns(keys)]

    def inverse(self, task: np.ndarray, params: Params = None) -> np.ndarray:
        return self.model.inverse(task, self.frame_params(params))

    def forward(self, commands: np.ndarray, params: Params = None) -> np.ndarray:
        return self.model.forward(commands, self.frame_params(params))
