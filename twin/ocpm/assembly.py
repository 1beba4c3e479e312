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

Options used by the drive and thermal effects (:mod:`pmcal.twin.ocpm.effects`):

- **motor springs** (``motor_stiffness``, N m/rad per motor): the motor joints are no longer held; a
  torsional spring in series behind each motor ties the joint to its commanded angle, adding
  ``1/2 K (q_m - q_cmd)^2`` to the energy (residual rows ``sqrt(K) (q_m - q_cmd)`` after the SS row). The
  commanded angles are the motor values of the ``qpos`` given to :meth:`BatchAssembler.solve`. The
  sensitivities of :mod:`pmcal.twin.ocpm.sensitivity` assume held motors; do not use them with springs.
- **per-pose models** (:meth:`BatchAssembler.set_models`): simulation i runs on its own compiled model
  (same structure, other numbers: a payload mass, a thermally scaled geometry).
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import mujoco
import numpy as np

from pmcal.twin.closures import solve_stacked
from pmcal.twin.ocpm.model import ModelIndex


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


HINGE, SLIDE, BALL = 0, 1, 2      # joint kinds in :func:`chain_dofs`


def chain_dofs(m: mujoco.MjModel, body: int) -> list[tuple[int, int, int, int, int]]:
    """Every degree of freedom that moves ``body``, walking the tree to the world: ``(dof, jnt, kind,
    body, k)`` with kind :data:`HINGE`, :data:`SLIDE` or :data:`BALL` (``k`` the ball's axis 0-2, about
    the axes of its ``body``'s frame: MuJoCo's ball velocities are local)."""
    out = []
    while body > 0:
        for jnt in range(m.body_jntadr[body], m.body_jntadr[body] + m.body_jntnum[body]):
            kind, dof = int(m.jnt_type[jnt]), int(m.jnt_dofadr[jnt])
            if kind == mujoco.mjtJoint.mjJNT_BALL:
                out += [(dof + k, jnt, BALL, body, k) for k in range(3)]
            elif kind == mujoco.mjtJoint.mjJNT_HINGE:
                out.append((dof, jnt, HINGE, body, 0))
            elif kind == mujoco.mjtJoint.mjJNT_SLIDE:
                out.append((dof, jnt, SLIDE, body, 0))
            else:
                raise ValueError("free joints are not expected inside the closed chain")
        body = int(m.body_parentid[body])
    return out


class _ChainJacobian:
    """Translational Jacobians of sites from batched kinematics (numpy, vectorised over simulations).

    Same columns as ``mj_jacSite``: a hinge contributes ``axis x (p - anchor)``, a slide its axis, a
    ball three columns about the axes of its body frame (MuJoCo's ball velocities are local).
    """

    def __init__(self, m: mujoco.MjModel, sites: np.ndarray):
        self.nv, self.n_sites = m.nv, len(sites)
        # (site row, dof, jnt, kind, body, k) for every dof that moves a site
        c = np.array([(i, *col) for i, s in enumerate(sites) for col in chain_dofs(m, int(m.site_bodyid[s]))])
        self.site, self.dof, self.jnt, self.kind, self.body, self.k = c.T
        self.ball = self.kind == BALL
        self.slide = self.kind == SLIDE
        half = self.n_sites // 2
        self.sign = np.where(self.site < half, 1.0, -1.0)
        # flat positions of column c, component i in a (3 half, nv) gap Jacobian: row 3 (site % half) + i
        self._flat = ((3 * (self.site % half))[:, None] + np.arange(3)) * self.nv + self.dof[:, None]
        # one-hot (C, nv): sums per-column terms into their degree of freedom
        self._to_dof = np.zeros((len(c), self.nv))
        self._to_dof[np.arange(len(c)), self.dof] = 1.0
        self._axis_index: tuple[int, np.ndarray] | None = None    # gather of the axes, set on first use

    def gap(self, site_pos: np.ndarray, xanchor: np.ndarray, xaxis: np.ndarray,
            xmat: np.ndarray, col: np.ndarray | None = None) -> np.ndarray:
        """Jacobians (N, 3 n, nv) of the gaps ``site[j] - site[n + j]`` for sites given as 2n rows
        (``col``: the :meth:`columns` at these kinematics, if already computed).

        The two sites of a gap must not share a degree of freedom (true for a closure of a loop
        whose two halves hang on different branches of the tree).
        """
        N, half = site_pos.shape[0], self.n_sites // 2
        if col is None:
            col = self.columns(site_pos, xanchor, xaxis, xmat)
        J = np.zeros((N, 3 * half * self.nv))
        J[:, self._flat] = col * self.sign[None, :, None]
        return J.reshape(N, 3 * half, self.nv)

    def gap_gradient(self, col: np.ndarray, force: np.ndarray) -> np.ndarray:
        """``J_gap^T f`` (N, nv) for gap-space vectors ``force`` (N, n, 3) from the :meth:`columns`
        ``col``, without forming the Jacobian."""
        half = self.n_sites // 2
        per_col = np.einsum("nci,nci->nc", col, force[:, self.site % half]) * self.sign
        return per_col @ self._to_dof

    def sites(self, site_pos: np.ndarray, xanchor: np.ndarray, xaxis: np.ndarray,
              xmat: np.ndarray) -> np.ndarray:
        """Jacobians (N, n_sites, 3, nv) of the sites' positions."""
        N = site_pos.shape[0]
        J = np.zeros((N, self.n_sites, self.nv, 3))
        J[:, self.site, self.dof] = self.columns(site_pos, xanchor, xaxis, xmat)
        return np.swapaxes(J, 2, 3)

    def columns(self, site_pos, xanchor, xaxis, xmat) -> np.ndarray:
        """Jacobian columns (N, C, 3), one per (site, dof that moves it) pair, world frame."""
        N = site_pos.shape[0]
        xaxis, xmat = xaxis.reshape(N, -1), xmat.reshape(N, -1)
        # a hinge's or slide's axis is xaxis[jnt]; a ball's k-th axis the k-th column of its body's xmat
        if self._axis_index is None or self._axis_index[0] != xaxis.shape[1]:
            idx = 3 * self.jnt[:, None] + np.arange(3)
            ball = xaxis.shape[1] + 9 * self.body + self.k
            idx[self.ball] = ball[self.ball, None] + 3 * np.arange(3)
            self._axis_index = (xaxis.shape[1], idx)
        axis = np.concatenate([xaxis, xmat], axis=1)[:, self._axis_index[1]]   # (N, C, 3)
        d = site_pos[:, self.site] - xanchor[:, self.jnt]
        a0, a1, a2 = axis[..., 0], axis[..., 1], axis[..., 2]
        d0, d1, d2 = d[..., 0], d[..., 1], d[..., 2]
        col = np.stack([a1 * d2 - a2 * d1, a2 * d0 - a0 * d2, a0 * d1 - a1 * d0], axis=-1)
        col[:, self.slide] = axis[:, self.slide]
        return col


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    w1, x1, y1, z1 = np.moveaxis(a, -1, 0)
    w2, x2, y2, z2 = np.moveaxis(b, -1, 0)
    return np.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], -1)


