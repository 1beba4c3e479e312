"""Linearised nested-model tests for the discrepancy diagnosis (numerics only).

At a fit of the whole-chain model the measurements are, to first order,
``r = y - T(x)``, whitened by the tracker noise sigma, against the derivative columns ``J`` of every
parameter: the fitted ones and the candidate effects' (their *signatures*). Columns are in units of each
parameter's prior standard deviation, so a parameter in the model contributes a prior row ``z^2``
(``z`` its value in those units; :func:`pmcal.calib.ocpm.fullchain.identify_full`'s MAP form). Everything here
is linear algebra on ``(J, r)``: fits on any subset of rows (cross-validation folds) and any set of
columns, the information an effect keeps once the model's parameters have absorbed what they can (the
Schur complement), and nested-model F tests with the null distribution of a prior-weighted chi-square
(Satterthwaite). Units: whitened (per sigma) unless stated.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats


@dataclass
class Linearization:
    """Whitened first-order model at a fit.

    r (n,) residual / sigma; J (n, m) derivative columns per prior std, / sigma; keys (m,) names of the
    columns; z0 (m,) the fit's values in prior-std units (0 for columns not in the model); pose (n,) the
    pose of every row; sigma the noise (mm) used to whiten; scale (m,) and mean (m,) the prior std and
    mean of every column: a parameter is ``mean + z * scale`` (internal units).
    """

    r: np.ndarray
    J: np.ndarray
    keys: list[str]
    z0: np.ndarray
    pose: np.ndarray
    sigma: float
    scale: np.ndarray
    mean: np.ndarray

    def values(self, sub: "SubFit") -> dict[str, float]:
        """Parameter values (internal units) after the linear fit ``sub``."""
        z = self.z0[sub.cols] + sub.dz
        return {self.keys[c]: float(self.mean[c] + zc * self.scale[c]) for c, zc in zip(sub.cols, z)}

    def cols(self, keys) -> np.ndarray:
        return np.array([self.keys.index(k) for k in keys], dtype=int)

    def rows(self, poses) -> np.ndarray:
        """Row mask of a set of poses."""
        return np.isin(self.pose, np.asarray(poses))


@dataclass
class SubFit:
    """A linear fit on some rows with some columns: step dz (prior units) from z0, residual sum of
    squares (data + prior rows, whitened), effective number of parameters, data rows used."""

    cols: np.ndarray
    dz: np.ndarray
    rss: float
    p_eff: float
    n: int
    info: np.ndarray           # J^T J of the fitted columns on these rows

    @property
    def dof(self) -> float:
        return max(self.n - self.p_eff, 1.0)


def huber_weighted(lin: Linearization, cols: np.ndarray, c: float = 2.0) -> Linearization:
    """A copy with rows weighted as a Huber M-estimator would after a fit of ``cols``: rows whose residual
    exceeds ``c`` robust standard deviations (1.4826 MAD) get weight ``c s / |r|``, applied as its square
    root to ``r`` and ``J``. Tests on it are not driven by a few outlying coordinates (heavy-tailed
    noise); Gaussian data lose ~1 % of rows' weight."""
    r = predict(lin, fit(lin, cols), np.ones(len(lin.r), bool))
    s = 1.4826 * np.median(np.abs(r - np.median(r)))
    w = np.sqrt(np.minimum(1.0, c * s / np.maximum(np.abs(r), 1e-300)))
    return Linearization(r=lin.r * w, J=lin.J * w[:, None], keys=lin.keys, z0=lin.z0, pose=lin.pose,
                         sigma=lin.sigma, scale=lin.scale, mean=lin.mean)


def fit(lin: Linearization, cols: np.ndarray, rows: np.ndarray | None = None,
        drop: np.ndarray | None = None) -> SubFit:
    """MAP least squares of ``r`` on columns ``cols`` over ``rows`` (mask), from ``z0`` with unit priors.

    Columns outside ``cols`` stay at their ``z0``, except those in ``drop``, which are set to zero (an
    effect of the fit taken out of the model). The RSS counts the prior terms of ``cols``.
    """
    rows = np.ones(len(lin.r), bool) if rows is None else rows
    J, r, z0 = lin.J[rows][:, cols], lin.r[rows], lin.z0[cols]
    if drop is not None and len(drop):
        r = r + lin.J[rows][:, drop] @ lin.z0[drop]
    H = J.T @ J
    M = H + np.eye(len(cols))
    dz = np.linalg.solve(M, J.T @ r - z0)
    res = r - J @ dz
    rss = float(res @ res + np.sum((z0 + dz) ** 2))
    p_eff = float(np.trace(np.linalg.solve(M, H)))
    return SubFit(cols=np.asarray(cols), dz=dz, rss=rss, p_eff=p_eff, n=int(rows.sum()), info=H)


