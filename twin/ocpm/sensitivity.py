"""Derivatives of the twin's equilibrium with respect to its parameters (implicit function theorem).

At equilibrium the gradient of the elastic energy vanishes on the free joints F:
``g(q, p) = J_F^T r = 0`` with ``r`` the stiffness-weighted closure residual. Differentiating,

    dq_F/dp = -(J_F^T J_F)^{-1} J_F^T dr/dp

(the Gauss-Newton Hessian; the dropped curvature terms are of the relative size of the closure gaps
over the link lengths, ~0.5 % with mm-size errors, and vanish on a consistent machine). The targets
follow as ``dT/dp = J_T dq_F/dp + (dT/dp at fixed q)``. ``dr/dp`` at fixed joint angles is geometry:
moving B_j moves S1_j, tilting an axis turns a link about its joint, and so on (see the code).

Parameters are the interface keys of :mod:`pmcal.mechanism.ocpm.params` in internal units (mm, rad), the motor
commands (``L1.dtheta``/``L2.dtheta`` act exactly like commands), and optionally the logarithm of the
stiffness ratio (key :data:`LOG_RATIO`). Results are in mm per unit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pmcal.mechanism.ocpm.kinematics import limb_frames
from pmcal.mechanism.ocpm.params import LOG_RATIO
from pmcal.twin.ocpm.assembly import _ChainJacobian
from pmcal.twin.closures import solve_stacked
from pmcal.twin.ocpm.model import MM

_E = np.eye(3)


@dataclass
class Sensitivity:
    """targets (N, k, 3) mm at the equilibria; d_targets (N, k, 3, n_keys) mm per unit of each key;
    dq (N, n_free, n_keys) the free joints' derivatives (rad or m per unit; ball joints in their body
    frame, MuJoCo's velocity convention) over the free dof indices ``free``: the tangent along which a
    warm start can follow a parameter or command change."""

    targets: np.ndarray
    d_targets: np.ndarray
    keys: list[str]
    dq: np.ndarray | None = None
    free: np.ndarray | None = None


def target_sensitivity(twin, qpos: np.ndarray, keys: list[str]) -> Sensitivity:
    """Targets and their derivatives w.r.t. ``keys`` at equilibrium configurations ``qpos`` (N, nq)."""
    asm, idx, geom, e = twin.assembler, twin.index, twin.geom, twin.errors
    lin = asm.linearize(qpos)
    N = len(qpos)
    n_limbs = len(idx.site_s1)
    S1, S2 = lin.site_xpos[:, idx.site_s1], lin.site_xpos[:, idx.site_s2]
    B, A = lin.xpos[:, idx.link1], lin.xpos[:, idx.link2]
    Rp, Rss = lin.xmat[:, idx.platform], lin.xmat[:, idx.ss_link]
    Q1 = limb_frames(geom.psi, e.dalpha, e.dgamma)
    Q2 = limb_frames(geom.psi, e.dmu, e.dnu)
    k_t = len(idx.site_targets)
    n_res = lin.res.shape[1]
    DR = np.zeros((N, n_res, len(keys)))                  # weighted residual derivatives
    DT = np.zeros((N, k_t, 3, len(keys)))                 # direct target derivatives at fixed q, m
    w = asm._w.reshape(n_limbs, 3)

    def gap(col: int, j: int, v: np.ndarray) -> None:     # v (N, 3): d(S1_j - S2_j)/dp in m
        DR[:, 3 * j:3 * j + 3, col] += v * w[j]

    for col, key in enumerate(keys):
        if key == LOG_RATIO:
            mask = np.zeros(n_res)
            for j in geom.actuated:
                mask[3 * (j - 1):3 * j] = 1.0
            mask[3 * n_limbs] = 1.0                       # the SS row (motor-spring rows may follow)
            DR[:, :, col] = lin.res * mask
            continue
        group, name = key.split(".", 1)
        if group == "SS":
            if name == "dh":
                delta = Rss[:, :, 2] * MM                  # platform slides along the SS limb
            else:
                delta = -Rp[:, :, "xyz".index(name[-1])] * MM   # platform moves against its joint
            for j in range(n_limbs):
                gap(col, j, -delta)
            DT[:, :, :, col] = delta[:, None, :]
            continue
        j = int(group[1:]) - 1
        if name in ("dbx", "dby", "dbz"):
            gap(col, j, np.broadcast_to(_E["xyz".index(name[-1])] * MM, (N, 3)))
        elif name == "dalpha":
            gap(col, j, np.cross(Q1[j][:, 0], S1[:, j] - B[:, j]))
        elif name == "dgamma":
            gap(col, j, np.cross(_E[2], S1[:, j] - B[:, j]))
        elif name == "dl1":
            u = S1[:, j] - B[:, j]
            gap(col, j, u / np.linalg.norm(u, axis=1, keepdims=True) * MM)
        elif name in ("dax", "day", "daz"):
            gap(col, j, -Rp[:, :, "xyz".index(name[-1])] * MM)
        elif name == "dmu":
            gap(col, j, -np.cross(Rp @ Q2[j][:, 0], S2[:, j] - A[:, j]))
        elif name == "dnu":
            gap(col, j, -np.cross(Rp[:, :, 2], S2[:, j] - A[:, j]))
        elif name == "dl2":
            u = S2[:, j] - A[:, j]
            gap(col, j, -u / np.linalg.norm(u, axis=1, keepdims=True) * MM)
        elif name == "dtheta":
            if getattr(asm, "motor_stiffness", None) is None:
                DR[:, :, col] = lin.J[:, :, idx.dadr_base[j]]
            else:                                         # series spring: its rest angle moves
                DR[:, 3 * n_limbs + 1 + j, col] = -np.sqrt(asm.motor_stiffness[j])
        else:
            raise KeyError(f"no sensitivity for '{key}'")
    free = lin.free
    JF = lin.J[:, :, free]
    JFt = np.swapaxes(JF, 1, 2)
    dq = -solve_stacked(JFt @ JF, JFt @ DR)                           # (N, n_free, n_keys)
    if not hasattr(twin, "_target_jac"):
        twin._target_jac = _ChainJacobian(twin.model, idx.site_targets)
    JT = twin._target_jac.sites(lin.site_xpos[:, idx.site_targets], lin.xanchor, lin.xaxis,
                                lin.xmat.reshape(N, -1, 9))[..., free]   # (N, k, 3, n_free)
    d_targets = (np.einsum("nkif,nfp->nkip", JT, dq) + DT) / MM
    return Sensitivity(targets=lin.site_xpos[:, idx.site_targets] / MM, d_targets=d_targets, keys=list(keys),
                       dq=dq, free=free)
