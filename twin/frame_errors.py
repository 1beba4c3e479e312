"""Geometric errors of a closed chain as small displacements of its model's frames.

The vocabulary of ``[errors]`` in a machine.toml (``docs/machine_toml.md``): a body frame carries ``dx, dy,
dz`` (mm) and ``drx, dry, drz`` (deg), a translation along and a rotation vector about its *parent's* axes
through the body's frame origin (``body_pos``; joints, geoms and sites written in the body frame move with
it); a site carries ``dx, dy, dz`` (mm) in its body's frame; a motor a zero offset ``mK.dzero`` (deg / mm):
joint position = command - zero + dzero. :class:`FrameErrors` lists the keys, writes values into a compiled
model (``body_pos``, ``body_quat``, ``site_pos``; no recompilation: nothing else of the model depends on
them for kinematics) and differentiates the world positions and orientations of sites with respect to
them at fixed joints, in closed form (a rotation error through the left Jacobian of SO(3), exact at any
error). :class:`pmcal.twin.closed_chain.ClosedChainTwin` adds the joints' response (implicit-function
theorem).

Units: keys in mm / deg; the model in SI.
"""

from __future__ import annotations

from typing import Mapping

import mujoco
import numpy as np

from pmcal.errors import InputError
from pmcal.mechanism.machine_spec import ERROR_COMPONENTS, MachineSpec
from pmcal.mechanism.rotations import rotvec_matrix, so3_left_jacobian

MM = 1e-3                                   # m per mm
DEG = np.pi / 180.0                         # rad per deg
_OBJ = mujoco.mjtObj
# Kinds of error parameters.
BODY_T, BODY_R, SITE_T, ZERO = range(4)