def predict(lin: Linearization, sub: SubFit, rows: np.ndarray, drop: np.ndarray | None = None) -> np.ndarray:
    """Whitened residual of ``rows`` after the linear fit ``sub`` (``drop`` as in :func:`fit`)."""
    r = lin.r[rows] - lin.J[rows][:, sub.cols] @ sub.dz
    if drop is not None and len(drop):
        r = r + lin.J[rows][:, drop] @ lin.z0[drop]
    return r


def pose_leverage(lin: Linearization, cols: np.ndarray) -> np.ndarray:
    """Leverage (N,) of every pose in the fit of the columns ``cols``: the trace of the pose's block of the
    hat matrix ``J (J^T J + I)^-1 J^T`` (whitened, priors as unit rows), i.e. how many directions of the
    model the pose determines by itself (0 up to its number of coordinates; over the campaign they add up
    to the effective number of parameters). A pose near or above 1 is predicted by extrapolation when it
    is held out."""
    J = lin.J[:, cols]
    h = np.einsum("ij,ji->i", J, np.linalg.solve(J.T @ J + np.eye(len(cols)), J.T))
    return np.bincount(lin.pose, weights=h)


def conditional_information(lin: Linearization, model_cols: np.ndarray, effect_cols: np.ndarray,
                            rows: np.ndarray | None = None) -> np.ndarray:
    """Information (prior units) the data keep about ``effect_cols`` once ``model_cols`` have absorbed what
    they can: the Schur complement ``S^T S - S^T J (J^T J + I)^-1 J^T S`` = ``S_perp^T S_perp``."""
    rows = np.ones(len(lin.r), bool) if rows is None else rows
    J, S = lin.J[rows][:, model_cols], lin.J[rows][:, effect_cols]
    JtS = J.T @ S
    return S.T @ S - JtS.T @ np.linalg.solve(J.T @ J + np.eye(len(model_cols)), JtS)


@dataclass
class NestedTest:
    """Adding an effect to a model.

    delta_chi2 : whitened RSS drop; k : directions of the effect the data determine better than its
    prior (tested); p_classic : F test of the RSS drop against the residual variance (independent
    errors); p_cluster : pose-clustered Wald test; p_value : the larger of the two (both must reject);
    F : the clustered statistic; fit / base : the larger / smaller model's fits; eig : eigenvalues of the
    effect's conditional information (prior units).
    """

    delta_chi2: float
    k: int
    F: float
    p_value: float
    p_classic: float
    p_cluster: float
    n_poses: int
    fit: SubFit
    base: SubFit
    eig: np.ndarray


