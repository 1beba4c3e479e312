"""A machine folder simulated without pmcal: plain MuJoCo for the kinematics, scipy for the loops.

Read from the folder with ``tomllib`` and MuJoCo alone: the motors (``[[motors]] joint``, ``zero``; a hinge
commanded in deg, a slide in mm), the tracker nests, the task site and its coordinates, the error sizes of
``[errors]``.

**Errors, this simulator's own parameterisation** (not pmcal's frame errors), written into the model's
``MjSpec`` before it is compiled:

- every body but the world's and a free-floating one: ``<body>/t<x|y|z>`` (mm) added to its ``pos`` in the
  parent frame, and ``<body>/e<x|y|z>`` (deg) intrinsic x-y-z Euler angles composed on the right of its
  ``quat`` (a rotation about the body's own axes, where pmcal's rotates about the parent's);
- every site a site-based loop closure uses: ``<site>/t<x|y|z>`` (mm) added to its ``pos``;
- every motor: ``<joint>/zero`` (deg or mm), joint position = (command - zero + offset) in SI.

Random errors are drawn normal with the sizes of ``[errors]`` (``position_mm``, ``angle_deg``, ``zero_deg``
/ ``zero_mm``; pmcal's defaults 1.0, 0.3, 1.0 when absent).

**Loops, this simulator's own solver**: the unknowns are the tangent coordinates of every joint that is not
a motor; the residual is, per ``connect`` equality, the world distance vector (mm) between its two anchor
points (two sites, or body1's ``anchor`` and the point of body2 MuJoCo's compiler placed there); scipy
``least_squares`` (trust-region reflective, finite-difference Jacobian) from the previous solution, the
motors moved from the ``home`` configuration (the keyframe, else the default configuration) in sub-steps
of at most 10 % of their ranges. An over-constrained loop (a planar loop closed by a 3-D ``connect``
carrying an out-of-plane error, a parallelogram's second rod, a closing hinge made of two ``connect``s)
cannot close exactly: the least-squares solution is kept when the joints can reduce its gap no further
(the gap's part in the range of the closure Jacobian below 1e-5 mm) and the gap left, taken up by the
joints' play, is below :data:`PLAY` mm or :data:`PLAY_FRACTION` of the machine's size, the larger. A site-based ``weld``: the distance vector (mm) and the rotation vector
between the two site frames (mrad); body-based welds are not simulated (no corpus model has one). A ``joint`` equality
(coupled drivers) is a residual row ``q1 - q1_0 - poly(q2 - q2_0)`` (rad).

Units: mm and degrees at the interface, SI inside MuJoCo.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

import mujoco
import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

POSITION = ("x_mm", "y_mm", "z_mm")
SUBSTEP = 0.1
PLAY = 10.0         # mm: the largest gap an over-constrained loop may leave to the joints' play (random
#                     0.1 deg tilts over the five-bar's 0.9 m loop leave up to 6 mm out of its plane) ...
PLAY_FRACTION = 0.01  # ... or this fraction of the machine's size (its bodies' extent at home), if larger: a
#                     4 m four-bar's 0.3 deg axis tilts leave up to 13 mm


class SimMachine:
    """The machine of ``folder`` with this simulator's errors ``errors`` ({key: value}, mm / deg; missing
    keys 0)."""

    def __init__(self, folder: str | Path, errors: dict[str, float] | None = None):
        self.folder = Path(folder)
        doc = tomllib.loads((self.folder / "machine.toml").read_text())
        mach = doc.get("machine", {})
        self.model_path = self.folder / mach.get("model", f"{mach.get('name', self.folder.name)}.xml")
        self.motors = [m["joint"] for m in doc["motors"]]
        self.zero = np.array([float(m.get("zero", 0.0)) for m in doc["motors"]])
        self.range = np.array([m["range"] for m in doc["motors"]], float)
        self.targets = list(doc["tracker"]["targets"])
        self.task_site = doc["task"]["site"]
        self.coordinates = list(doc["task"]["coordinates"])
        err = doc.get("errors", {})
        self.sizes = {"t": float(err.get("position_mm", 1.0)), "e": float(err.get("angle_deg", 0.3)),
                      "zero_deg": float(err.get("zero_deg", 1.0)), "zero_mm": float(err.get("zero_mm", 1.0))}
        self.errors = dict(errors or {})
        nominal = mujoco.MjModel.from_xml_path(str(self.model_path))
        self._keys, self._size = self._error_keys(nominal)
        self.model = self._compile()
        self.data = mujoco.MjData(self.model)
        m = self.model
        jid = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, j) for j in self.motors]
        self.hinge = np.array([m.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE for j in jid])
        self.motor_q = np.array([m.jnt_qposadr[j] for j in jid])
        motor_dof = {int(m.jnt_dofadr[j]) for j in jid}
        self.free_dofs = np.array([d for d in range(m.nv) if d not in motor_dof])
        home = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_KEY, mach.get("home", "home"))
        self.home = m.key_qpos[home].copy() if home >= 0 else m.qpos0.copy()
        self.home_cmd = self.commands_of(self.home)
        self.data.qpos[:] = self.home
        mujoco.mj_kinematics(m, self.data)
        extent = np.ptp(self.data.xpos[1:], axis=0) * 1e3 if m.nbody > 1 else np.zeros(3)
        self.play = max(PLAY, PLAY_FRACTION * float(np.linalg.norm(extent)))     # mm
        self.home = self._close(self.home)
        self.target_ids = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, t) for t in self.targets]
        self.task_id = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, self.task_site)

    # ------------------------------------------------------------------ errors
    def _error_keys(self, m: mujoco.MjModel) -> tuple[list[str], list[float]]:
        keys, size = [], []
        free_bodies = {int(m.jnt_bodyid[j]) for j in range(m.njnt) if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE}
        for b in range(1, m.nbody):
            name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, b)
            if name and b not in free_bodies:
                keys += [f"{name}/t{a}" for a in "xyz"] + [f"{name}/e{a}" for a in "xyz"]
                size += [self.sizes["t"]] * 3 + [self.sizes["e"]] * 3
        for e in range(m.neq):
            if int(m.eq_type[e]) in (int(mujoco.mjtEq.mjEQ_CONNECT), int(mujoco.mjtEq.mjEQ_WELD)) \
                    and m.eq_objtype[e] == mujoco.mjtObj.mjOBJ_SITE:
                for s in (m.eq_obj1id[e], m.eq_obj2id[e]):
                    name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_SITE, int(s))
                    if f"{name}/tx" not in keys:
                        keys += [f"{name}/t{a}" for a in "xyz"]
                        size += [self.sizes["t"]] * 3
        for j in self.motors:
            hinge = m.jnt_type[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, j)] == mujoco.mjtJoint.mjJNT_HINGE
            keys.append(f"{j}/zero")
            size.append(self.sizes["zero_deg" if hinge else "zero_mm"])
        return keys, size

    @property
    def error_keys(self) -> list[str]:
        return list(self._keys)

    def random_errors(self, rng: np.random.Generator) -> dict[str, float]:
        """Errors of the toml's sizes, drawn normal (mm / deg)."""
        return {k: float(v) for k, v in zip(self._keys, rng.normal(0.0, self._size))}

    def _compile(self) -> mujoco.MjModel:
        spec = mujoco.MjSpec.from_file(str(self.model_path))
        by_frame: dict[str, dict[str, float]] = {}
        for k, v in self.errors.items():
            frame, _, comp = k.rpartition("/")
            by_frame.setdefault(frame, {})[comp] = float(v)
        for frame, comps in by_frame.items():
            if "zero" in comps:
                continue
            t = np.array([comps.get(f"t{a}", 0.0) for a in "xyz"]) / 1000.0
            body = spec.body(frame)
            if body is not None:
                body.pos = np.asarray(body.pos) + t
                e = [comps.get(f"e{a}", 0.0) for a in "xyz"]
                if any(e):
                    q = np.asarray(body.quat, float)
                    r = Rotation.from_quat(q[[1, 2, 3, 0]]) * Rotation.from_euler("XYZ", e, degrees=True)
                    body.quat = r.as_quat()[[3, 0, 1, 2]]
                continue
            site = spec.site(frame)
            site.pos = np.asarray(site.pos) + t
        return spec.compile()

    # ------------------------------------------------------------------ kinematics
    def _joint_of(self, commands: np.ndarray) -> np.ndarray:
        off = np.array([self.errors.get(f"{j}/zero", 0.0) for j in self.motors])
        val = np.asarray(commands, float) - self.zero + off
        return np.where(self.hinge, np.deg2rad(val), val / 1000.0)

    def commands_of(self, qpos: np.ndarray) -> np.ndarray:
        """The commands (M,) at which the motor joints sit at ``qpos`` (without zero offsets)."""
        q = qpos[self.motor_q]
        return np.where(self.hinge, np.rad2deg(q), q * 1000.0) + self.zero

    def _gaps(self, qpos: np.ndarray) -> np.ndarray:
        m, d = self.model, self.data
        d.qpos[:] = qpos
        mujoco.mj_kinematics(m, d)
        out = []
        for e in range(m.neq):
            if not m.eq_active0[e]:
                continue
            kind, data = m.eq_type[e], m.eq_data[e]
            if kind == mujoco.mjtEq.mjEQ_CONNECT:
                if m.eq_objtype[e] == mujoco.mjtObj.mjOBJ_SITE:
                    p1, p2 = d.site_xpos[m.eq_obj1id[e]], d.site_xpos[m.eq_obj2id[e]]
                else:
                    b1, b2 = m.eq_obj1id[e], m.eq_obj2id[e]
                    p1 = d.xpos[b1] + d.xmat[b1].reshape(3, 3) @ data[0:3]
                    p2 = d.xpos[b2] + d.xmat[b2].reshape(3, 3) @ data[3:6]
                out.append((p1 - p2) * 1000.0)
            elif kind == mujoco.mjtEq.mjEQ_WELD and m.eq_objtype[e] == mujoco.mjtObj.mjOBJ_SITE:
                a, b = m.eq_obj1id[e], m.eq_obj2id[e]
                rot = Rotation.from_matrix(d.site_xmat[a].reshape(3, 3).T @ d.site_xmat[b].reshape(3, 3))
                out.append((d.site_xpos[a] - d.site_xpos[b]) * 1000.0)
                out.append(rot.as_rotvec() * 1000.0)
            elif kind == mujoco.mjtEq.mjEQ_JOINT:
                j1, j2 = m.eq_obj1id[e], m.eq_obj2id[e]
                q1 = qpos[m.jnt_qposadr[j1]] - m.qpos0[m.jnt_qposadr[j1]]
                x = qpos[m.jnt_qposadr[j2]] - m.qpos0[m.jnt_qposadr[j2]] if j2 >= 0 else 0.0
                out.append(np.array([q1 - sum(data[k] * x ** k for k in range(5))]))
            else:
                raise NotImplementedError("this simulator closes connect, site-based weld and joint equalities only")
        return np.concatenate(out)

    def _close(self, q0: np.ndarray) -> np.ndarray:
        m = self.model

        def at(x):
            q = q0.copy()
            dv = np.zeros(m.nv)
            dv[self.free_dofs] = x
            mujoco.mj_integratePos(m, q, dv, 1.0)
            return q

        sol = least_squares(lambda x: self._gaps(at(x)), np.zeros(len(self.free_dofs)), method="trf",
                            xtol=1e-13, ftol=1e-13, gtol=1e-13, max_nfev=100)
        q = at(sol.x)
        gap = self._gaps(q)
        if np.max(np.abs(gap)) <= 1e-7:                            # mm: closed
            return q
        J = sol.jac                                                # over-constrained: what can the joints still move?
        movable = J @ np.linalg.lstsq(J, gap, rcond=None)[0] if J.size else np.zeros_like(gap)
        if np.max(np.abs(movable)) > 1e-5 or np.max(np.abs(gap)) > self.play:
            return np.full(m.nq, np.nan)
        return q

    def solve(self, commands) -> np.ndarray:
        """Assembled configurations (N, nq) at commands (N, M) (deg / mm); NaN rows where a loop does not
        close. Each from ``home`` by sub-steps of the motors."""
        commands = np.atleast_2d(np.asarray(commands, float))
        out = np.full((len(commands), self.model.nq), np.nan)
        if not np.isfinite(self.home).all():                       # home itself does not assemble
            return out
        span = np.ptp(self.range, axis=1)
        for i, c in enumerate(commands):
            n = max(1, int(np.ceil(np.max(np.abs(c - self.home_cmd) / span) / SUBSTEP)))
            q = self.home.copy()
            for t in np.linspace(0.0, 1.0, n + 1)[1:]:
                q[self.motor_q] = self._joint_of(self.home_cmd + t * (c - self.home_cmd))
                q = self._close(q)
                if not np.isfinite(q).all():
                    break
            out[i] = q
        return out

    def nests(self, commands) -> np.ndarray:
        """Nest positions (N, K, 3) mm, world frame."""
        return np.array([self._sites(q, self.target_ids) for q in self.solve(commands)])

    def _sites(self, q: np.ndarray, ids) -> np.ndarray:
        if not np.isfinite(q).all():
            return np.full((len(ids), 3), np.nan)
        self.data.qpos[:] = q
        mujoco.mj_kinematics(self.model, self.data)
        return self.data.site_xpos[ids] * 1000.0

    def task(self, commands) -> np.ndarray:
        """Task coordinates (N, C) of the task site: x, y, z mm and rx, ry, rz deg (R = Rz Ry Rx)."""
        out = []
        for q in self.solve(commands):
            if not np.isfinite(q).all():
                out.append(np.full(len(self.coordinates), np.nan))
                continue
            self.data.qpos[:] = q
            mujoco.mj_kinematics(self.model, self.data)
            out.append(self.task_here())
        return np.array(out)

    def task_here(self) -> np.ndarray:
        """Task coordinates (C,) of the configuration whose kinematics ran last (as :meth:`task`)."""
        p = self.data.site_xpos[self.task_id] * 1000.0
        R = self.data.site_xmat[self.task_id].reshape(3, 3)
        rz, ry, rx = Rotation.from_matrix(R).as_euler("ZYX", degrees=True)
        vals = dict(x_mm=p[0], y_mm=p[1], z_mm=p[2], rx_deg=rx, ry_deg=ry, rz_deg=rz)
        return np.array([vals[c] for c in self.coordinates])
