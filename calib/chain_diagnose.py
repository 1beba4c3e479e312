"""Where a closed-chain machine's geometric model and its measurements disagree, and why, for any machine
described as data (:class:`pmcal.calib.chain_model.ChainModel`).

Starting point: the geometric identification (:func:`pmcal.calib.closed_chain.identify_chain`) and its
residuals, whitened by the tracker noise. Around it the model is linear: residual ``r = J_b d + G_f t + e``
with ``J_b`` the base errors' Jacobian (prior as in identification) and ``G_f`` the columns of a candidate
effect family ``f``. The families are those any machine can show, written through the machine's own
derivatives (no machine-specific model):

- ``backlash``: per motor, the joint lags the command by half its dead band against the direction of the
  last move, ``joint = command - (B_k / 2) s_k`` (``s_k`` = +1 / -1 from the row order, 0 before the first
  move); the value is the **full dead band** ``B_k`` (deg or mm).
- ``zero_drift``: per motor, the zero moves linearly with time, ``joint = command + w_k t`` (deg/h, mm/h).
- ``frame_drift``: the base (or the tracker) moves rigidly during the campaign: every measured point
  ``y`` moves by ``(v + w x y) t`` (``v`` mm/h, ``w`` deg/h).
- ``thermal_expansion``: the machine grows uniformly with its temperature, every point by
  ``alpha (T - T_mean) y`` (1/K; exact for a machine of one material with revolute motors).

Without a ``time_s`` column, time is the row order (units "pose"); without ``temp_c`` the thermal family
is not tested.

**A name is earned on rows the fit did not see.** A family is named when (1) its columns lower the
whitened residual sum of squares significantly (F-test, Bonferroni over the candidates, family-wise
:data:`ALPHA`), (2) added to the model it removes at least :data:`HELD_OUT_SHARE` of the structure beyond
the noise on held-out rows, under two splits: random folds and folds of whole workspace regions (an effect
transfers across the workspace; an alias fitted to another shape does not), each split's noise-only level
calibrated on noise-only campaigns run through the same folds, and (3) its values are
plausible (:data:`PLAUSIBLE`). Families are added one at a time, the strongest first, while the random
folds' held-out residual stays more than 3 standard deviations above its noise-only level. What is left
beyond the noise on held-out rows is reported as unexplained, with what it follows most (time, temperature, a
motor's command, a motor's direction of approach), never under a family's name.

Units: residuals mm; values as above.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import stats

from pmcal.calib.chain_model import ChainModel
from pmcal.calib.closed_chain import ChainIdentResult, base_prior_cov, flat_jacobian
from pmcal.mechanism.motion import approach_from_order

#: family-wise false-name rate of the significance test
ALPHA = 0.01
#: share of the held-out structure beyond the noise a family must remove to be named
HELD_OUT_SHARE = 0.5
#: folds of each held-out split
FOLDS = 5
#: noise-only campaigns that calibrate a held-out residual's spread
NULL_DRAWS = 200
#: largest plausible value of each family (per parameter, its unit)
PLAUSIBLE = {"backlash": 2.0, "zero_drift": 2.0, "frame_drift": 5.0, "thermal_expansion": 60e-6}
#: what to do about each family
FIX = {"backlash": "compensate the dead band per motor (approach from one side, or add B/2 against the move)",
       "zero_drift": "re-reference the motor (homing) or warm the drive up before measuring",
       "frame_drift": "fix the machine's base and the tracker, and re-measure the reference nests during the "
                      "campaign",
       "thermal_expansion": "measure at the working temperature, or compensate the scale with temperature"}


@dataclass
class NamedEffect:
    """A family the data show: ``values`` per parameter (``labels``, ``units``) with ``std`` and 95 %
    ``interval``; ``motors`` the motors whose own value differs from zero at 95 % (per-motor families);
    ``held_out_share`` the share of the held-out structure it removed; ``p_value`` its test's
    (Bonferroni-adjusted); ``fix`` what to do."""

    name: str
    labels: list[str]
    units: list[str]
    values: np.ndarray
    std: np.ndarray
    held_out_share: float
    p_value: float
    motors: list[str] = field(default_factory=list)
    fix: str = ""

    @property
    def interval(self) -> np.ndarray:
        return np.stack([self.values - 1.96 * self.std, self.values + 1.96 * self.std], axis=1)

    def headline(self) -> str:
        pairs = [(lab, v, s, u) for lab, v, s, u in zip(self.labels, self.values, self.std, self.units)
                 if not self.motors or lab.split(".")[0] in self.motors]
        what = ", ".join(f"{lab} {v:.4g} +- {1.96 * s:.2g} {u}" for lab, v, s, u in pairs)
        who = f" ({', '.join(self.motors)})" if self.motors else ""
        return f"{self.name}{who}: {what}"


@dataclass
class ChainDiagnosis:
    """Result of :func:`diagnose_chain`.

    verdict : ``"noise"`` (nothing beyond the tracker noise), ``"named"``, ``"unexplained"`` or
        ``"named+unexplained"``. named : the :class:`NamedEffect` s in the order named. candidates : per
        family tested, a dict of its statistics and the reason it was or was not named. gap_before,
        gap_after : RMS held-out residual (mm, random folds) of the geometric model and with the named
        families.
        noise_mm : the tracker noise used. unexplained : the structure left (``excess_mm``) and its
        correlates (``context``, ``share``, ``p_value``), strongest first; empty when nothing is left.
        time_unit : ``"h"`` or ``"pose"``.
    """

    verdict: str
    named: list[NamedEffect]
    candidates: list[dict]
    gap_before: float
    gap_after: float
    noise_mm: float
    unexplained: dict
    time_unit: str

    @property
    def found_unnamed(self) -> list[dict]:
        """Candidates significant (p <= ALPHA) but not named (held-out share, implausible values), most
        significant first: what the verdict must not call noise."""
        found = [c for c in self.candidates if c.get("verdict") != "named" and c.get("p_value", 1.0) <= ALPHA]
        return sorted(found, key=lambda c: c["p_value"])

    def summary(self) -> str:
        """One line: the verdict and what was named; it agrees with the candidates (a significant one that was
        not named is said with its p-value and why)."""
        found = "; ".join(f"{c['name']} (p = {c['p_value']:.2g}, {c['verdict']})" for c in self.found_unnamed)
        if self.verdict == "noise":
            if found:
                return (f"no effect named, but significant: {found}; held-out residual {self.gap_before:.4f} mm "
                        f"RMS (noise {self.noise_mm:g} mm per coordinate)")
            return (f"nothing beyond the tracker noise: held-out residual {self.gap_before:.4f} mm RMS "
                    f"(noise {self.noise_mm:g} mm per coordinate)")
        parts = [e.headline() for e in self.named]
        if self.unexplained:
            best = self.unexplained["correlates"][0] if self.unexplained["correlates"] else None
            parts.append(f"unexplained structure {self.unexplained['excess_mm']:.4f} mm"
                         + (f", follows {best['context']} ({best['share']:.0%} of it)" if best else ""))
        elif found:
            parts.append(f"significant but not named: {found}")
        return f"{'; '.join(parts)}; held-out gap {self.gap_before:.4f} -> {self.gap_after:.4f} mm"


def _motor_jacobian(model: ChainModel, commands: np.ndarray, params) -> np.ndarray:
    """d targets / d motor joint (N, K, 3, M), mm per command unit: the zero offsets' exact Jacobian when the
    model has them, else central differences on the commands."""
    M = commands.shape[1]
    keys = [f"m{k + 1}.dzero" for k in range(M)]
    if all(k in model.error_keys for k in keys):
        return model.jacobian(commands, params, keys)
    h = 1e-3
    out = []
    for k in range(M):
        step = np.zeros(M)
        step[k] = h
        out.append((model.targets(commands + step, params) - model.targets(commands - step, params)) / (2 * h))
    return np.stack(out, axis=-1)


def _families(model, commands, y, params, t, temp, time_unit, units):
    """``name -> (G (n_rows, p) mm per unit, labels, units)`` of the families the data's context allows."""
    N, K, _ = y.shape
    M = commands.shape[1]
    Jm = _motor_jacobian(model, commands, params)                   # (N, K, 3, M)
    s = approach_from_order(commands)
    fam = {"backlash": (-0.5 * Jm * s[:, None, None, :], [f"m{k + 1}.dead_band" for k in range(M)], units)}
    tt = t - t.mean()
    fam["zero_drift"] = (Jm * tt[:, None, None, None], [f"m{k + 1}.rate" for k in range(M)],
                         [f"{u}/{time_unit}" for u in units])
    G = np.zeros((N, K, 3, 6))
    G[..., :3] = np.eye(3) * tt[:, None, None, None]
    w = np.deg2rad(1.0)
    for a in range(3):                                               # d(w x y)/dw_a = e_a x y
        e = np.zeros(3)
        e[a] = 1.0
        G[..., 3 + a] = np.cross(e, y) * w * tt[:, None, None]
    fam["frame_drift"] = (G, ["v_x", "v_y", "v_z", "w_x", "w_y", "w_z"],
                          [f"mm/{time_unit}"] * 3 + [f"deg/{time_unit}"] * 3)
    if temp is not None and np.ptp(temp) >= 1.0:
        fam["thermal_expansion"] = ((y * (temp - temp.mean())[:, None, None])[..., None], ["alpha"], ["1/K"])
    return {k: (g.reshape(N * K * 3, -1), lab, u) for k, (g, lab, u) in fam.items()}


