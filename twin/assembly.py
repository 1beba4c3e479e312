"""Quasi-static assembly of the closed chain with explicit closure compliance.

With the motors held, the machine settles where the stored elastic energy (plus, optionally, the
gravity potential) is least::

    E(q) = 1/2 sum_j k_j |S1_j(q) - S2_j(q)|^2 + 1/2 k_ss s(q)^2 + U_gravity(q)

``k_j`` is the closure stiffness at the spherical joint S_j (N/m), ``k_ss`` the axial stiffness of the
SS limb (joint ``ss_slide``, displacement ``s``). Reference: passive closures k_p, actuated closures and
the SS limb ``ratio * k_p`` (ratio 1000, docs/ocpm_2dof.md). On a consistent machine every closure closes and
the solution is exact (Gauss-Newton on a zero-residual problem converges quadratically to ~1e-16 m);
on an inconsistent one the misfit is shared in proportion to compliance, which is what a real
over-constrained machine does.

Residuals and Jacobians come from MuJoCo (``mj_kinematics``, ``mj_comPos``, ``mj_jacSite``); the step is
a Gauss-Newton step on the free degrees of freedom (all but the held motor joints), integrated with
``mj_integratePos`` (ball quaternion). Units inside: SI.

Options used by the drive and thermal effects (:mod:`pmcal.twin.effects`):

- **motor springs** (``motor_stiffness``, N m/rad per motor): the motor joints are no longer held; a
  torsional spring in series behind each motor ties the joint to its commanded angle, adding
  ``1/2 K (q_m - q_cmd)^2`` to the energy (residual rows ``sqrt(K) (q_m - q_cmd)`` after the SS row). The
  commanded angles are the motor values of the ``qpos`` given to :meth:`BatchAssembler.solve`. The
  sensitivities of :mod:`pmcal.twin.sensitivity` assume held motors; do not use them with springs.
- **per-pose models** (:meth:`BatchAssembler.set_models`): simulation i runs on its own compiled model
  (same structure, other numbers: a payload mass, a thermally scaled geometry).
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import mujoco
import numpy as np

from pmcal.twin.model import ModelIndex


@dataclass
class Stiffness:
    """Closure and SS stiffness (N/m). ``closure`` has one value per limb."""

    closure: np.ndarray
    ss_axial: float

    @classmethod
    def reference(cls, passive: float = 1.0e6, ratio: float = 1000.0, n_limbs: int = 4,
                  actuated: tuple[int, ...] = (1, 2)) -> "Stiffness":
        """Passive closures ``passive``; actuated closures and SS ``ratio * passive`` (N/m)."""
        k = np.full(n_limbs, float(passive))
        for j in actuated:
            k[j - 1] = passive * ratio
        return cls(closure=k, ss_axial=passive * ratio)


@dataclass
class Linearization:
    """Kinematics and the weighted closure residual at configurations (SI), for sensitivities.

    site_xpos (N, nsite, 3), xpos (N, nbody, 3), xmat (N, nbody, 3, 3), xanchor/xaxis (N, njnt, 3),
    res (N, 3 n + 1) weighted residual, J (N, 3 n + 1, nv) its Jacobian, free: free dof indices;
    bias (N, nv) gravity generalised force ``dU/dq`` (N m or N), zero when gravity is off. The
    generalised force a joint must supply to stay put is ``J^T res + bias`` (the energy gradient).
    """

    site_xpos: np.ndarray
    xpos: np.ndarray
    xmat: np.ndarray
    xanchor: np.ndarray
    xaxis: np.ndarray
    res: np.ndarray
    J: np.ndarray
    free: np.ndarray
    bias: np.ndarray | None = None


@dataclass
class AssemblyResult:
    """Outcome of assembling N configurations (SI units).

    qpos : (N, nq) equilibrium configurations.
    converged : (N,) step below tolerance within the iteration limit.
    iterations : (N,) Gauss-Newton iterations used.
    gaps : (N, n_limbs, 3) closure gap S1_j - S2_j in the world frame, m.
    ss_axial : (N,) axial deflection of the SS limb, m.
    energy : (N,) elastic energy, J.
    """

    qpos: np.ndarray
    converged: np.ndarray
    iterations: np.ndarray
    gaps: np.ndarray
    ss_axial: np.ndarray
    energy: np.ndarray


class _ChainJacobian:
    """Translational Jacobians of sites from batched kinematics (numpy, vectorised over simulations).

    Same columns as ``mj_jacSite``: a hinge contributes ``axis x (p - anchor)``, a slide its axis, a
    ball three columns about the axes of its body frame (MuJoCo's ball velocities are local).
    """

    def __init__(self, m: mujoco.MjModel, sites: np.ndarray):
        self.nv, self.n_sites = m.nv, len(sites)
        cols = []   # (site row, dof, jnt, kind, body, k) for every dof that moves a site
        for i, s in enumerate(sites):
            body = int(m.site_bodyid[s])
            while body > 0:
                for jnt in range(m.body_jntadr[body], m.body_jntadr[body] + m.body_jntnum[body]):
                    kind, dof = int(m.jnt_type[jnt]), int(m.jnt_dofadr[jnt])
                    if kind == mujoco.mjtJoint.mjJNT_BALL:
                        cols += [(i, dof + k, jnt, 2, body, k) for k in range(3)]
                    elif kind == mujoco.mjtJoint.mjJNT_HINGE:
                        cols.append((i, dof, jnt, 0, body, 0))
                    elif kind == mujoco.mjtJoint.mjJNT_SLIDE:
                        cols.append((i, dof, jnt, 1, body, 0))
                    else:
                        raise ValueError("free joints are not expected inside the closed chain")
                body = int(m.body_parentid[body])
        c = np.array(cols)
        self.site, self.dof, self.jnt, self.kind, self.body, self.k = c.T
        self.ball = self.kind == 2
        self.slide = self.kind == 1

    def gap(self, site_pos: np.ndarray, xanchor: np.ndarray, xaxis: np.ndarray,
            xmat: np.ndarray) -> np.ndarray:
        """Jacobians (N, 3 n, nv) of the gaps ``site[j] - site[n + j]`` for sites given as 2n rows.

        The two sites of a gap must not share a degree of freedom (true for a closure of a loop
        whose two halves hang on different branches of the tree).
        """
        N, half = site_pos.shape[0], self.n_sites // 2
        col = self._columns(site_pos, xanchor, xaxis, xmat)
        sign = np.where(self.site < half, 1.0, -1.0)
        J = np.zeros((N, half, self.nv, 3))
        J[:, self.site % half, self.dof] = col * sign[None, :, None]
        return np.swapaxes(J, 2, 3).reshape(N, 3 * half, self.nv)

    def sites(self, site_pos: np.ndarray, xanchor: np.ndarray, xaxis: np.ndarray,
              xmat: np.ndarray) -> np.ndarray:
        """Jacobians (N, n_sites, 3, nv) of the sites' positions."""
        N = site_pos.shape[0]
        J = np.zeros((N, self.n_sites, self.nv, 3))
        J[:, self.site, self.dof] = self._columns(site_pos, xanchor, xaxis, xmat)
        return np.swapaxes(J, 2, 3)

    def _columns(self, site_pos, xanchor, xaxis, xmat) -> np.ndarray:
        N = site_pos.shape[0]
        axis = xaxis[:, self.jnt]                                         # (N, C, 3)
        frames = xmat[:, self.body[self.ball]].reshape(N, -1, 3, 3)
        axis[:, self.ball] = np.take_along_axis(
            frames, self.k[self.ball][None, :, None, None], axis=3)[..., 0]
        col = np.cross(axis, site_pos[:, self.site] - xanchor[:, self.jnt])
        col[:, self.slide] = axis[:, self.slide]
        return col


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    w1, x1, y1, z1 = np.moveaxis(a, -1, 0)
    w2, x2, y2, z2 = np.moveaxis(b, -1, 0)
    return np.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], -1)