class FrameErrors:
    """The geometric errors of a machine and their effect on a set of sites (see module docstring).

    Parameters
    ----------
    spec : the machine (``[errors]``, motors).
    model : its compiled model; its current frames are the nominal ones.
    points : site ids whose motion :meth:`derivatives` reports (closure sites, targets, task site).
    error_sites : the sites that carry errors under ``frames = "all"``.
    motor_dof, motor_unit : dof address and SI-per-command-unit of each motor (for ``mK.dzero``).
    """

    def __init__(self, spec: MachineSpec, model: mujoco.MjModel, points: np.ndarray, error_sites: list[int],
                 motor_dof: np.ndarray, motor_unit: np.ndarray):
        self.spec, self.model = spec, model
        self.points = np.asarray(points, int)
        self.motor_dof, self.motor_unit = motor_dof, motor_unit
        self._nominal_body_pos = model.body_pos.copy()
        self._nominal_body_quat = model.body_quat.copy()
        self._nominal_site_pos = model.site_pos.copy()
        self._build(error_sites)
        self.x = np.zeros(len(self.keys))
        self.rot: dict[int, np.ndarray] = {}
        self.zero_offset = np.zeros(len(spec.motors))

    def _free_bodies(self) -> set[int]:
        m = self.model
        return {int(m.jnt_bodyid[j]) for j in range(m.njnt) if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE}

    def _build(self, error_sites: list[int]) -> None:
        """Keys from ``spec.errors`` and the table used to apply and differentiate them."""
        m, es = self.model, self.spec.errors
        body_name = lambda b: mujoco.mj_id2name(m, _OBJ.mjOBJ_BODY, b)  # noqa: E731
        site_name = lambda s: mujoco.mj_id2name(m, _OBJ.mjOBJ_SITE, s)  # noqa: E731
        free = self._free_bodies()
        if es.frames == "all":
            bodies = [b for b in range(1, m.nbody) if b not in free]
            sites = list(error_sites)
        else:
            bodies, sites = [], []
            for f in es.frames:
                b = mujoco.mj_name2id(m, _OBJ.mjOBJ_BODY, f)
                if b >= 0:
                    if b in free:
                        raise InputError(f"body {f!r} floats on a free joint: its frame is a coordinate of the "
                                         f"solve, not an error (name its sites instead)",
                                         file=str(self.spec.folder / "machine.toml"), field="errors.frames")
                    bodies.append(b)
                else:
                    sites.append(mujoco.mj_name2id(m, _OBJ.mjOBJ_SITE, f))
        bodies = [b for b in bodies if body_name(b) not in es.exclude]
        sites = [s for s in sites if site_name(s) not in es.exclude]
        keys, table, units, prior = [], [], [], []
        for b in bodies:
            for k, c in enumerate(ERROR_COMPONENTS):
                if c in es.components:
                    rot = k >= 3
                    keys.append(f"{body_name(b)}.{c}")
                    table.append((BODY_R if rot else BODY_T, b, k % 3))
                    units.append("deg" if rot else "mm")
                    prior.append(es.angle_deg if rot else es.position_mm)
        for s in sites:
            for k, c in enumerate(ERROR_COMPONENTS[:3]):
                if c in es.components:
                    keys.append(f"{site_name(s)}.{c}")
                    table.append((SITE_T, s, k))
                    units.append("mm")
                    prior.append(es.position_mm)
        if es.motor_zero:
            for j, mot in enumerate(self.spec.motors):
                keys.append(f"{mot.name}.dzero")
                table.append((ZERO, j, 0))
                units.append(mot.unit)
                prior.append(es.zero_deg if mot.unit == "deg" else es.zero_mm)
        #: every error key, ``"<frame>.<component>"`` and ``"mK.dzero"``
        self.keys = keys
        self._table = table
        self._units = units
        self._prior = np.array(prior, float)
        self._key_index = {k: i for i, k in enumerate(keys)}
        # For each error: which points it moves (the points on its frame's subtree, or the site itself).
        point_body = m.site_bodyid[self.points]
        self._moves = np.zeros((len(keys), len(self.points)), bool)
        for i, (kind, obj, _) in enumerate(table):
            if kind in (BODY_T, BODY_R):
                self._moves[i] = [self._is_ancestor(obj, int(b)) for b in point_body]
            elif kind == SITE_T:
                self._moves[i] = self.points == obj
            else:
                self._moves[i] = True

    def _is_ancestor(self, a: int, b: int) -> bool:
        """Whether body ``a`` is ``b`` or one of its ancestors."""
        while b > 0:
            if b == a:
                return True
            b = int(self.model.body_parentid[b])
        return a == 0

    def units(self, keys: list[str] | None = None) -> list[str]:
        """Unit of each key (``"mm"`` or ``"deg"``); default every key."""
        return [self._units[self.index(k)] for k in (keys or self.keys)]

    def prior_std(self, keys: list[str] | None = None) -> np.ndarray:
        """Prior size (1 sigma) of each key in its unit, from ``[errors]`` of the machine.toml."""
        return np.array([self._prior[self.index(k)] for k in (keys or self.keys)])

    def index(self, key: str) -> int:
        """Position of ``key`` in :attr:`keys`; KeyError naming the machine if unknown."""
        try:
            return self._key_index[key]
        except KeyError:
            raise KeyError(f"unknown error key {key!r} of {self.spec.name} (known: e.g. "
                           f"{', '.join(self.keys[:4])}, ...; twin.error_keys lists all)") from None

    def apply(self, params: Mapping[str, float] | None) -> bool:
        """Write ``{key: value}`` (mm / deg; missing keys 0, None: nominal) into the model; the motor zero
        offsets go to :attr:`zero_offset`. Returns whether anything changed."""
        x = np.zeros(len(self.keys))
        for k, v in (params or {}).items():
            x[self.index(k)] = float(v)
        if np.array_equal(x, self.x):
            return False
        m = self.model
        m.body_pos[:] = self._nominal_body_pos
        m.body_quat[:] = self._nominal_body_quat
        m.site_pos[:] = self._nominal_site_pos
        rot: dict[int, np.ndarray] = {}
        zero = np.zeros(len(self.spec.motors))
        for (kind, obj, k), v in zip(self._table, x):
            if v == 0.0:
                continue
            if kind == BODY_T:
                m.body_pos[obj, k] += v * MM
            elif kind == BODY_R:
                rot.setdefault(obj, np.zeros(3))[k] = v * DEG
            elif kind == SITE_T:
                m.site_pos[obj, k] += v * MM
            else:
                zero[obj] = v
        for b, w in rot.items():
            dq = np.zeros(4)
            mujoco.mju_mat2Quat(dq, rotvec_matrix(w).reshape(9))
            q = np.zeros(4)
            mujoco.mju_mulQuat(q, dq, self._nominal_body_quat[b])
            m.body_quat[b] = q
        self.rot, self.zero_offset, self.x = rot, zero, x
        return True

    def zero_columns(self, idx: list[int]) -> list[tuple[int, int, float]]:
        """The motor zero offsets among the errors ``idx``: (column in ``idx``, motor dof, SI per command
        unit) each. A zero offset moves its motor joint: any row's derivative by it is the row's derivative
        by that dof times the unit."""
        return [(c, int(self.motor_dof[self._table[i][1]]), float(self.motor_unit[self._table[i][1]]))
                for c, i in enumerate(idx) if self._table[i][0] == ZERO]

    def derivatives(self, kin, idx: list[int]) -> tuple[np.ndarray, np.ndarray]:
        """d position (m) and d orientation (rad) of every point per unit of each error ``idx`` at fixed
        joints, (N, npoints, 3, P) each, from the world poses ``kin``
        (:class:`pmcal.twin.closed_chain.Kinematics`)."""
        m = self.model
        N, P = len(kin.qpos), len(idx)
        dP = np.zeros((N, len(self.points), 3, P))
        dW = np.zeros((N, len(self.points), 3, P))
        for c, i in enumerate(idx):
            kind, obj, k = self._table[i]
            mv = self._moves[i]
            dp, dw = dP[..., c], dW[..., c]                                 # views (N, npoints, 3)
            if kind == BODY_T:
                parent = int(m.body_parentid[obj])
                dp[:, mv] = kin.xmat[:, parent, :, k][:, None, :] * MM
            elif kind == BODY_R:
                parent = int(m.body_parentid[obj])
                Rp = kin.xmat[:, parent]                                    # (N, 3, 3)
                w_local = so3_left_jacobian(self.rot.get(obj, np.zeros(3)))[:, k]
                w = np.einsum("nij,j->ni", Rp, w_local) * DEG               # (N, 3) rad per deg
                origin = kin.xpos[:, parent] + np.einsum("nij,j->ni", Rp, m.body_pos[obj])
                dp[:, mv] = np.cross(w[:, None, :], kin.site_xpos[:, mv] - origin[:, None, :])
                dw[:, mv] = w[:, None, :]
            elif kind == SITE_T:
                body = int(m.site_bodyid[obj])
                dp[:, mv] = kin.xmat[:, body, :, k][:, None, :] * MM
            else:
                dof, unit = self.motor_dof[obj], self.motor_unit[obj]
                dp[:] = kin.jacp[..., dof] * unit
                dw[:] = kin.jacr[..., dof] * unit
        return dP, dW