def _carriers(effect: NamedEffect) -> list[str]:
    """The motors whose own value of a per-motor family differs from zero at 95 %, Bonferroni over the
    motors (none for the other families)."""
    if effect.name not in ("backlash", "zero_drift"):
        return []
    z = stats.norm.ppf(1.0 - 0.025 / len(effect.values))
    return [lab.split(".")[0] for lab, v, s in zip(effect.labels, effect.values, effect.std) if abs(v) > z * s]


def _region_folds(commands: np.ndarray, n: int, rng) -> np.ndarray:
    """Fold index per pose: ``n`` regions of the command space (k-means, a few iterations)."""
    X = (commands - commands.mean(axis=0)) / (commands.std(axis=0) + 1e-12)
    centres = X[rng.choice(len(X), n, replace=False)]
    for _ in range(20):
        lab = np.argmin(((X[:, None] - centres[None]) ** 2).sum(axis=2), axis=1)
        centres = np.array([X[lab == j].mean(axis=0) if np.any(lab == j) else centres[j] for j in range(n)])
    return lab


class _Linear:
    """The whitened linear model around the baseline: base columns with their prior, family columns free."""

    def __init__(self, r, Jb, prior_prec, rows_per_pose):
        self.r, self.Jb, self.P = r, Jb, prior_prec
        self.k = rows_per_pose
        self._null = None

    def fit(self, G, rows=None):
        """(coefficients, covariance, residual) of the fit on ``rows`` (pose indices; default all)."""
        A = np.concatenate([self.Jb, G], axis=1) if G is not None else self.Jb
        idx = self._rows(rows)
        nb = self.Jb.shape[1]
        N = A[idx].T @ A[idx]
        N[:nb, :nb] += self.P
        cov = np.linalg.pinv(N, hermitian=True)
        x = cov @ (A[idx].T @ self.r[idx])
        return x, cov, self.r - A @ x

    def _rows(self, poses):
        if poses is None:
            return slice(None)
        return (np.asarray(poses)[:, None] * self.k + np.arange(self.k)).ravel()

    def held_out(self, G, folds, cov_all: np.ndarray) -> tuple[float, float, float]:
        """Mean squared whitened residual on held-out poses, each fold fitted on the others, with the mean
        and standard deviation it has when the model is right: the same folds run on :data:`NULL_DRAWS`
        campaigns ``d = J_b z + e`` (tracker noise ``e``, base errors ``z`` from their prior, whose pull the
        fit carries) turned into this model's residuals (``d - A C A^T d``, the full fit's, ``C = cov_all``
        of :meth:`fit` on every row). Exact for the linear model, folds' correlations included: where a
        fold extrapolates, its poses share one prediction error and both the mean and the spread grow."""
        A = np.concatenate([self.Jb, G], axis=1) if G is not None else self.Jb
        if self._null is None:            # noise, plus base errors drawn from their prior (its shrinkage)
            rng = np.random.default_rng(12345)
            L = np.linalg.cholesky(np.linalg.inv(self.P))
            self._null = rng.normal(size=(self.r.size, NULL_DRAWS)) + self.Jb @ (L @ rng.normal(
                size=(self.Jb.shape[1], NULL_DRAWS)))
        R0 = self._null - A @ (cov_all @ (A.T @ self._null))
        R = np.concatenate([self.r[:, None], R0], axis=1)
        nb = self.Jb.shape[1]
        sq, n = np.zeros(R.shape[1]), 0
        for f in np.unique(folds):
            train, rows = self._rows(np.flatnonzero(folds != f)), self._rows(np.flatnonzero(folds == f))
            N = A[train].T @ A[train]
            N[:nb, :nb] += self.P
            X = np.linalg.pinv(N, hermitian=True) @ (A[train].T @ R[train])
            E = R[rows] - A[rows] @ X
            sq += np.einsum("ij,ij->j", E, E)
            n += len(rows)
        mse = sq / n
        return float(mse[0]), float(mse[1:].mean()), float(mse[1:].std())