_layouts: dict[int, tuple] = {}


def _joint_layout(m: mujoco.MjModel):
    """(qpos addresses, dof addresses) of the hinge and slide joints and (qpos, dof) addresses (nb,) of the
    balls of ``m``; read once per model (the joint structure of a compiled model does not change)."""
    key = id(m)
    if key in _layouts and _layouts[key][0] is m:
        return _layouts[key][1]
    q1, d1, qb, db = [], [], [], []
    for jnt in range(m.njnt):
        qa, da, kind = int(m.jnt_qposadr[jnt]), int(m.jnt_dofadr[jnt]), int(m.jnt_type[jnt])
        if kind == mujoco.mjtJoint.mjJNT_BALL:
            qb.append(qa)
            db.append(da)
        elif kind in (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE):
            q1.append(qa)
            d1.append(da)
        else:
            raise ValueError("free joints are not expected inside the closed chain")
    layout = (np.array(q1, int), np.array(d1, int), np.array(qb, int), np.array(db, int))
    if len(_layouts) > 64:                                # models of finished studies
        _layouts.clear()
    _layouts[key] = (m, layout)
    return layout


def integrate_pos(m: mujoco.MjModel, qpos: np.ndarray, dv: np.ndarray) -> None:
    """Vectorised ``mj_integratePos(m, qpos, dv, 1)`` for hinge, slide and ball joints (in place)."""
    q1, d1, qa, da = _joint_layout(m)
    qpos[:, q1] += dv[:, d1]
    if not len(qa):
        return
    w = dv[:, da[:, None] + np.arange(3)]                              # (N, nb, 3)
    ang = np.linalg.norm(w, axis=-1)
    half = 0.5 * ang
    scale = np.where(ang > 1e-300, np.sin(half) / np.maximum(ang, 1e-300), 0.5)
    dq = np.concatenate([np.cos(half)[..., None], w * scale[..., None]], axis=-1)
    idx = qa[:, None] + np.arange(4)
    q = _quat_mul(qpos[:, idx], dq)
    qpos[:, idx] = q / np.linalg.norm(q, axis=-1, keepdims=True)