def _joint_layout(m: mujoco.MjModel) -> tuple[np.ndarray, np.ndarray, list[tuple[int, int]]]:
    """(qpos addresses, dof addresses) of the hinge and slide joints and (qpos, dof) of the balls of ``m``."""
    q1, d1, balls = [], [], []
    for jnt in range(m.njnt):
        qa, da, kind = int(m.jnt_qposadr[jnt]), int(m.jnt_dofadr[jnt]), int(m.jnt_type[jnt])
        if kind == mujoco.mjtJoint.mjJNT_BALL:
            balls.append((qa, da))
        elif kind in (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE):
            q1.append(qa)
            d1.append(da)
        else:
            raise ValueError("free joints are not expected inside the closed chain")
    return np.array(q1, int), np.array(d1, int), balls


def integrate_pos(m: mujoco.MjModel, qpos: np.ndarray, dv: np.ndarray) -> None:
    """Vectorised ``mj_integratePos(m, qpos, dv, 1)`` for hinge, slide and ball joints (in place)."""
    q1, d1, balls = _joint_layout(m)
    qpos[:, q1] += dv[:, d1]
    if not balls:
        return
    qa = np.array([b[0] for b in balls])
    da = np.array([b[1] for b in balls])
    w = dv[:, da[:, None] + np.arange(3)]                              # (N, nb, 3)
    ang = np.linalg.norm(w, axis=-1)
    half = 0.5 * ang
    scale = np.where(ang > 1e-300, np.sin(half) / np.maximum(ang, 1e-300), 0.5)
    dq = np.concatenate([np.cos(half)[..., None], w * scale[..., None]], axis=-1)
    idx = qa[:, None] + np.arange(4)
    q = _quat_mul(qpos[:, idx], dq)
    qpos[:, idx] = q / np.linalg.norm(q, axis=-1, keepdims=True)


