"""Aiming the twin: the motor angles whose equilibrium points the platform at a target orientation.

Compensation asks for the commands ``c`` (2 motors) whose quasi-static equilibrium ``q*(c)``
(:mod:`pmcal.twin.ocpm.assembly`) puts the platform normal ``w`` on the target normal. Instead of an outer
Newton on ``c`` around a full assembly per step, the equilibrium and the pointing are solved together:
unknowns the free joints ``q_F`` and the motor joints ``c``, equations

    g(q_F, c) = J_F^T r = 0          (energy gradient on the free joints, as the assembly)
    e(q_F)    = (u . w, v . w) = 0   (the normal's offset in the target's tangent plane, u v its axes)

Each step linearises once (``mj_kinematics`` for every target, the closure Jacobian ``J``, the platform's
rotational Jacobian) and takes the bordered Gauss-Newton step

    [ J_F^T J_F   J_F^T J_c ] [dq_F]     [g]
    [ de/dq_F     0         ] [dc  ] = - [e]

by block elimination (12x12 normal equations, then 2x2 for the motors). The fixed point is the
assembly's equilibrium at commands that point exactly: the same commands as a Newton on the assembled
forward model, in one loop of ~3 kinematics passes per target instead of ~40. The first two steps of a
target use its fresh bordered matrix; later steps (chord steps) keep it and re-evaluate only the
residual ``g`` (``J^T r`` from the Jacobian's columns, without forming ``J``) and ``e``, unless the steps
stop shrinking fast. The platform normal is the third column of the platform body's frame (the
platform frame is the target frame, :mod:`pmcal.twin.ocpm.model`), which a rigid fit of the noise-free
targets returns exactly.

Held motors only (no motor springs, no gravity): the geometric twin of :class:`pmcal.twin.ocpm.forward.FullChainModel`.
Units: SI inside (rad, m), angles in rad at the interface.
"""

from __future__ import annotations

import mujoco
import numpy as np

from pmcal.mechanism.ocpm.kinematics import nominal_ik, nominal_pose
from pmcal.mechanism.rotations import tilt_torsion
from pmcal.twin.ocpm.assembly import BALL, HINGE, chain_dofs, integrate_pos
from pmcal.twin.closures import solve_stacked


class _BodyRotation:
    """World angular-velocity Jacobian (N, 3, nv) of one body from batched kinematics: a hinge
    contributes its axis, a ball the axes of its body frame (MuJoCo's ball velocities are local), a slide
    nothing."""

    def __init__(self, m: mujoco.MjModel, body: int):
        self.nv = m.nv
        dofs = chain_dofs(m, body)
        self.hinge = np.array([(dof, jnt) for dof, jnt, kind, _, _ in dofs if kind == HINGE], int).reshape(-1, 2)
        self.ball = np.array([(dof, b, k) for dof, _, kind, b, k in dofs if kind == BALL], int).reshape(-1, 3)

    def __call__(self, xaxis: np.ndarray, xmat: np.ndarray) -> np.ndarray:
        N = len(xaxis)
        J = np.zeros((N, 3, self.nv))
        frames = xmat.reshape(N, -1, 3, 3)
        for dof, jnt in self.hinge:
            J[:, :, dof] = xaxis[:, jnt]
        for dof, body, k in self.ball:
            J[:, :, dof] = frames[:, body, :, k]
        return J


def _inverse(H: np.ndarray) -> np.ndarray:
    """Inverses of a stack of square matrices (M, k, k); NaN for the singular ones (numpy's batched
    inverse fails as a whole, :func:`solve_stacked` then goes row by row)."""
    try:
        return np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return solve_stacked(H, np.broadcast_to(np.eye(H.shape[1]), H.shape).copy())


def aim(twin, phi: np.ndarray, theta: np.ndarray, tol: float = 1e-12, max_iter: int = 40,
        chunk: int = 1024) -> tuple[np.ndarray, np.ndarray]:
    """True motor joint angles (N, 2) rad whose equilibrium points the platform at (phi, theta) rad.

    ``twin`` is a :class:`pmcal.twin.ocpm.machine.Twin` with held motors and no gravity. Starts at the target
    pose of the nominal machine with every limb's angle from the twin's real IK. Returns the joint
    angles and the equilibrium configurations (N, nq). A target is solved when its estimated remaining
    error (last step times ``rho / (1 - rho)``, ``rho`` the ratio of its last two steps) or its last
    step is below ``tol`` (rad, or m for the SS slide); rows out of reach (outside the nominal
    workspace, no real IK of a limb at the start pose, a singular step, or not solved within
    ``max_iter`` steps, judged from the rate of the steps after :data:`GIVE_UP_AFTER`) are NaN.
    Targets are solved ``chunk`` at a time (arrays that stay in the cache).
    """
    asm = twin.assembler
    if asm.gravity or asm.motor_stiffness is not None:
        raise ValueError("aiming assumes held motors and no gravity")
    phi, theta = np.atleast_1d(np.asarray(phi, float)), np.atleast_1d(np.asarray(theta, float))
    N = len(phi)
    inside = np.isfinite(nominal_ik(phi, theta, twin.geom)).all(axis=1)
    qpos = np.full((N, twin.model.nq), np.nan)
    if inside.any():
        r, R = nominal_pose(phi[inside], theta[inside], twin.geom)
        qpos[inside] = twin.pose_qpos(r, R)
    Rt = tilt_torsion(phi, theta)
    uv = np.swapaxes(Rt[:, :, :2], 1, 2)                      # (N, 2, 3): target tangent axes u, v
    rows = np.flatnonzero(np.isfinite(qpos).all(axis=1))       # no start where a limb's IK has no solution
    out = np.full_like(qpos, np.nan)
    for i in range(0, len(rows), chunk):
        part = rows[i:i + chunk]
        out[part] = _aim_chunk(twin, qpos[part], uv[part], tol, max_iter)
    return out[:, twin.index.qadr_base[:2]].copy(), out