class BatchAssembler:
    """Quasi-static assembly of many configurations at once.

    MuJoCo computes the kinematics of every configuration (``mujoco.batch.Batch``, position stage, on a
    thread pool); the Gauss-Newton steps run vectorised in numpy. Reuse one assembler for one model.

    Near the limbs' stretched-link singularity a full Gauss-Newton step can leave the basin (a strained
    machine at 80 deg tilt, or a fit trying large parameters): steps are capped at ``MAX_STEP`` (rad, or
    m for the SS slide) per coordinate, and a pose whose normal equations are singular stops, not
    converged, instead of filling its state with NaN. With ``secant_steps`` a pose whose steps bounce back
    and forth (the normal equations lack gravity's curvature) takes shorter, secant-scaled steps
    (:meth:`_overshoots`).
    """

    MAX_STEP = 0.2
    #: Secant step lengths for poses whose steps bounce (:meth:`_overshoots`); off by default: the twin
    #: generating a campaign skips such a pose as an operator skips one where the machine binds (from a
    #: bouncing start it converged, in the twin's campaigns, to equilibria 0.1-13 mm from its neighbours'
    #: trend); the diagnosis' model (:class:`pmcal.twin.ocpm.effect_model.EffectChainModel`) turns them on to
    #: reproduce poses another machine did measure.
    secant_steps = False

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
                             xmat=self._b_xmat[:N].reshape(N, -1, 3, 3).copy(), xanchor=anchor.copy(),
                             xaxis=axis.copy(), res=res, J=Jw, free=self.free,
                             bias=bias.copy() if self.gravity else np.zeros((N, self.m.nv)))

    def _kinematics(self, qpos: np.ndarray, ids: np.ndarray):
        batch = self._ensure_batch(len(qpos))
        stage = mujoco.mjtStage.mjSTAGE_VEL if self.gravity else mujoco.mjtStage.mjSTAGE_POS
        if len(ids) == len(qpos) and (len(ids) == 0 or ids[-1] == len(ids) - 1):
            ids = slice(0, len(qpos))                     # every row, in order: views, not copies
            self._b_qpos[ids] = qpos
            batch.forward(ids=np.arange(len(qpos)), stage=stage)
        else:
            self._b_qpos[ids] = qpos[ids]
            batch.forward(ids=ids, stage=stage)
        return (self._b_site[ids][:, self._sites], self._b_anchor[ids], self._b_axis[ids],
                self._b_xmat[ids], self._b_bias[ids])

    def _rest_of(self, qpos: np.ndarray) -> np.ndarray:
        """Commanded motor angles of the rows of ``qpos``: those of the last solve if it had as many rows."""
        if len(self._rest) == len(qpos):
            return self._rest
        return qpos[:, self.idx.qadr_base[:2]]

    def _residual(self, site, anchor, axis, xmat, qpos_ids, rest=None, col=None):
        n = len(self.idx.site_s1)
        Jg = self._jac.gap(site, anchor, axis, xmat, col)             # (M, 3n, nv)
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

    @staticmethod
    def _overshoots(step: np.ndarray, last: np.ndarray) -> np.ndarray:
        """Poses (bool per row) whose Gauss-Newton step turns back on the previous one without shrinking
        much (cosine < -0.5, length > half): an overshoot that does not die out. Under gravity the normal
        equations lack the load's curvature, and a soft spring (joint compliance, a strained pose with
        10 kg) can then bounce between two configurations for ever (the refit of a compliant machine
        stalled on such poses). From then on that pose takes secant step lengths
        (:meth:`_secant_damping`); the equilibrium, where the step is zero, is unchanged."""
        a, b = np.linalg.norm(step, axis=1), np.linalg.norm(last, axis=1)
        dot = np.einsum("nf,nf->n", step, last)
        return (dot < -0.5 * a * b) & (a > 0.5 * b) & (b > 0)

    @staticmethod
    def _secant_damping(step: np.ndarray, last: np.ndarray, taken: np.ndarray) -> np.ndarray:
        """Step length (per row, 1/16 .. 1) from the curvature along the step just taken relative to the
        Gauss-Newton matrix: ``lam = -(step - last) . taken / |taken|^2`` (1 where the normal equations
        hold the whole curvature, ~2 for a bouncing pose), length ``1 / lam`` (a Barzilai-Borwein step in
        the Gauss-Newton metric). Rows with no step taken yet get 1/2."""
        tt = np.einsum("nf,nf->n", taken, taken)
        lam = -np.einsum("nf,nf->n", step - last, taken) / np.where(tt > 0, tt, 1.0)
        length = np.clip(1.0 / np.where(lam > 0, lam, 1.0), 1.0 / 16.0, 1.0)
        return np.where(tt > 0, length, 0.5)

    def solve(self, qpos: np.ndarray) -> AssemblyResult:
        """Assemble every row of ``qpos`` (N, nq) in place; held joints stay at their values."""
        qpos = np.atleast_2d(qpos)
        N = qpos.shape[0]
        iters = np.zeros(N, int)
        converged = np.zeros(N, bool)
        active = np.arange(N)
        free = self.free
        self._rest = qpos[:, self.idx.qadr_base[:2]].copy()
        last = np.zeros((N, len(free)))                   # each pose's previous Gauss-Newton step
        taken = np.zeros((N, len(free)))                  # and the step it took
        damp = np.ones(N)
        shaky = np.zeros(N, bool)                         # poses that overshot: secant step lengths
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
            shaky[active] |= self.secant_steps & self._overshoots(step, last[active])
            damp[active] = np.where(shaky[active], self._secant_damping(step, last[active], taken[active]), 1.0)
            last[active] = step
            step *= np.minimum(1.0, self.MAX_STEP / np.where(bad, 1.0, np.maximum(size, 1e-300)))[:, None]
            step *= damp[active, None]
            taken[active] = step
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
