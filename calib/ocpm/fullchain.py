"""Whole-closed-chain calibration of the over-constrained PM (issue: get past the paper's accuracy limit).

Forward model: the pose the machine reaches for motor commands, given the full parameter set (all four
limbs, SS, motor zero offsets, closure stiffness ratio) and the same closure-compliance physics as the
twin: it *is* the twin's quasi-static solve (:class:`pmcal.twin.ocpm.machine.Twin`) with the candidate parameters,
differentiated analytically (:mod:`pmcal.twin.ocpm.sensitivity`).

Identification: maximum a posteriori least squares on the raw target coordinates,

    min_x  sum |(y_meas - y(x)) / sigma|^2 + sum (x_i / s_i)^2

with ``s_i`` the manufacturing tolerance of each parameter (the prior regularises the directions the
data cannot see, instead of a hard truncation). Solved with ``scipy.optimize.least_squares`` (trust
region, analytic Jacobian). Covariance: ``(J^T J / sigma^2 + diag(1/s^2))^-1``.

Compensation (:func:`chain_commands_deg`): the motor commands that make the identified machine point at
each target orientation, solved by the model itself when it can
(:class:`pmcal.calib.ocpm.forward_model.AimingModel`), else by Newton on the forward model.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from pmcal.mechanism.ocpm.data import Measurements
from pmcal.mechanism.ocpm.kinematics import nominal_ik
from pmcal.mechanism.ocpm.params import LOG_RATIO, ErrorSet, all_keys, is_angular
from pmcal.mechanism.rotations import tilt_torsion
from pmcal.calib.ocpm.forward_model import AimingModel, ForwardModel
from pmcal.calib.solvers.result import IdentResult


@dataclass
class Priors:
    """Manufacturing tolerances (1 sigma) used as priors: positions/lengths mm, angles deg."""

    position_mm: float = 1.0
    angle_deg: float = 0.3
    zero_offset_deg: float = 2.0
    log_ratio: float = 2.0          # the stiffness ratio is known within a factor e^2 ~ 7

    def std(self, key: str) -> float:
        """Prior std of ``key`` in internal units (mm, rad)."""
        if key == LOG_RATIO:
            return self.log_ratio
        if key.endswith("dtheta"):
            return np.deg2rad(self.zero_offset_deg)
        return np.deg2rad(self.angle_deg) if is_angular(key) else self.position_mm


@dataclass
class FullChainOptions:
    keys: list[str] | None = None           # parameters to identify (default: every key)
    fit_stiffness_ratio: bool = False
    stiffness_ratio: float | None = None    # initial / fixed ratio (default machine.toml)
    priors: Priors = field(default_factory=Priors)
    sigma_mm: float | None = None           # tracker noise (default machine.toml)
    max_nfev: int = 50
    #: Prior std (internal units) of keys outside the geometric vocabulary, e.g. the effect parameters
    #: of :class:`pmcal.twin.ocpm.effect_model.EffectChainModel`; their prior mean is 0.
    extra_prior_std: dict[str, float] = field(default_factory=dict)
    #: Start values (internal units) instead of the prior mean, e.g. a previous fit (warm start).
    x0: dict[str, float] | None = None


class UnassembledError(ValueError):
    """Measured poses the model cannot assemble at the start of a fit (outside its workspace)."""


def identify_full(meas: Measurements, model: ForwardModel, options: FullChainOptions | None = None
                  ) -> IdentResult:
    """Identify the whole-chain parameters from measured targets (see module docstring)."""
    opt = options or FullChainOptions()
    geom = model.geom
    if opt.stiffness_ratio is not None:
        model.set(ErrorSet(), opt.stiffness_ratio)
    sigma = opt.sigma_mm or geom.sigma_mm
    keys = list(opt.keys or all_keys(geom.n_limbs, geom.actuated))
    ratio0 = model.stiffness_ratio if opt.stiffness_ratio is None else opt.stiffness_ratio
    if opt.fit_stiffness_ratio:
        keys = keys + [LOG_RATIO]
    s = np.array([opt.extra_prior_std[k] if k in opt.extra_prior_std else opt.priors.std(k) for k in keys])
    x_prior = np.array([np.log(ratio0) if k == LOG_RATIO else 0.0 for k in keys])
    z_start = np.zeros(len(keys)) if not opt.x0 else \
        np.array([(opt.x0[k] - xp) / sk if k in opt.x0 else 0.0 for k, xp, sk in zip(keys, x_prior, s)])
    y = meas.targets.reshape(-1)
    n_eval = 0
    cache: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}
    accepted: list[bytes | None] = [None]

    def evaluate(z: np.ndarray):
        nonlocal n_eval
        key = z.tobytes()
        if key not in cache:
            model.set_vector(keys, x_prior + z * s, ratio0)
            T, dT = model.predict_meas(meas, keys)
            n_eval += 1
            # Keep the last accepted point: re-solving it from another warm start near the workspace
            # edge need not give the same poses.
            for k in [k for k in cache if k != accepted[0]]:
                del cache[k]
            cache[key] = (T.reshape(-1), dT.reshape(len(y), len(keys)))
        return cache[key]

    def fun(z):
        T, _ = evaluate(z)
        return np.concatenate([(y - T) / sigma, z])

    def jac(z):                                       # scipy asks for it at accepted points only
        _, dT = evaluate(z)
        accepted[0] = z.tobytes()
        return np.vstack([-dT * (s / sigma), np.eye(len(z))])

    def unassembled(z):
        """Rows (0-based) of the poses the model cannot assemble at ``z``."""
        return np.flatnonzero(~np.isfinite(evaluate(z)[0].reshape(len(meas), -1)).any(axis=1))

    t0 = time.perf_counter()
    if opt.x0 and unassembled(z_start).size:
        z_start = np.zeros(len(keys))                 # the model cannot assemble every pose there
    bad = unassembled(z_start)
    if bad.size:
        raise UnassembledError(f"the model cannot assemble {len(bad)} measured pose(s) at its starting "
                               f"parameters (rows {', '.join(str(i + 1) for i in bad[:5])}"
                               f"{', ...' if len(bad) > 5 else ''}): are they inside the workspace?")
    sol = least_squares(fun, z_start, jac=jac, method="trf", x_scale=1.0,
                        xtol=1e-10, ftol=1e-12, gtol=1e-10, max_nfev=opt.max_nfev)
    wall = time.perf_counter() - t0
    x = x_prior + sol.x * s
    T, dT = evaluate(sol.x)
    resid = y - T
    A = dT / sigma
    AtA = A.T @ A
    cov = np.linalg.inv(AtA + np.diag(1.0 / s**2))
    p_eff = float(np.trace(cov @ AtA))                 # effective number of fitted parameters
    dof = len(y) - p_eff
    units = ["log" if k == LOG_RATIO else ("rad" if is_angular(k) else "mm") for k in keys]
    return IdentResult(
        method="full-chain-map", names=keys, x=x, residuals=resid, covariance=cov, n_eval=n_eval,
        n_iter=int(sol.nfev), wall_time=wall, success=bool(sol.success), message=str(sol.message),
        units=units,
        info={"sigma_mm": sigma,
              "stiffness_ratio": float(np.exp(x[keys.index(LOG_RATIO)])) if LOG_RATIO in keys else ratio0,
              "singular_values": np.linalg.svd(A, compute_uv=False), "prior_std": s, "prior_mean": x_prior,
              "jacobian": dT,     # d targets / d x at the solution, (9 N, len(keys)) mm per internal unit
              "effective_parameters": p_eff, "chi2_per_dof": float(resid @ resid / sigma**2 / dof),
              "dof": dof})


def platform_normals(targets: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Platform normals (N, 3) of rigid fits of targets (N, k, 3) to platform coordinates X."""
    from pmcal.mechanism.rigid import fit_pose

    _, R, _ = fit_pose(targets, X)
    return R[:, :, 2]


