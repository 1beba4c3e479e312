"""The planar robot's closed forms as a chain model: the fast path of the generic closed-chain core.

:class:`PlanarChainModel` answers the forward-model protocol of the generic core
(:class:`pmcal.calib.chain_model.ChainModel`: targets, readings, their exact derivatives with respect to
the errors, forward and inverse kinematics) with the paper's closed forms (eq. 1-13) instead of Newton on
the MJCF's loop closures. The generic algorithms (:func:`pmcal.calib.closed_chain.identify_chain`,
:func:`~pmcal.calib.closed_chain.crlb`, :func:`~pmcal.calib.closed_chain.reading_covariance`,
:func:`~pmcal.calib.closed_chain.compensate_targets`) run on it unchanged; the MuJoCo twin of
``mjcf/planar_2dof/chain`` (``NamedModel(ClosedChainTwin(spec), spec.names)``) answers the same calls with
the same numbers (to 1e-9 mm; ``tests/test_planar_chain_model.py``) about 30-500 times slower
(``benchmarks/chain_planar_bench.py``). What is *not* closed-form here stays the twin's: physical effects,
pictures, models with other errors than the paper's twelve.

Errors (keys and units of the machine.toml's ``[names]``, paper Table 2): ``dtheta1``, ``dtheta2`` (deg, the
real motor angle is the command plus the offset), ``de1x``, ``de1y``, ``de2x``, ``de2y`` (mm, the active
joints A1, A2), ``dL1``, ``dL2``, ``dl1``, ``dl2`` (mm, link lengths), ``drMx``, ``drMy`` (mm, the measuring
mechanism's MAEMM, eq. 17). ``m1.dzero`` / ``m2.dzero`` are accepted as the zero offsets' frame-error
names (what :func:`~pmcal.calib.closed_chain.reading_covariance` asks for).

Frames and units: commands (N, 2) deg, the paper's seed angles (counter-clockwise from +x); task
coordinates (N, 2) ``x_mm, y_mm`` in the seed frame O-xy (y up, the platform below the base); targets (the
scale's two ends O1 on the base and O2 on the platform) in the MJCF's world frame, mm: world x = seed x,
world z = seed y, world y = 0, shifted by ``origin_mm`` (the world position of O).

Derivatives are exact at the assembled configuration of the machine with the given errors: the
differential of the loop equation ``r = e_i + L_i u_i + l_i w_i`` there (eq. 11 evaluated on the perturbed
geometry, not the paper's first-order model at the nominal one).

Example
-------
>>> from pmcal.mechanism.machine_spec import MachineSpec
>>> from pmcal.mjcf import machine_dir
>>> model = PlanarChainModel(MachineSpec.load(machine_dir("planar_2dof") / "chain"))
>>> cmd = model.inverse(np.array([[0.0, -707.0]]))
>>> bool(np.allclose(model.forward(cmd), [[0.0, -707.0]]))
True
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

from pmcal.mechanism.machine_spec import MachineSpec
from pmcal.mechanism.planar.geometry import ANGLE_KEYS, ERROR_KEYS, Errors, Geometry
from pmcal.mechanism.planar.kinematics import directions, forward, inverse, mm_vector

#: frame-error aliases of the zero offsets (the generic core's ``mK.dzero``)
ALIASES = {"m1.dzero": "dtheta1", "m2.dzero": "dtheta2"}
#: world position (mm) of the seed frame's origin O in ``mjcf/planar_2dof/planar_2dof.xml``
ORIGIN_MM = (0.0, 0.0, 1200.0)


class PlanarChainModel:
    """The planar robot of paper 003 with its measuring mechanism, in closed form (module docstring).

    Parameters
    ----------
    spec : the machine description (``mjcf/planar_2dof/chain``): motor ranges, tracker noise, the priors of
        ``[errors]``, the reading reference.
    geometry : the nominal geometry (default the paper's, :class:`~pmcal.mechanism.planar.geometry.Geometry`).
    origin_mm : world position (3,) mm of the seed frame's origin O (the targets' offset).
    """

    def __init__(self, spec: MachineSpec, geometry: Geometry | None = None, origin_mm=ORIGIN_MM):
        if len(spec.motors) != 2 or spec.measure != "distance":
            raise ValueError(f"{spec.folder}: the planar closed forms need 2 motors and a distance measurement")
        self.spec = spec
        self.geometry = geometry or Geometry()
        self.origin_mm = np.asarray(origin_mm, float)
        self.error_keys = list(ERROR_KEYS)
        self.sigma_mm = float(spec.sigma_mm)
        self.reading_reference = spec.reference
        self._lo = np.array([m.range[0] for m in spec.motors])
        self._hi = np.array([m.range[1] for m in spec.motors])
        self._last = None

    # ------------------------------------------------------------------ errors
    def error_units(self, keys: list[str] | None = None) -> list[str]:
        return ["deg" if ERROR_KEYS[i] in ANGLE_KEYS else "mm" for i in self._columns(keys)]

    def prior_std(self, keys: list[str] | None = None) -> np.ndarray:
        e = self.spec.errors
        return np.array([e.zero_deg if u == "deg" else e.position_mm for u in self.error_units(keys)])

    def _columns(self, keys: list[str] | None) -> np.ndarray:
        """Indices into :data:`ERROR_KEYS` of ``keys`` (default every error); aliases resolved."""
        try:
            return _INDEX[tuple(keys or ERROR_KEYS)]
        except ValueError:
            unknown = [k for k in keys if ALIASES.get(k, k) not in ERROR_KEYS]
            raise ValueError(f"unknown error key {unknown[0]!r} of the planar robot ({', '.join(ERROR_KEYS)})") \
                from None

    def _state(self, commands, params: Mapping[str, float] | None) -> _Pose:
        """The machine with ``params`` at ``commands`` (N, 2) deg (the last one kept: a fit asks for the
        readings and their derivatives at the same errors)."""
        commands = np.atleast_2d(np.asarray(commands, float))
        values = {ALIASES.get(k, k): float(v) for k, v in (params or {}).items() if v}
        key = (commands.tobytes(), commands.shape, tuple(sorted(values.items())))
        if self._last is None or self._last[0] != key:
            unknown = set(values) - set(ERROR_KEYS)
            if unknown:
                raise ValueError(f"unknown error key {sorted(unknown)[0]!r} of the planar robot")
            err = Errors.from_interface(values)
            geom = self.geometry.perturbed(err)
            theta = np.deg2rad(commands) + err.dtheta
            self._last = (key, _Pose(geom, err.dtheta, theta, forward(geom, theta)))
        return self._last[1]

    # ------------------------------------------------------------------ kinematics
    def forward(self, commands, params: Mapping[str, float] | None = None) -> np.ndarray:
        """P (N, 2) mm in the seed frame at commands (N, 2) deg; NaN where the circles do not meet."""
        return self._state(commands, params).r.copy()

    def inverse(self, task, params: Mapping[str, float] | None = None) -> np.ndarray:
        """Commands (N, 2) deg that put P at ``task`` (N, 2) mm (seed frame) on the machine with ``params``
        (the paper's assembly mode); NaN rows out of reach or outside a motor's range."""
        pose = self._state(np.zeros((1, 2)), params)
        cmd = np.rad2deg(inverse(pose.geom, np.atleast_2d(np.asarray(task, float))) - pose.dtheta)
        cmd = (cmd - self._lo) % 360.0 + self._lo                          # into the range's turn
        bad = ~((cmd >= self._lo) & (cmd <= self._hi)).all(axis=1)
        cmd[bad] = np.nan
        return cmd

    def _world(self, seed_xy: np.ndarray) -> np.ndarray:
        out = np.zeros(seed_xy.shape[:-1] + (3,))
        out[..., 0], out[..., 2] = seed_xy[..., 0], seed_xy[..., 1]
        return out + self.origin_mm

    def targets(self, commands, params: Mapping[str, float] | None = None) -> np.ndarray:
        """The scale's ends O1 (base) and O2 (platform), (N, 2, 3) mm, world frame."""
        pose = self._state(commands, params)
        o1 = np.broadcast_to(pose.geom.c, pose.r.shape)
        return self._world(np.stack([o1, pose.r - pose.geom.d], axis=1))

    def observe(self, commands, params: Mapping[str, float] | None = None) -> np.ndarray:
        """|O1 O2| (N, 1) mm: what the scale reads of each pose before its reference is taken off."""
        return self._state(commands, params).distance()[:, None]

    # ------------------------------------------------------------------ exact derivatives
    def jacobian(self, commands, params: Mapping[str, float] | None = None,
                 keys: list[str] | None = None) -> np.ndarray:
        """d targets / d errors (N, 2, 3, P), mm per key unit (world frame)."""
        cols = self._columns(keys)
        pose = self._state(commands, params)
        out = np.zeros((len(pose.r), 2, 3, len(cols)))
        dP = pose.position_derivatives()[:, :, cols]
        out[:, 1, 0], out[:, 1, 2] = dP[:, 0], dP[:, 1]                   # O2 = P - d
        out[:, 0, 0], out[:, 0, 2] = _DRM[0, cols], _DRM[1, cols]         # O1 = c + drM
        return out

    def observation_jacobian(self, commands, params: Mapping[str, float] | None = None,
                             keys: list[str] | None = None) -> np.ndarray:
        """d |O1 O2| / d errors (N, 1, P), mm per key unit: ``lhat^T (dP - d drM)`` (eq. 21 at the real pose)."""
        return self._state(commands, params).distance_derivatives()[:, None, self._columns(keys)]


#: columns of the MAEMM in the derivative of O1 = c + drM (seed x, y) by error, :data:`ERROR_KEYS` order
_DRM = np.zeros((2, len(ERROR_KEYS)))
_DRM[0, ERROR_KEYS.index("drMx")] = _DRM[1, ERROR_KEYS.index("drMy")] = 1.0


class _IndexOf(dict):
    """keys tuple -> indices into :data:`ERROR_KEYS` (aliases resolved), made on first use."""

    def __missing__(self, keys: tuple[str, ...]) -> np.ndarray:
        idx = np.array([ERROR_KEYS.index(ALIASES.get(k, k)) for k in keys], int)    # ValueError: unknown
        self[keys] = idx
        return idx


_INDEX = _IndexOf()


@dataclass
class _Pose:
    """The machine with one set of errors at N motor commands: its geometry, zero offsets (2,) rad, real
    motor angles theta (N, 2) rad and P (N, 2) mm, and (made on first use) the derivatives of P and of
    |O1 O2| with respect to every error of :data:`ERROR_KEYS`."""

    geom: Geometry
    dtheta: np.ndarray
    theta: np.ndarray
    r: np.ndarray
    _dP: np.ndarray | None = None
    _drho: np.ndarray | None = None

    def distance(self) -> np.ndarray:
        """|O1 O2| (N,) mm."""
        return np.linalg.norm(mm_vector(self.geom, self.r), axis=-1)

    def position_derivatives(self) -> np.ndarray:
        """dP / d errors (N, 2, 12) mm per key unit, :data:`ERROR_KEYS` order (0 for the MAEMM)."""
        if self._dP is None:
            g, theta, r = self.geom, self.theta, self.r
            u, w = directions(g, r, theta)                                # (N, 2 limbs, 2)
            ux, uy, wx, wy = u[..., 0], u[..., 1], w[..., 0], w[..., 1]
            # row i of eq. 11: w_i^T dP = w_i^T de_i + dL_i w_i^T u_i + L_i w_i^T Q u_i dtheta_i + dl_i
            terms = np.stack([g.L * (wy * ux - wx * uy) * (np.pi / 180.0), wx, wy, wx * ux + wy * uy,
                              np.ones(theta.shape)], axis=-1)             # (N, 2 limbs, 5 terms)
            rows = np.zeros((len(r), 2 * len(ERROR_KEYS)))
            rows[:, _LIMB_COLUMNS] = terms.reshape(len(r), -1)
            rows = rows.reshape(len(r), 2, len(ERROR_KEYS))
            det = wx[:, 0] * wy[:, 1] - wy[:, 0] * wx[:, 1]               # W = [w_1^T; w_2^T], 2 x 2 inverse
            self._dP = np.stack([wy[:, 1, None] * rows[:, 0] - wy[:, 0, None] * rows[:, 1],
                                 wx[:, 0, None] * rows[:, 1] - wx[:, 1, None] * rows[:, 0]], axis=1) / \
                det[:, None, None]
        return self._dP

    def distance_derivatives(self) -> np.ndarray:
        """d |O1 O2| / d errors (N, 12) mm per key unit, :data:`ERROR_KEYS` order."""
        if self._drho is None:
            lam = mm_vector(self.geom, self.r)
            lhat = lam / np.linalg.norm(lam, axis=-1, keepdims=True)
            self._drho = np.einsum("ni,nip->np", lhat, self.position_derivatives()) - lhat @ _DRM
        return self._drho


#: where the five terms of eq. 11 of each limb (dtheta_i, de_ix, de_iy, dL_i, dl_i) go in the rows (2, 12) of
#: the two limbs' loop equations, flattened
_LIMB_COLUMNS = np.array([(i - 1) * len(ERROR_KEYS) + ERROR_KEYS.index(n) for i in (1, 2)
                          for n in (f"dtheta{i}", f"de{i}x", f"de{i}y", f"dL{i}", f"dl{i}")])