def nested_test(lin: Linearization, model_cols: np.ndarray, effect_cols: np.ndarray,
                rows: np.ndarray | None = None) -> NestedTest:
    """Test of ``model + effect`` against ``model`` on ``rows``.

    The effect's columns are reduced to the directions its conditional information determines better
    than its prior (eigenvalue > 1, prior units): k of them. Two tests must both reject:

    - classical: ``F = (dchi2 / k) / (RSS / dof)`` of the larger model, ``F(k, dof)``; exact for
      independent Gaussian errors, and a wrong sigma does not bias it;
    - pose-clustered Wald test: with the model projected out of the k directions (``S``), the statistic
      ``g^T V^-1 g`` (``g = S^T r``) uses the clustered covariance ``V = sum_i S_i^T e_i e_i^T S_i`` of
      the larger model's residuals per pose, leverage-corrected (``e_i = (I - H_ii)^-1/2 r_i``, CR2), with
      Hotelling's small-sample correction ``W (P - k) / (k (P - 1)) ~ F(k, P - k)`` for P poses. Errors
      shared by the nine coordinates of a pose (joint scatter, an unmodelled pose-level effect) do not
      make it anti-conservative; the classical test would be.

    If the effect is in the current fit (non-zero ``z0``), the smaller model has it at zero.
    """
    rows = np.ones(len(lin.r), bool) if rows is None else rows
    base = fit(lin, model_cols, rows, drop=effect_cols)
    big = fit(lin, np.concatenate([model_cols, effect_cols]), rows)
    delta = max(base.rss - big.rss, 0.0)
    lam, U = np.linalg.eigh(conditional_information(lin, model_cols, effect_cols, rows))
    keep = lam > 1.0
    pose = lin.pose[rows]
    P = int(np.unique(pose).size)
    k = int(keep.sum())
    if k == 0 or P - k < 2:
        return NestedTest(delta, k, 0.0, 1.0, 1.0, 1.0, P, big, base, np.clip(lam, 0, None))
    p_classic = float(stats.f.sf((delta / k) / (big.rss / big.dof), k, big.dof))
    Jm = lin.J[rows][:, model_cols]
    E = lin.J[rows][:, effect_cols] @ U[:, keep]
    S = E - Jm @ np.linalg.solve(Jm.T @ Jm + np.eye(len(model_cols)), Jm.T @ E)
    r0 = predict(lin, base, rows, drop=effect_cols)
    g = E.T @ r0
    theta = np.linalg.solve(S.T @ S, g)
    r1 = r0 - S @ theta
    X = np.hstack([Jm, S])                                   # the larger model's design (model + effect)
    Minv = np.linalg.inv(X.T @ X + np.diag(np.r_[np.ones(Jm.shape[1]), np.zeros(k)]))
    q = len(pose) // P                                      # rows of a pose (whole poses, pose-major)
    Xp, Sp, rp = X.reshape(P, q, -1), S.reshape(P, q, k), r1.reshape(P, q)
    H = (Xp @ Minv) @ np.swapaxes(Xp, 1, 2)
    w, V = np.linalg.eigh(np.eye(q) - H)                    # CR2: (I - H_ii)^(-1/2) r_i
    a = (np.swapaxes(V, 1, 2) @ rp[..., None])[..., 0] / np.sqrt(np.clip(w, 1e-12, None))
    e = (V @ a[..., None])[..., 0]
    per_pose = (np.swapaxes(Sp, 1, 2) @ e[..., None])[..., 0]
    meat = per_pose.T @ per_pose
    W = float(g @ np.linalg.lstsq(meat, g, rcond=1e-12)[0])
    F = W * (P - k) / (k * (P - 1))
    p_cluster = float(stats.f.sf(F, k, P - k))
    return NestedTest(delta, k, F, max(p_classic, p_cluster), p_classic, p_cluster, P, big, base,
                      np.clip(lam, 0, None))


def power(nc: float, nu: float, alpha: float) -> float:
    """Probability that a chi-square test of ``nu`` dof at level ``alpha`` detects noncentrality ``nc``."""
    if nu <= 0:
        return 0.0
    crit = stats.chi2.isf(alpha, nu)
    return float(stats.ncx2.sf(crit, nu, max(nc, 1e-12)))


def alpha_weights(power_at_easy_level: dict[str, float], easy_share: float, easy: float = 0.999
                  ) -> dict[str, float]:
    """Weights of the weighted Bonferroni split of the level (they sum to 1 over the candidates).

    A candidate the campaign detects at a typical size with probability >= ``easy`` even at the small
    level ``alpha * easy_share / m`` (``power_at_easy_level``) needs little of the level: the easy ones
    share ``easy_share`` of it, the others the rest, equally within each group (all equal when one group
    is empty). The weights depend on the campaign's design (the Jacobian) and the typical sizes only,
    not on the residuals, so the family-wise level holds (weighted Bonferroni); the level a test is run
    at is ``alpha * w / sum(w of the candidates in play)`` (:meth:`_Problem.level`).

    >>> alpha_weights({"backlash": 1.0, "encoder_eccentricity": 0.4}, 0.1)
    {'backlash': 0.1, 'encoder_eccentricity': 0.9}
    """
    easy_ones = [n for n, p in power_at_easy_level.items() if p >= easy]
    hard = [n for n in power_at_easy_level if n not in easy_ones]
    if not easy_ones or not hard:
        return {n: 1.0 / len(power_at_easy_level) for n in power_at_easy_level}
    return {n: easy_share / len(easy_ones) if n in easy_ones else (1.0 - easy_share) / len(hard)
            for n in power_at_easy_level}