def diagnose_chain(model: ChainModel, commands, targets, baseline: ChainIdentResult, *, time_s=None,
                   temp_c=None, motor_units: list[str] | None = None, seed: int = 0) -> ChainDiagnosis:
    """Find, name and characterise what the geometric model ``baseline`` leaves in a campaign (module
    docstring).

    Parameters
    ----------
    model : the machine. commands : (N, M) deg / mm, in the order driven. targets : (N, K, 3) mm.
    baseline : its geometric identification on these rows (:func:`pmcal.calib.closed_chain.identify_chain`).
    time_s, temp_c : (N,) optional context columns. motor_units : ``"deg"`` / ``"mm"`` per motor (default
    deg). seed : the random folds.

    Returns
    -------
    ChainDiagnosis

    Examples
    --------
    >>> res = identify_chain(twin, meas.commands, meas.targets)                        # doctest: +SKIP
    >>> diagnose_chain(twin, meas.commands, meas.targets, res, time_s=meas.time_s).summary()  # doctest: +SKIP
    'backlash (m2): m2.dead_band 0.0398 +- 0.0031 deg; held-out gap 0.0243 -> 0.0171 mm'
    """
    commands = np.atleast_2d(np.asarray(commands, float))
    y = np.asarray(targets, float)
    ok = np.isfinite(commands).all(axis=1) & np.isfinite(y).all(axis=(1, 2))
    commands, y = commands[ok], y[ok]
    time_s = None if time_s is None else np.asarray(time_s, float)[ok]
    temp_c = None if temp_c is None else np.asarray(temp_c, float)[ok]
    has_time = time_s is not None and np.isfinite(time_s).all() and np.ptp(time_s) > 0
    t, unit = (time_s / 3600.0, "h") if has_time else (np.arange(len(y), dtype=float), "pose")
    temp = temp_c if temp_c is not None and np.isfinite(temp_c).all() else None
    sigma = baseline.sigma_mm
    p = baseline.params
    base = baseline.base
    r = (y - model.targets(commands, p)).reshape(-1) / sigma
    Jb = flat_jacobian(model, commands, p, base) / sigma
    lin = _Linear(r, Jb, np.linalg.inv(base_prior_cov(model, baseline.basis)), y.shape[1] * 3)
    units = list(motor_units or ["deg"] * commands.shape[1])
    fams = {k: (g / sigma, lab, u) for k, (g, lab, u) in
            _families(model, commands, y, p, t, temp, unit, units).items()}
    rng = np.random.default_rng(seed)
    splits = [rng.permutation(len(y)) % FOLDS, _region_folds(commands, FOLDS, rng)]
    n_rows = r.size

    def columns(names: list[str]) -> np.ndarray | None:
        return np.concatenate([fams[c][0] for c in names], axis=1) if names else None

    def chi2_of(G) -> float:
        _, _, res = lin.fit(G)
        return float(res @ res)

    def stats_of(G):
        """The fit on every row (coefficients, covariance, residual sum of squares) and per split the
        held-out (mean square, its noise-only mean and standard deviation)."""
        x, cov, res = lin.fit(G)
        return x, cov, float(res @ res), [lin.held_out(G, s, cov) for s in splits]

    def excess(ho) -> float:
        """Held-out structure beyond the noise, in standard deviations of a noise-only held-out residual,
        on random folds (the region folds extrapolate: their spread under noise alone has a long tail, so
        they judge whether a name transfers, not whether structure is there)."""
        a, b, sd = ho[0]
        return (a - b) / sd

    noise_band = 3.0                                            # standard deviations
    _, _, chi_cur, ho_cur = stats_of(None)
    ho_base = ho_cur
    chosen: list[str] = []
    named: list[NamedEffect] = []
    candidates = {k: {"name": k, "verdict": "not significant"} for k in fams}
    while excess(ho_cur) > noise_band:
        best = None
        remaining = [k for k in fams if k not in chosen]
        for k in remaining:
            G = columns(chosen + [k])
            x, cov, chi, ho = stats_of(G)
            q = fams[k][0].shape[1]
            dof = n_rows - Jb.shape[1] - G.shape[1]
            F = ((chi_cur - chi) / q) / (chi / dof)
            pval = min(1.0, float(stats.f.sf(F, q, dof)) * len(remaining))
            share = min([(a[0] - b[0]) / (a[0] - a[1]) for a, b in zip(ho_cur, ho) if a[0] > a[1]] or [0.0])
            vals = x[-q:]
            std = np.sqrt(np.clip(np.diag(cov)[-q:], 0.0, None))
            plausible = bool(np.all(np.abs(vals) <= PLAUSIBLE[k]))
            cand = {"name": k, "F": F, "p_value": pval, "held_out_share": share, "plausible": plausible}
            if pval > ALPHA:
                cand["verdict"] = "not significant"
            elif share < HELD_OUT_SHARE:
                cand["verdict"] = (f"does not hold on held-out rows (removes {share:.0%} of the structure, "
                                   f"{HELD_OUT_SHARE:.0%} needed)")
            elif not plausible:
                cand["verdict"] = "implausible values"
            else:
                cand["verdict"] = "named"
                if best is None or F > best[1]["F"]:
                    best = (k, cand, chi, ho, vals, std)
            candidates[k] = cand
        if best is None:
            break
        k, cand, chi_cur, ho_cur, vals, std = best
        chosen.append(k)
        named.append(NamedEffect(name=k, labels=fams[k][1], units=fams[k][2], values=vals, std=std,
                                 held_out_share=cand["held_out_share"], p_value=cand["p_value"], fix=FIX[k]))
    # Backward: a family named early may have stood in for one named later (a frame drift's rotation looks
    # like the motors' zeros drifting together): drop each one the others make insignificant.
    for k in list(chosen)[::-1]:
        if len(chosen) < 2:
            break
        others = [c for c in chosen if c != k]
        G_all = columns(chosen)
        chi_all, chi_rest = chi2_of(G_all), chi2_of(columns(others))
        q = fams[k][0].shape[1]
        dof = n_rows - Jb.shape[1] - G_all.shape[1]
        pval = min(1.0, float(stats.f.sf(((chi_rest - chi_all) / q) / (chi_all / dof), q, dof)) * len(chosen))
        if pval > ALPHA:
            chosen.remove(k)
            named = [e for e in named if e.name != k]
            candidates[k]["verdict"] = f"explained by {', '.join(others)} (p = {pval:.2g} once they are in)"
    G = columns(chosen)
    x, cov, res = lin.fit(G)
    ho_cur = [lin.held_out(G, s_, cov) for s_ in splits]
    if named:                                     # the values, intervals and motors of the final set
        start = Jb.shape[1]
        for e in named:
            q = len(e.labels)
            e.values, e.std = x[start:start + q], np.sqrt(np.clip(np.diag(cov)[start:start + q], 0.0, None))
            e.motors = _carriers(e)
            start += q
    for c in candidates.values():
        if c["name"] in chosen:
            c["verdict"] = "named"
    gap = lambda ho: float(np.sqrt(ho[0][0]) * sigma)  # noqa: E731   (random folds: the typical pose)
    unexplained = {}
    if excess(ho_cur) > noise_band:
        contexts = {"time" if has_time else "row order": t}
        if temp is not None:
            contexts["temperature"] = temp
        s = approach_from_order(commands)
        for k in range(commands.shape[1]):
            contexts[f"m{k + 1} command"] = commands[:, k]
            contexts[f"m{k + 1} approach"] = s[:, k]
        centre = y.mean(axis=1)                                   # where the nests are
        for a, axis in enumerate("xyz"):
            contexts[f"nests' {axis}"] = centre[:, a]
        contexts["nests' distance from the z axis"] = np.hypot(centre[:, 0], centre[:, 1])
        unexplained = {"excess_mm": float(sigma * np.sqrt(max(ho_cur[0][0] - ho_cur[0][1], 0.0))),
                       "correlates": _correlates(res.reshape(len(y), -1), contexts)[:5]}
    verdict = ("named" if named else "") + ("+unexplained" if named and unexplained else
                                            "unexplained" if unexplained else "")
    return ChainDiagnosis(verdict=verdict or "noise", named=named, candidates=list(candidates.values()),
                          gap_before=gap(ho_base), gap_after=gap(ho_cur), noise_mm=sigma,
                          unexplained=unexplained, time_unit=unit)


def _correlates(E: np.ndarray, contexts: dict) -> list[dict]:
    """How much of the per-pose residuals ``E`` (N, 3K, whitened) each context explains by a quadratic in
    it (share of the structure beyond the noise, F-test p-value), strongest first."""
    out = []
    N, D = E.shape
    total = float(np.sum(E ** 2))
    for name, c in contexts.items():
        c = np.asarray(c, float)
        if np.ptp(c) == 0:
            continue
        z = (c - c.mean()) / c.std()
        X = np.stack([z, z ** 2 - np.mean(z ** 2)], axis=1)
        if np.unique(c).size < 3:
            X = X[:, :1]
        coef, *_ = np.linalg.lstsq(X, E, rcond=None)
        explained = float(np.sum((X @ coef) ** 2))
        q = X.shape[1] * D
        dof = max(N * D - q, 1)
        F = (explained / q) / max((total - explained) / dof, 1e-300)
        structure = max(total - N * D, explained, 1e-300)           # beyond the noise (whitened: 1 per row)
        out.append({"context": name, "share": min(explained / structure, 1.0),
                    "p_value": float(stats.f.sf(F, q, dof))})
    return sorted(out, key=lambda d: d["p_value"])