#: Steps after which the bordered matrix is kept (chord steps: only the residual is re-evaluated) while
#: a target's steps shrink at least this fast.
FRESH_STEPS, CHORD_RATE = 2, 0.05
#: Steps before a target whose convergence is too slow to finish within ``max_iter`` is given up (near
#: the singular bands at the workspace edge steps can grow before they shrink).
GIVE_UP_AFTER = 3


def _aim_chunk(twin, qpos: np.ndarray, uv: np.ndarray, tol: float, max_iter: int) -> np.ndarray:
    """:func:`aim` for start configurations ``qpos`` (M, nq) and tangent axes ``uv`` (M, 2, 3); the
    equilibria (rows NaN: not solved)."""
    asm, idx, m = twin.assembler, twin.index, twin.model
    if not hasattr(twin, "_platform_rotation"):
        twin._platform_rotation = _BodyRotation(m, idx.platform)
    rot, jac = twin._platform_rotation, asm._jac
    free, motors = asm.free, idx.dadr_base[:2]
    n = len(idx.site_s1)
    w2 = (asm._w ** 2).reshape(n, 3)                                         # closure stiffness, N/m
    qpos = qpos.copy()
    out = np.full_like(qpos, np.nan)
    active = np.arange(len(qpos))
    prev = np.full(len(qpos), np.inf)                                        # last step size
    age = np.zeros(len(qpos), int)                                           # steps taken
    refresh = np.zeros(len(qpos), bool)                                      # chord steps too slow
    Hinv = np.zeros((len(qpos), len(free), len(free)))
    Xc = np.zeros((len(qpos), len(free), 2))
    E = np.zeros((len(qpos), 2, len(free)))
    Sinv = np.zeros((len(qpos), 2, 2))
    for _ in range(max_iter):
        if active.size == 0:
            break
        q = qpos[active]
        site, anchor, axis, xmat, _ = asm._kinematics(q, np.arange(len(q)))
        col = jac.columns(site, anchor, axis, xmat)
        gap = site[:, :n] - site[:, n:]
        g = jac.gap_gradient(col, gap * w2)                                  # dE/dq, (M, nv)
        g[:, idx.dadr_slide] += asm._w_ss ** 2 * q[:, idx.qadr_slide]
        w = xmat[:, idx.platform, 2::3]                                      # platform normal (M, 3)
        e = np.einsum("nki,ni->nk", uv[active], w)                            # pointing offset (M, 2)
        fresh = (age[active] < FRESH_STEPS) | refresh[active]
        f = np.flatnonzero(fresh)
        if f.size:
            J = asm._residual(site[f], anchor[f], axis[f], xmat[f], q[f], col=col[f])[1]
            JF, Jc = J[:, :, free], J[:, :, motors]
            JFt = np.swapaxes(JF, 1, 2)
            H = JFt @ JF
            Hi = _inverse(H)
            Ef = np.einsum("nki,nid->nkd", np.cross(w[f][:, None, :], uv[active[f]]),
                           rot(axis[f], xmat[f]))[:, :, free]                 # d(u.w)/dq = omega.(w x u)
            Xcf = Hi @ (JFt @ Jc)
            S = Ef @ Xcf                                                     # d e / d motors (2x2)
            det = S[:, 0, 0] * S[:, 1, 1] - S[:, 0, 1] * S[:, 1, 0]
            Si = np.stack([np.stack([S[:, 1, 1], -S[:, 0, 1]], -1), np.stack([-S[:, 1, 0], S[:, 0, 0]], -1)], 1)
            with np.errstate(divide="ignore", invalid="ignore"):
                Si = Si / det[:, None, None]
            a = active[f]
            Hinv[a], Xc[a], E[a], Sinv[a] = Hi, Xcf, Ef, Si
        a = active
        Xg = np.einsum("nfg,ng->nf", Hinv[a], g[:, free])
        dc = np.einsum("nck,nk->nc", Sinv[a], e - np.einsum("nkf,nf->nk", E[a], Xg))
        dq = -Xg - np.einsum("nfc,nc->nf", Xc[a], dc)
        step = np.concatenate([dq, dc], axis=1)
        size = np.max(np.abs(step), axis=1)
        bad = ~np.isfinite(size)                                             # singular: given up
        step[bad] = 0.0
        step *= np.minimum(1.0, asm.MAX_STEP / np.where(bad, 1.0, np.maximum(size, 1e-300)))[:, None]
        dv = np.zeros((len(a), m.nv))
        dv[:, free], dv[:, motors] = step[:, :len(free)], step[:, len(free):]
        integrate_pos(m, q, dv)
        qpos[a] = q
        rate = size / prev[a]
        with np.errstate(divide="ignore", invalid="ignore"):
            remaining = np.where(np.isfinite(prev[a]) & (rate < 0.5), size * rate / (1.0 - rate), np.inf)
        done = ~bad & ((size < tol) | (remaining < tol))
        # give a target up once its steps, shrinking at their last rate, would not reach tol in time
        with np.errstate(divide="ignore", invalid="ignore"):
            needed = np.where(rate < 1.0, np.log(tol / size) / np.log(rate), np.inf)
        bad |= ~done & (age[a] + 1 >= GIVE_UP_AFTER) & (age[a] + 1 + needed > max_iter)
        out[a[done]] = q[done]
        refresh[a] = rate > CHORD_RATE                                       # the matrix is stale
        prev[a] = size
        age[a] += 1
        active = a[~(done | bad)]
    return out