def chain_commands_deg(model: ForwardModel, errors: ErrorSet, phi_deg, theta_deg,
                       stiffness_ratio: float | None = None, tol_deg: float = 1e-10, max_iter: int = 20
                       ) -> np.ndarray:
    """Motor commands (N, 2) deg that make the machine described by ``errors`` (internal units: mm, rad)
    and the closure ``stiffness_ratio`` point its platform normal at the tilt-torsion orientations
    (``phi_deg``, ``theta_deg``) deg (base frame). Targets out of reach come back as NaN: outside the
    nominal workspace, not assembled by the model, or not converged.

    A model that solves this directly (:class:`pmcal.calib.ocpm.forward_model.AimingModel`, e.g. the twin's
    :class:`pmcal.twin.ocpm.forward.FullChainModel`) does. Otherwise: Newton on the forward model, the residual
    the platform normal's offset from the target normal in the target's tangent plane (2 equations, 2
    motors), derivatives from the implicit function theorem, stopped when the offset is below
    ``tol_deg`` or after ``max_iter`` steps. It starts from the nominal IK, vectorised across targets,
    and each step predicts only the targets not yet converged (a model that keeps its last equilibria,
    like the twin's, warm-starts from them).
    """
    model.set(errors, stiffness_ratio)
    if isinstance(model, AimingModel):
        cmd = model.aim_commands_deg(phi_deg, theta_deg)
        if cmd is not None:
            return cmd
    phi, theta = np.deg2rad(np.atleast_1d(phi_deg)), np.deg2rad(np.atleast_1d(theta_deg))
    Rt = tilt_torsion(phi, theta)                          # target frames: normal = third column
    cmd = np.rad2deg(nominal_ik(phi, theta, model.geom)) - np.rad2deg(errors.dtheta[:2])
    X = model.geom.targets
    keys = ["L1.dtheta", "L2.dtheta"]
    done = np.zeros(len(phi), bool)
    active = np.flatnonzero(np.isfinite(cmd).all(axis=1))
    for _ in range(max_iter):
        if active.size == 0:
            break
        T, dT = model.predict(cmd[active], keys)
        ok = np.isfinite(T).all(axis=(1, 2))
        active, T, dT = active[ok], T[ok], dT[ok]
        w = platform_normals(T, X)
        u, v = Rt[active, :, 0], Rt[active, :, 1]
        e = np.stack([np.einsum("ni,ni->n", u, w), np.einsum("ni,ni->n", v, w)], 1)
        conv = np.abs(e).max(axis=1) < np.deg2rad(tol_deg)
        done[active[conv]] = True
        keep = ~conv
        active, T, dT, w, u, v, e = active[keep], T[keep], dT[keep], w[keep], u[keep], v[keep], e[keep]
        if active.size == 0:
            break
        h = 1e-6                                           # d normal / d targets by a small rigid fit step
        dw = np.stack([(platform_normals(T + h * dT[..., c], X) - w) / h for c in range(2)], axis=-1)
        Je = np.stack([np.einsum("ni,nic->nc", u, dw), np.einsum("ni,nic->nc", v, dw)], 1)
        regular = np.abs(np.linalg.det(Je)) > 0           # a singular step: the target is given up
        active, Je, e = active[regular], Je[regular], e[regular]
        step = -np.linalg.solve(Je, e[..., None])[..., 0]  # rad
        cmd[active] += np.rad2deg(step)
    cmd[~done] = np.nan
    return cmd
