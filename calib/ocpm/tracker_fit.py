"""Whole-chain identification from real tracker data: registration, nest offsets, blocked targets, outliers.

The physics is the same :class:`~pmcal.calib.ocpm.forward_model.ForwardModel` as in
:func:`pmcal.calib.ocpm.fullchain.identify_full`; what a tracker adds is applied outside it:

    y_ik = R_g (T_ik(x) + R_p,i  d_k) + t_g

with ``T_ik(x)`` the model's target k of pose i at the drawing coordinates, ``R_p,i`` the platform
orientation (rigid fit of ``T_i``), ``d_k`` the nest offset of target k in platform coordinates (shape
part only, :mod:`pmcal.mechanism.ocpm.nests`) and ``(R_g, t_g)`` the base frame's pose in the tracker frame
(:mod:`pmcal.calib.ocpm.registration`; identity for ``frame="base"``). Unknowns: the machine parameters
(priors as in ``identify_full``; the gauge keys held at zero in the tracker frame), the nest shape
coordinates (prior: the nest tolerance) and the registration (no prior; rotation as a small increment on
the start value). Blocked targets (NaN) contribute nothing.

Robust fit: scipy ``least_squares`` (trf) with a ``soft_l1`` loss whose scale is a few tracker sigmas,
then every target whose residual exceeds ``reject_sigma`` robust sigmas is rejected (named in
``info["rejected"]``), and a plain Gaussian fit on the kept targets gives the estimate and covariance.
More than ``max_reject_fraction`` of the rows rejected, or a residual scale many times the tracker noise,
is a bad campaign (:class:`BadCampaignError`), never a silent drop.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from pmcal.mechanism.ocpm.data import Measurements
from pmcal.mechanism.ocpm.nests import shape_basis
from pmcal.mechanism.ocpm.params import LOG_RATIO, ErrorSet, all_keys, is_angular
from pmcal.mechanism.rigid import fit_pose
from pmcal.calib.ocpm.forward_model import ForwardModel
from pmcal.calib.ocpm.fullchain import FullChainOptions, UnassembledError
from pmcal.calib.ocpm.registration import GAUGE_KEYS, rigid_fit
from pmcal.calib.solvers.result import IdentResult

#: Median of the norm of a 3-D standard normal vector (chi with 3 dof): robust scale of target residuals.
CHI3_MEDIAN = 1.5382
ROT_UNIT = 1e-3     # rad per unit of the rotation increment in the solver's vector


class BadCampaignError(ValueError):
    """Too much of the campaign disagrees with the model to be trusted (named, never silently dropped)."""


@dataclass
class TrackerOptions:
    """How the tracker side of a campaign is handled (mm, deg at the interface)."""

    frame: str = "tracker"                  # "tracker": registration identified; "base": identity
    registration0: tuple[np.ndarray, np.ndarray] | None = None   # start (R, t mm); default from the data
    fit_nests: bool = True
    nest_std_mm: float = 0.5                # nest tolerance (1 sigma per coordinate), the prior
    robust: bool = True
    f_scale_sigma: float = 3.0              # soft_l1 scale in tracker sigmas
    reject_sigma: float = 6.0               # target residual (3-D norm) beyond which it is rejected
    max_reject_fraction: float = 0.2        # more rows than this rejected: bad campaign
    max_scale_ratio: float = 5.0            # robust residual scale over tracker sigma beyond which: bad
    max_nfev: int = 60
    #: Poses the model cannot assemble (at the start, or at the parameters a stalled fit reached: poses at
    #: the edge of the workspace) are left out of the fit and named in ``info["unassembled"]``; when False
    #: they are an :class:`UnassembledError`.
    leave_out_unassembled: bool = False
    #: Machine keys held at zero in the tracker frame (the base frame's definition, the motor axes). Empty
    #: when the key set itself fixes the frame's rotation (e.g. the diagnosis baseline, passive limbs
    #: held nominal: docs/tracker_frame.md).
    gauge: tuple[str, ...] = GAUGE_KEYS

    def __post_init__(self) -> None:
        if self.frame not in ("base", "tracker"):
            raise ValueError(f"frame must be 'base' or 'tracker', got {self.frame!r}")
        if not self.nest_std_mm > 0:
            raise ValueError(f"nest tolerance must be a positive number of mm, got {self.nest_std_mm}")


@dataclass
class _Problem:
    meas: Measurements
    model: ForwardModel
    keys: list[str]
    s: np.ndarray
    x_prior: np.ndarray
    ratio0: float
    R0: np.ndarray
    t0: np.ndarray
    N: np.ndarray              # (3 k, m) nest shape basis
    nest_std: float
    tracker: bool
    fit_nests: bool
    cache: dict = field(default_factory=dict)

    @property
    def sizes(self) -> tuple[int, int, int]:
        return len(self.keys), 6 if self.tracker else 0, self.N.shape[1] if self.fit_nests else 0

    def split(self, z):
        p, g, m = self.sizes
        return z[:p], z[p:p + g], z[p + g:p + g + m]

    def registration(self, z) -> tuple[np.ndarray, np.ndarray]:
        _, g, _ = self.split(z)
        if not self.tracker:
            return np.eye(3), np.zeros(3)
        return Rotation.from_rotvec(g[:3] * ROT_UNIT).as_matrix() @ self.R0, self.t0 + g[3:]

    def nests(self, z) -> np.ndarray:
        _, _, q = self.split(z)
        k = self.N.shape[0] // 3
        return (self.N[:, :len(q)] @ (q * self.nest_std)).reshape(k, 3) if len(q) else np.zeros((k, 3))

    def evaluate(self, z):
        """Predicted tracker-frame targets (N, k, 3) and d/dz (N, k, 3, len(z)); last point cached."""
        key = z.tobytes()
        if key in self.cache:
            return self.cache[key]
        zm, _, q = self.split(z)
        self.model.set_vector(self.keys, self.x_prior + zm * self.s, self.ratio0)
        T, dT = self.model.predict_meas(self.meas, self.keys)
        X = self.model.geom.targets[: T.shape[1]]
        ok = np.isfinite(T).all(axis=(1, 2))
        Rp = np.tile(np.eye(3), (len(T), 1, 1))
        if ok.any():
            Rp[ok] = fit_pose(T[ok], X)[1]
        dn = self.nests(z)
        P = T + np.einsum("nij,kj->nki", Rp, dn)
        Rg, tg = self.registration(z)
        V = P @ Rg.T                                           # rotated, before the translation
        Y = V + tg
        J = [np.einsum("ij,nkjp->nkip", Rg, dT) * self.s]
        if self.tracker:
            E = np.eye(3)
            J.append(np.stack([np.cross(E[a], V) for a in range(3)], axis=-1) * ROT_UNIT)
            J.append(np.broadcast_to(E, Y.shape + (3,)))
        if len(q):
            Nk = self.N[:, :len(q)].reshape(-1, 3, len(q)) * self.nest_std
            J.append(np.einsum("ij,njl,klq->nkiq", Rg, Rp, Nk))
        self.cache = {key: (Y, np.concatenate(J, axis=-1))}
        return self.cache[key]

    def priors(self, z) -> np.ndarray:
        zm, _, q = self.split(z)
        return np.concatenate([zm, q])

    def prior_jac(self, n: int) -> np.ndarray:
        p, g, m = self.sizes
        P = np.zeros((p + m, n))
        P[:p, :p] = np.eye(p)
        P[p:, p + g:] = np.eye(m)
        return P


def initial_registration(meas: Measurements, model: ForwardModel) -> tuple[np.ndarray, np.ndarray]:
    """Start value of the registration from the data: rigid fit (Kabsch) of every measured target to
    where the nominal machine puts it for the row's commands. Blocked targets are left out; a
    millimetre outlier among hundreds of points moves it by micrometres."""
    model.set(ErrorSet())
    T0, _ = model.predict(meas.m_cmd_deg)
    return rigid_fit(meas.targets, T0)


def build_problem(meas: Measurements, model: ForwardModel, opt: FullChainOptions, topt: TrackerOptions
                  ) -> _Problem:
    """The unknowns of a tracker-frame fit (machine keys without the gauge, registration, nest shape)
    for a campaign, at the prior mean; also used to design campaigns (:mod:`.tracker_design`)."""
    geom = model.geom
    if opt.stiffness_ratio is not None:
        model.set(ErrorSet(), opt.stiffness_ratio)
    is_tracker = topt.frame == "tracker"
    keys = list(opt.keys or all_keys(geom.n_limbs, geom.actuated))
    if is_tracker:
        keys = [k for k in keys if k not in topt.gauge]
    ratio0 = model.stiffness_ratio if opt.stiffness_ratio is None else opt.stiffness_ratio
    if opt.fit_stiffness_ratio:
        keys = keys + [LOG_RATIO]
    s = np.array([opt.extra_prior_std.get(k, opt.priors.std(k)) for k in keys])
    x_prior = np.array([np.log(ratio0) if k == LOG_RATIO else 0.0 for k in keys])
    k_t = meas.targets.shape[1]
    R0, t0 = (np.eye(3), np.zeros(3))
    if is_tracker:
        R0, t0 = topt.registration0 if topt.registration0 is not None else initial_registration(meas, model)
    return _Problem(meas, model, keys, s, x_prior, ratio0, np.asarray(R0, float), np.asarray(t0, float),
                    shape_basis(geom.targets[:k_t]), topt.nest_std_mm, is_tracker, topt.fit_nests)


def identify_tracker(meas: Measurements, model: ForwardModel, options: FullChainOptions | None = None,
                     tracker: TrackerOptions | None = None) -> IdentResult:
    """Identify machine parameters, registration and nest offsets from a campaign (module docstring).

    Returns an :class:`IdentResult` over the machine keys (internal units, as ``identify_full``) with
    ``info["registration"]`` (``R``, ``t_mm``, ``rotvec_deg``, their standard deviations ``std_rot_deg``
    about the tracker axes and ``std_t_mm``), ``info["nests"]`` (offsets (k, 3) mm in platform
    coordinates and their standard deviations) and ``info["rejected"]`` (row index from 0, pose id,
    target number from 1, residual mm). With ``leave_out_unassembled``: ``info["unassembled"]`` (row
    from 1, pose id, ``at``: "start" for a pose the model cannot assemble at the prior mean, "fit" for one
    lost where the fit went), left out of the fit.
    """
    opt = options or FullChainOptions()
    topt = tracker or TrackerOptions()
    sigma = opt.sigma_mm or model.geom.sigma_mm
    is_tracker = topt.frame == "tracker"
    prob = build_problem(meas, model, opt, topt)
    keys, s, x_prior, ratio0 = prob.keys, prob.s, prob.x_prior, prob.ratio0
    p, g, m = prob.sizes
    y = meas.targets
    keep = meas.visible.copy()
    t_start = time.perf_counter()
    z = np.zeros(p + g + m)
    unassembled: list[tuple[int, str]] = []    # (row from 0, "start" or "fit"): the model cannot assemble it
    lost: set[int] = set()                     # rows that did not assemble at a point the solver tried

    def rows_not_assembled(Y, mask) -> np.ndarray:
        return np.flatnonzero(~np.isfinite(Y).all(axis=(1, 2)) & mask.any(axis=1))

    def leave_out(rows, when: str) -> None:
        rows = [int(i) for i in rows if keep[i].any()]
        if not rows:
            return
        if not topt.leave_out_unassembled:
            raise UnassembledError(
                f"the model cannot assemble {len(rows)} measured pose(s) {when} (rows "
                f"{', '.join(str(i + 1) for i in rows[:5])}{', ...' if len(rows) > 5 else ''}): are they "
                "inside the workspace?")
        keep[rows] = False
        unassembled.extend((i, "start" if "start" in when else "fit") for i in rows)
        if len(unassembled) > topt.max_reject_fraction * len(meas) or keep.any(axis=1).sum() < 2:
            raise BadCampaignError(
                f"bad campaign: the model cannot assemble {len(unassembled)} of {len(meas)} measured poses "
                f"(limit {topt.max_reject_fraction:.0%}; first rows "
                f"{', '.join(str(i + 1) for i, _ in sorted(unassembled)[:5])}): are they inside the workspace?")

    Y0, _ = prob.evaluate(z)
    leave_out(rows_not_assembled(Y0, keep), "at its starting parameters")

    def solve(z0, mask, loss, nfev):
        def fun(z):
            Y, _ = prob.evaluate(z)
            r = np.concatenate([((y - Y)[mask] / sigma).reshape(-1), prob.priors(z)])
            if not np.isfinite(r).all():
                lost.update(rows_not_assembled(Y, mask).tolist())
            return r

        def jac(z):
            _, J = prob.evaluate(z)
            return np.vstack([-J[mask].reshape(-1, len(z)) / sigma, prob.prior_jac(len(z))])

        return least_squares(fun, z0, jac=jac, method="trf", loss=loss, f_scale=topt.f_scale_sigma,
                             xtol=1e-10, ftol=1e-12, gtol=1e-10, max_nfev=nfev)

    def fit(z0, loss):
        """One solve; a fit that stalls where poses stop assembling (or ends at a point the model cannot
        evaluate again) leaves those poses out and starts again from the prior mean."""
        for _ in range(4):
            lost.clear()
            try:
                sol = solve(z0, keep, loss, topt.max_nfev)
            except ValueError:                 # not finite at z0: the poses the model lost are named below
                prob.cache = {}
                rows = rows_not_assembled(prob.evaluate(z0)[0], keep)
                if not rows.size:
                    raise
                leave_out(rows, "at the fit's start")
                z0 = np.zeros_like(z0)
                continue
            prob.cache = {}                    # the assembly is warm-started: evaluate sol.x afresh
            now = rows_not_assembled(prob.evaluate(sol.x)[0], keep)
            if not now.size and (sol.status > 0 or not lost):
                return sol
            leave_out(sorted(set(now.tolist()) | lost), "at the parameters the fit reached")
            z0 = np.zeros_like(z0)
            prob.cache = {}
        raise UnassembledError("the fit keeps reaching parameters at which the model cannot assemble "
                               "measured poses: are they inside the workspace?")

    rejected = []
    nfev = 0
    scale = float("nan")
    if topt.robust:
        sol = fit(z, "soft_l1")
        z, nfev = sol.x, sol.nfev
        Y, _ = prob.evaluate(z)
        e = np.linalg.norm(y - Y, axis=-1)                     # (N, k) mm, NaN where blocked
        scale = float(np.nanmedian(e) / CHI3_MEDIAN)
        if scale > topt.max_scale_ratio * sigma:
            raise BadCampaignError(
                f"bad campaign: the robust residual scale is {scale:.3g} mm, {scale / sigma:.0f} times the "
                f"tracker noise {sigma:g} mm (most rows are outliers, the noise is wrong, or the file is not "
                f"in the {'tracker' if is_tracker else 'base'} frame)")
        out = keep & (e > topt.reject_sigma * max(sigma, scale))
        rows = np.flatnonzero(out.any(axis=1))
        if len(rows) > topt.max_reject_fraction * len(meas):
            raise BadCampaignError(
                f"bad campaign: {len(rows)} of {len(meas)} rows have rejected targets (limit "
                f"{topt.max_reject_fraction:.0%}); first rows {', '.join(str(i + 1) for i in rows[:5])}")
        for i, k in np.argwhere(out):
            rejected.append({"row": int(i) + 1, "pose_id": meas.pose_id[i], "target": int(k) + 1,
                             "residual_mm": float(e[i, k])})
        keep &= ~out                   # the row's other targets stay: each is a point in the tracker frame
    sol = fit(z, "linear")
    z = sol.x
    wall = time.perf_counter() - t_start
    Y, J = prob.evaluate(z)
    A = J[keep].reshape(-1, len(z)) / sigma
    AtA = A.T @ A
    Pj = prob.prior_jac(len(z))
    cov_z = np.linalg.inv(AtA + Pj.T @ Pj)
    resid = (y - Y)[keep].reshape(-1)
    p_eff = float(np.trace(cov_z @ AtA))
    dof = len(resid) - p_eff
    x = x_prior + z[:p] * s
    cov_x = cov_z[:p, :p] * np.outer(s, s)
    info = {"sigma_mm": sigma, "stiffness_ratio": float(np.exp(x[keys.index(LOG_RATIO)]))
            if LOG_RATIO in keys else ratio0, "prior_std": s, "prior_mean": x_prior,
            "jacobian": (J[..., :p] / s).reshape(-1, p), "effective_parameters": p_eff,
            "chi2_per_dof": float(resid @ resid / sigma**2 / dof), "dof": dof, "frame": topt.frame,
            "singular_values": np.linalg.svd(A[:, :p], compute_uv=False),
            "rejected": rejected, "robust_scale_mm": scale, "n_targets_used": int(keep.sum()),
            "n_targets_blocked": int((~meas.visible).sum()),
            "unassembled": [{"row": int(i) + 1, "pose_id": meas.pose_id[i], "at": at}
                            for i, at in sorted(unassembled)],
            "gauge_fixed": list(topt.gauge) if is_tracker else []}
    if is_tracker:
        Rg, tg = prob.registration(z)
        C = cov_z[p:p + 6, p:p + 6]
        info["registration"] = {
            "R": Rg, "t_mm": tg, "rotvec_deg": np.rad2deg(Rotation.from_matrix(Rg).as_rotvec()),
            "std_rot_deg": np.rad2deg(np.sqrt(np.diag(C)[:3]) * ROT_UNIT),
            "std_t_mm": np.sqrt(np.diag(C)[3:]), "covariance": C * np.r_[[ROT_UNIT] * 3, [1.0] * 3][:, None]
            * np.r_[[ROT_UNIT] * 3, [1.0] * 3][None, :]}
    if m:
        Nq = prob.N * topt.nest_std_mm
        Cn = Nq @ cov_z[p + g:, p + g:] @ Nq.T
        info["nests"] = {"offsets_mm": prob.nests(z), "std_mm": np.sqrt(np.diag(Cn)).reshape(-1, 3),
                         "covariance": Cn, "prior_std_mm": topt.nest_std_mm}
    units = ["log" if k == LOG_RATIO else ("rad" if is_angular(k) else "mm") for k in keys]
    return IdentResult(method=f"full-chain-map-{topt.frame}", names=keys, x=x, residuals=resid,
                       covariance=cov_x, n_eval=nfev + int(sol.nfev), n_iter=nfev + int(sol.nfev),
                       wall_time=wall, success=bool(sol.success), message=str(sol.message), units=units,
                       info=info)