def solve_stacked(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``A^-1 B`` for a stack of square matrices ``A`` (M, k, k) and right-hand sides ``B`` (M, k) or
    (M, k, m). Rows whose ``A`` is singular (a configuration at the singularity, a pose the solve gave
    up) come back as NaN; numpy's batched solve fails as a whole, so those rows are redone one by one."""
    vec = B.ndim == A.ndim - 1
    Bm = B[..., None] if vec else B
    try:
        out = np.linalg.solve(A, Bm)
    except np.linalg.LinAlgError:
        out = np.full(Bm.shape, np.nan)
        for i in range(len(A)):
            try:
                out[i] = np.linalg.solve(A[i], Bm[i])
            except np.linalg.LinAlgError:
                pass
    return out[..., 0] if vec else out


class BatchAssembler:
    """Quasi-static assembly of many configurations at once.

    MuJoCo computes the kinematics of every configuration (``mujoco.batch.Batch``, position stage, on a
    thread pool); the Gauss-Newton steps run vectorised in numpy. Reuse one assembler for one model.

    Near the limbs' stretched-link singularity a full Gauss-Newton step can leave the basin (a strained
    machine at 80 deg tilt, or a fit trying large parameters): steps are capped at ``MAX_STEP`` (rad, or
    m for the SS slide) per coordinate, and a pose whose normal equations are singular stops, not
    converged, instead of filling its state with NaN.
    """

    MAX_STEP = 0.2

    def __init__(self, m: mujoco.MjModel, index: ModelIndex, stiffness: Stiffness,
                 gravity: bool = False, held_dofs: np.ndarray | None = None,
                 tol: float = 1e-13, max_iter: int = 40, nthread: int | None = None,
                 motor_stiffness: np.ndarray | None = None):
        from mujoco import batch as mjbatch

        self.m, self.idx = m, index
        # The batch only needs kinematics (and gravity forces): the model skips building constraint
        # rows and limits. The batch reads the model live (set_models), so in-place edits of ``m``
        # (new errors) are seen by the next solve. Simulation uses its own copy (twin.dynamics).
        m.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONSTRAINT | mujoco.mjtDisableBit.mjDSBL_LIMIT)
        self.gravity = gravity
        self.tol, self.max_iter = tol, max_iter
        self._held = index.dadr_base[:2] if held_dofs is None else np.asarray(held_dofs)
        self.free = np.setdiff1d(np.arange(m.nv), self._held)
        self._models: list | None = None
        self._rest = np.zeros((0, 2))
        self.set_motor_stiffness(motor_stiffness)
        self.set_stiffness(stiffness)
        self._sites = np.concatenate([index.site_s1, index.site_s2])
        self._jac = _ChainJacobian(m, self._sites)
        self._nthread = nthread or max(1, min(4, os.cpu_count() or 1))
        self._mjbatch = mjbatch
        self._batch = None

    def set_stiffness(self, stiffness: Stiffness) -> None:
        self.stiffness = stiffness
        self._w = np.sqrt(np.repeat(np.asarray(stiffness.closure, float), 3))
        self._w_ss = float(np.sqrt(stiffness.ss_axial))

    def set_motor_stiffness(self, stiffness: np.ndarray | None) -> None:
        """Series springs behind the motors, N m/rad (one per motor, or None: motors held exactly)."""
        if stiffness is None:
            self.motor_stiffness = None
            self.free = np.setdiff1d(np.arange(self.m.nv), self._held)
            return
        k = np.broadcast_to(np.asarray(stiffness, float), (2,)).copy()
        if not np.all(np.isfinite(k) & (k > 0)):
            raise ValueError(f"motor stiffness must be positive N m/rad, got {k}")
        self.motor_stiffness = k
        self.free = np.arange(self.m.nv)

    def set_models(self, models: list[mujoco.MjModel] | None) -> None:
        """Run pose i of the next solves on ``models[i]`` (None: every pose on the assembler's model).

        The models must share the structure of the assembler's model (copies with other masses,
        positions, ...). Poses beyond ``len(models)`` use the assembler's model.
        """
        self._models = None if models is None else list(models)
        if self._batch is not None:
            self._bind_models()

    def _bind_models(self) -> None:
        if self._models is None:
            self._batch.set_models(self.m)
            return
        n = self._batch.nsim
        models = self._models[:n] + [self.m] * max(0, n - len(self._models))
        self._batch.set_models(models)

    def _ensure_batch(self, n: int):
        if self._batch is None or self._batch.nsim < n:
            self._batch = self._mjbatch.Batch(self.m, nsim=max(n, 64), nthread=self._nthread)
            self._bind_models()
            self._b_qpos = self._batch.bind("qpos")
            self._b_site = self._batch.bind("site_xpos")
            self._b_anchor = self._batch.bind("xanchor")
            self._b_axis = self._batch.bind("xaxis")
            self._b_xmat = self._batch.bind("xmat")
            self._b_xpos = self._batch.bind("xpos")
            self._b_bias = self._batch.bind("qfrc_bias")
            self._b_qvel = self._batch.bind("qvel")
            self._b_qvel[:] = 0.0
        return self._batch

    def bodies(self, n: int, body: int) -> tuple[np.ndarray, np.ndarray]:
        """Position (n, 3) m and orientation (n, 3, 3) of ``body`` after the last :meth:`solve`."""
        return self._b_xpos[:n, body].copy(), self._b_xmat[:n, body].reshape(n, 3, 3).copy()

    def sites(self, n: int, sites: np.ndarray) -> np.ndarray:
        """Positions (n, len(sites), 3) m of ``sites`` after the last :meth:`solve`."""
        return self._b_site[:n][:, sites].copy()

    def linearize(self, qpos: np.ndarray) -> Linearization:
        """Kinematics, weighted residual and Jacobian at every row of ``qpos`` (N, nq)."""
        qpos = np.atleast_2d(qpos)
        N = len(qpos)
        ids = np.arange(N)
        site, anchor, axis, xmat, bias = self._kinematics(qpos, ids)
        res, Jw, _ = self._residual(site, anchor, axis, xmat, qpos, self._rest_of(qpos))
        return Linearization(site_xpos=self._b_site[:N].copy(), xpos=self._b_xpos[:N].copy(),
                             xmat=self._b_xmat[:N].reshape(N, -1, 3, 3).copy(), xanchor=anchor,
                             xaxis=axis, res=res, J=Jw, free=self.free,
                             bias=bias.copy() if self.gravity else np.zeros((N, self.m.nv)))

    def _kinematics(self, qpos: np.ndarray, ids: np.ndarray):
        batch = self._ensure_batch(len(qpos))
        self._b_qpos[ids] = qpos[ids]
        stage = mujoco.mjtStage.mjSTAGE_VEL if self.gravity else mujoco.mjtStage.mjSTAGE_POS
        batch.forward(ids=ids, stage=stage)
        return (self._b_site[ids][:, self._sites], self._b_anchor[ids], self._b_axis[ids],
                self._b_xmat[ids], self._b_bias[ids])

    def _rest_of(self, qpos: np.ndarray) -> np.ndarray:
        """Commanded motor angles of the rows of ``qpos``: those of the last solve if it had as many rows."""
        if len(self._rest) == len(qpos):
            return self._rest
        return qpos[:, self.idx.qadr_base[:2]]

    def _residual(self, site, anchor, axis, xmat, qpos_ids, rest=None):
        n = len(self.idx.site_s1)
        Jg = self._jac.gap(site, anchor, axis, xmat)                  # (M, 3n, nv)
        gap = site[:, :n] - site[:, n:]                               # (M, n, 3)
        res = np.concatenate([gap.reshape(len(site), 3 * n) * self._w,
                              self._w_ss * qpos_ids[:, [self.idx.qadr_slide]]], axis=1)
        Jss = np.zeros((len(site), 1, self.m.nv))
        Jss[:, 0, self.idx.dadr_slide] = self._w_ss
        Jw = np.concatenate([Jg * self._w[None, :, None], Jss], axis=1)
        if self.motor_stiffness is not None:
            wk = np.sqrt(self.motor_stiffness)
            res = np.concatenate([res, wk * (qpos_ids[:, self.idx.qadr_base[:2]] - rest)], axis=1)
            Jk = np.zeros((len(site), 2, self.m.nv))
            Jk[:, [0, 1], self.idx.dadr_base[:2]] = wk
            Jw = np.concatenate([Jw, Jk], axis=1)
        return res, Jw, gap

    def solve(self, qpos: np.ndarray) -> AssemblyResult:
        """Assemble every row of ``qpos`` (N, nq) in place; held joints stay at their values."""
        qpos = np.atleast_2d(qpos)
        N = qpos.shape[0]
        iters = np.zeros(N, int)
        converged = np.zeros(N, bool)
        active = np.arange(N)
        free = self.free
        self._rest = qpos[:, self.idx.qadr_base[:2]].copy()
        for it in range(1, self.max_iter + 1):
            site, anchor, axis, xmat, bias = self._kinematics(qpos, active)
            res, Jw, _ = self._residual(site, anchor, axis, xmat, qpos[active], self._rest[active])
            Jf = Jw[:, :, free]
            JfT = np.swapaxes(Jf, 1, 2)
            g = (JfT @ res[..., None])[..., 0]
            if self.gravity:
                g += bias[:, free]
            step = -solve_stacked(JfT @ Jf, g)
            size = np.max(np.abs(step), axis=1)
            bad = ~np.isfinite(size)                      # a singular configuration: give the pose up
            step[bad] = 0.0
            step *= np.minimum(1.0, self.MAX_STEP / np.where(bad, 1.0, np.maximum(size, 1e-300)))[:, None]
            dv = np.zeros((len(active), self.m.nv))
            dv[:, free] = step
            q = qpos[active]
            integrate_pos(self.m, q, dv)
            qpos[active] = q
            iters[active] = it
            done = size < self.tol
            converged[active[done]] = True
            active = active[~(done | bad)]
            if active.size == 0:
                break
        all_ids = np.arange(N)
        site, anchor, axis, xmat, _ = self._kinematics(qpos, all_ids)
        res, _, gap = self._residual(site, anchor, axis, xmat, qpos, self._rest)
        return AssemblyResult(qpos=qpos, converged=converged, iterations=iters, gaps=gap,
                              ss_axial=qpos[:, self.idx.qadr_slide].copy(),
                              energy=0.5 * np.sum(res * res, axis=1))
