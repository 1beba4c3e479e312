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

from functools import lru_cache
from typing import Mapping

import numpy as np

from pmcal.mechanism.machine_spec import MachineSpec
from pmcal.mechanism.planar.geometry import ANGLE_KEYS, ERROR_KEYS, Geometry
from pmcal.mechanism.planar.kinematics import forward, inverse, mm_vector

#: frame-error aliases of the zero offsets (the generic core's ``mK.dzero``)
ALIASES = {"m1.dzero": "dtheta1", "m2.dzero": "dtheta2"}
#: world position (mm) of the seed frame's origin O in ``mjcf/planar_2dof/planar_2dof.xml``
ORIGIN_MM = (0.0, 0.0, 1200.0)


#: the term of eq. 11 each error enters through (index into the stack of :meth:`_position_jacobian`)
_KIND = {"dtheta": 0, "dex": 1, "dey": 2, "dL": 3, "dl": 4, "drM": 5}


@lru_cache(maxsize=64)
def _columns(keys: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Per key: the term of eq. 11 (P,) and the limb it belongs to as a (2, P) 0/1 mask (the MAEMM: none)."""
    kind, limb = np.zeros(len(keys), int), np.zeros((2, len(keys)))
    for j, k in enumerate(keys):
        k = ALIASES.get(k, k)
        if k.startswith("drM"):
            kind[j] = _KIND["drM"]
        elif k.startswith("de"):                                        # de1x: limb 1, term dex
            kind[j], limb[int(k[2]) - 1, j] = _KIND["de" + k[3]], 1.0
        else:                                                           # dtheta1, dL2, dl1
            kind[j], limb[int(k[-1]) - 1, j] = _KIND[k[:-1]], 1.0
    return kind, limb


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
        return ["deg" if ALIASES.get(k, k) in ANGLE_KEYS else "mm" for k in self._keys(keys)]

    def prior_std(self, keys: list[str] | None = None) -> np.ndarray:
        e = self.spec.errors
        return np.array([e.zero_deg if u == "deg" else e.position_mm for u in self.error_units(keys)])

    def _keys(self, keys: list[str] | None) -> list[str]:
        keys = list(keys or self.error_keys)
        unknown = [k for k in keys if ALIASES.get(k, k) not in ERROR_KEYS]
        if unknown:
            raise ValueError(f"unknown error key {unknown[0]!r} of the planar robot ({', '.join(ERROR_KEYS)})")
        return keys

    def _state(self, commands, params: Mapping[str, float] | None):
        """The perturbed geometry, the zero offsets (2,) rad, the real motor angles (N, 2) rad and P (N, 2) mm
        (the last one kept: a fit asks for the readings and their derivatives at the same errors)."""
        commands = np.atleast_2d(np.asarray(commands, float))
        values = {ALIASES.get(k, k): float(v) for k, v in (params or {}).items() if v}
        key = (commands.tobytes(), commands.shape, tuple(sorted(values.items())))
        if self._last is None or self._last[0] != key:
            unknown = set(values) - set(ERROR_KEYS)
            if unknown:
                raise ValueError(f"unknown error key {sorted(unknown)[0]!r} of the planar robot")
            v = np.array([values.get(k, 0.0) for k in ERROR_KEYS])      # Table 2 order, mm and deg
            g = self.geometry
            geom = Geometry(e=g.e + v[2:6].reshape(2, 2), L=g.L + v[6:8], l=g.l + v[8:10], c=g.c + v[10:12],
                            d=g.d, home=g.home)                         # = g.perturbed(Errors(...))
            dtheta = np.deg2rad(v[:2])
            theta = np.deg2rad(commands) + dtheta
            self._last = (key, (geom, dtheta, theta, forward(geom, theta)))
        return self._last[1]

    # ------------------------------------------------------------------ kinematics
    def forward(self, commands, params: Mapping[str, float] | None = None) -> np.ndarray:
        """P (N, 2) mm in the seed frame at commands (N, 2) deg; NaN where the circles do not meet."""
        return self._state(commands, params)[3].copy()

    def inverse(self, task, params: Mapping[str, float] | None = None) -> np.ndarray:
        """Commands (N, 2) deg that put P at ``task`` (N, 2) mm (seed frame) on the machine with ``params``
        (the paper's assembly mode); NaN rows out of reach or outside a motor's range."""
        geom, dtheta, _, _ = self._state(np.zeros((1, 2)), params)
        cmd = np.rad2deg(inverse(geom, np.atleast_2d(np.asarray(task, float))) - dtheta)
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
        geom, _, _, r = self._state(commands, params)
        o1 = np.broadcast_to(geom.c, r.shape)
        return self._world(np.stack([o1, r - geom.d], axis=1))

    def observe(self, commands, params: Mapping[str, float] | None = None) -> np.ndarray:
        """|O1 O2| (N, 1) mm: what the scale reads of each pose before its reference is taken off."""
        geom, _, _, r = self._state(commands, params)
        return np.linalg.norm(mm_vector(geom, r), axis=-1)[:, None]

    # ------------------------------------------------------------------ exact derivatives
    def _position_jacobian(self, commands, params, keys):
        """dP/d errors (N, 2, P) mm per key unit and the perturbed geometry, P at the assembled poses."""
        geom, _, theta, r = self._state(commands, params)
        ux, uy = np.cos(theta), np.sin(theta)                             # (N, 2 limbs)
        wx = (r[:, None, 0] - geom.e[:, 0] - geom.L * ux) / geom.l        # distal unit vectors w_i
        wy = (r[:, None, 1] - geom.e[:, 1] - geom.L * uy) / geom.l
        # row i of eq. 11: w_i^T dP = w_i^T de_i + dL_i w_i^T u_i + L_i w_i^T Q u_i dtheta_i + dl_i
        terms = np.stack([geom.L * (wy * ux - wx * uy) * (np.pi / 180.0), wx, wy, wx * ux + wy * uy,
                          np.ones(theta.shape), np.zeros(theta.shape)], axis=-1)   # (N, 2 limbs, 6 kinds)
        kind, limb = _columns(tuple(keys))
        rows = terms[:, :, kind] * limb                                   # (N, 2, P)
        det = wx[:, 0] * wy[:, 1] - wy[:, 0] * wx[:, 1]                   # W = [w_1^T; w_2^T], 2 x 2 inverse
        dPx = (wy[:, 1, None] * rows[:, 0] - wy[:, 0, None] * rows[:, 1]) / det[:, None]
        dPy = (wx[:, 0, None] * rows[:, 1] - wx[:, 1, None] * rows[:, 0]) / det[:, None]
        return geom, r, np.stack([dPx, dPy], axis=1)

    def jacobian(self, commands, params: Mapping[str, float] | None = None,
                 keys: list[str] | None = None) -> np.ndarray:
        """d targets / d errors (N, 2, 3, P), mm per key unit (world frame)."""
        keys = self._keys(keys)
        _, _, dP = self._position_jacobian(commands, params, keys)
        dO = np.zeros((len(dP), 2, 2, len(keys)))
        dO[:, 1] = dP
        for j, k in enumerate(keys):
            if k in ("drMx", "drMy"):
                dO[:, 0, "xy".index(k[-1]), j] = 1.0                    # O1 = c + drM
        out = np.zeros((len(dP), 2, 3, len(keys)))
        out[:, :, 0], out[:, :, 2] = dO[:, :, 0], dO[:, :, 1]
        return out

    def observation_jacobian(self, commands, params: Mapping[str, float] | None = None,
                             keys: list[str] | None = None) -> np.ndarray:
        """d |O1 O2| / d errors (N, 1, P), mm per key unit: ``lhat^T (dP - d drM)`` (eq. 21 at the real pose)."""
        keys = self._keys(keys)
        geom, r, dP = self._position_jacobian(commands, params, keys)
        lam = mm_vector(geom, r)
        lhat = lam / np.linalg.norm(lam, axis=-1, keepdims=True)
        dlam = dP.copy()
        for j, k in enumerate(keys):
            if k in ("drMx", "drMy"):
                dlam[:, "xy".index(k[-1]), j] -= 1.0
        return np.einsum("ni,nip->np", lhat, dlam)[:, None, :]
