"""Discrepancy diagnosis: where the twin and the measurements disagree, and which effect is missing.

Steps (docs/diagnose.md):

a. Fit the baseline (default: the whole-chain geometric model of limbs 1-2 + SS + stiffness ratio, the
   passive limbs nominal) and compare its twin prediction with the measured targets.
b. Noise: sigma given, or estimated without any machine model from how far each pose's targets are
   from a similarity transform of their platform coordinates (2 dof a pose). An omnibus test says
   whether anything is left beyond the noise.
c. Every candidate effect's *signature* (d targets / d effect parameter) keeps only what the baseline
   cannot absorb (conditional information, :mod:`pmcal.calib.ocpm.linear_tests`); its power at a typical size
   says whether this campaign can see it at all, and if not, which measurement would.
d. Forward selection: the most significant candidate (F test, Bonferroni over the candidates in play)
   whose fitted value is physically plausible and large enough is added, the whole model is refitted
   (nonlinear, the effect's physics in the forward model), the others are re-tested there, named ones
   are re-checked.
e. Cross-validation: the same selection runs inside each fold (training poses only), every round
   linearised at the full-data fit of the model the fold has already named (refitted linearly on the
   fold's training poses), so a large first effect does not block a second; a name is kept if enough
   folds select it.
f. The named effects with value ± 95 % interval are written into the model; ``gap_before`` and
   ``gap_after`` are RMS held-out disagreements (folds refitted, linearised at the full-data fits),
   without the poses that held out are predicted by extrapolation (leverage > 1, named in a note).
f'. A name is earned on held-out data: its held-out share passes a test calibrated on this campaign's poses
   (:mod:`pmcal.calib.ocpm.held_out_test`: at least what it would leave were it the truth, 5 % quantile, at
   its fitted or a typical size, capped at 75 %; above what a structure of its size outside it gives, 95 %
   quantile); with structure left also half of the held-out excess, 90 % where that share is measured
   clearly; the share with workspace regions held out whole is reported beside it. A per-motor effect is
   reported on the motors whose own part passes that test against zero or is significant by itself at the
   naming level (nested test in the named model).
g. Structure left after that (omnibus test, also robust to heavy-tailed noise) is flagged unexplained.

Units: mm, rad inside (interface values of effects in :data:`VOCABULARY` units).

Longer than the project's ~400 lines on purpose: the steps a-g share one problem state (:class:`_Problem`)
and read top to bottom as the algorithm of docs/diagnose.md; the parts with a life of their own already
live beside it (linear tests, noise estimate, effect values, residual context, result type).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field

import numpy as np
from scipy import stats

from pmcal.calib.ocpm.forward_model import EffectModel
from pmcal.mechanism.ocpm.config import Geometry
from pmcal.mechanism.ocpm.data import Measurements
from pmcal.mechanism.ocpm.effects import (EFFECT_NAMES, T_REL, approach_from_order, VOCABULARY, effect_of_key,
                                          thermal_delta, with_context)
from pmcal.calib.ocpm.diagnosis_result import Candidate, Diagnosis, Omnibus
from pmcal.calib.ocpm.effect_values import EffectValue, effect_prior_std, effect_value
from pmcal.calib.ocpm.held_out_test import held_out_test
from pmcal.calib.ocpm.fullchain import FullChainOptions, Priors, UnassembledError, identify_full
from pmcal.mechanism.ocpm.params import LOG_RATIO
from pmcal.calib.ocpm.linear_tests import (Linearization, SubFit, alpha_weights, conditional_information, fit,
                                     huber_weighted, nested_test, pose_leverage, power, predict)
from pmcal.calib.ocpm.noise_estimate import NoiseEstimate, estimate_noise
from pmcal.calib.ocpm.residual_context import characterise, describe
from pmcal.mechanism.ocpm.params import LIMB_FIELDS, PAPER_LIMB_FIELDS, SS_FIELDS, is_angular
from pmcal.calib.solvers.result import IdentResult

#: Baseline key sets. "full": limbs 1-2 (12 geometric keys + dtheta each) and SS; "paper": the paper's 11
#: parameters of limbs 1-2 (evaluated with the whole-chain forward model).
BASELINES: dict[str, list[str]] = {
    "full": [f"L{j}.{f}" for j in (1, 2) for f in LIMB_FIELDS] + [f"SS.{f}" for f in SS_FIELDS],
    "paper": [f"L{j}.{f}" for j in (1, 2) for f in PAPER_LIMB_FIELDS],
}


@dataclass
class DiagnoseOptions:
    """Settings of :func:`diagnose`.

    baseline_keys : geometric keys of the baseline (default ``BASELINES["full"]``); the stiffness ratio
        is fitted too when ``fit_stiffness_ratio``. Passive-limb keys in it remove ``overconstraint``.
    sigma_mm : tracker noise if known (else estimated from the data, model-free).
    alpha : family-wise level of a naming round: weighted Bonferroni over the candidates in play
        (:func:`alpha_weights`: ``easy_share`` of it for the candidates the campaign detects at a typical
        size even at that small a level, the rest for the others).
    easy_share : the share of ``alpha`` spent on the easily detected candidates.
    folds : cross-validation folds (stratified by tilt, :func:`stratified_folds`).
    min_folds : share of the folds whose own selection must pick a named effect.
    min_rms_sigma : smallest RMS change of the measurements (in sigma) an effect must make to be named.
    min_explained : smallest share of the structure left beyond the noise an effect must explain to be
        named (a significant effect that explains a sliver of a larger structure is not forced onto it).
    gate_alpha, gate_excess : the omnibus test: structure if p < gate_alpha and the RMS excess over
        the noise is at least gate_excess sigma (also by the robust, median-based measure).
    max_leverage, max_extrapolated : a pose that determines more than ``max_leverage`` directions of the
        final model by itself (:func:`pose_leverage`) is predicted by extrapolation when held out; the
        held-out gaps leave such poses out (at most ``max_extrapolated`` of the poses, the highest first)
        and a note names them.
    min_held_out : when structure is left after the named model, a name stays only if, on the held-out
        poses, it removes at least this share of the held-out excess over the noise of the model without
        it (:func:`held_out_shares`); otherwise the structure is reported unexplained.
    min_held_out_measured : the most the calibrated held-out test (:func:`_earned_on_held_out`,
        :mod:`pmcal.calib.ocpm.held_out_test`) asks of a name's held-out share (its candidate-true 5 %
        quantile applies where lower).
    min_held_out_left, measured_sd : when structure is left after the named model and the name's own
        held-out improvement stands out of the noise of a held-out sum of squares by more than
        ``measured_sd`` standard deviations (the share is then measured, not noise), it must remove at
        least ``min_held_out_left`` of the held-out excess (``min_held_out`` where the improvement is not
        measured clearly).
    """

    baseline_keys: list[str] | None = None
    fit_stiffness_ratio: bool = True
    candidates: tuple[str, ...] = EFFECT_NAMES
    sigma_mm: float | None = None
    alpha: float = 0.003
    easy_share: float = 0.1
    folds: int = 10
    min_folds: float = 0.3
    min_rms_sigma: float = 0.03
    min_explained: float = 0.25
    max_effects: int = 3
    gate_alpha: float = 1e-3
    gate_excess: float = 0.25
    max_leverage: float = 1.0
    max_extrapolated: float = 0.03
    min_held_out: float = 0.5
    min_held_out_measured: float = 0.75
    min_held_out_left: float = 0.9
    measured_sd: float = 2.5
    priors: Priors = field(default_factory=Priors)
    initial: dict[str, float] | None = None      # start of the baseline fit (interface units), e.g. P.json
    max_nfev: int = 60


def limit_blas_threads(n: int | None = None) -> None:
    """Apply pmcal's BLAS thread policy (:func:`pmcal.threads.apply_blas_policy`: one thread unless
    ``n`` or ``$PMCAL_BLAS_THREADS`` say otherwise). The diagnosis does many small dense factorisations;
    with OpenBLAS threads competing one SVD took 0.4 s instead of 2 ms on the 2-core reference machine."""
    from pmcal.threads import apply_blas_policy

    apply_blas_policy(n)


# ======================================================================================== linearisation
def linearize(model: EffectModel, meas: Measurements, res: IdentResult, extra_keys: list[str],
              sigma: float, prior_std: dict[str, float]) -> Linearization:
    """Whitened linear model at the fit ``res`` with the columns of ``extra_keys`` (candidates) added."""
    keys = list(res.names) + [k for k in extra_keys if k not in res.names]
    n_fit = len(res.names)
    scale = np.concatenate([np.asarray(res.info["prior_std"], float), [prior_std[k] for k in keys[n_fit:]]])
    mean = np.concatenate([np.asarray(res.info["prior_mean"], float), np.zeros(len(keys) - n_fit)])
    model.set_vector(list(res.names), res.x, res.info["stiffness_ratio"])
    T, dT = model.predict_meas(meas, keys)
    n = T.size
    dT = dT.reshape(n, len(keys))
    z0 = np.zeros(len(keys))
    z0[:n_fit] = (res.x - mean[:n_fit]) / scale[:n_fit]
    pose = np.repeat(np.arange(len(meas)), n // len(meas))
    return Linearization(r=(meas.targets.reshape(-1) - T.reshape(-1)) / sigma,
                         J=dT * scale / sigma, keys=keys, z0=z0, pose=pose,
                         sigma=sigma, scale=scale, mean=mean)


def stratified_folds(meas: Measurements, k: int, geom: Geometry) -> np.ndarray:
    """Cross-validation fold of every pose (N,): poses ranked by measured tilt are taken in blocks of
    ``k``, one pose of a block to each fold, so each fold spans the whole tilt range; within a block the
    poses go to the folds (an assignment) that keep each farthest from its fold's closest pose (angle
    between platform normals; a close pair costs most), so neighbours in azimuth as well as tilt are held out in different folds. No region of the workspace is
    held out at once: a held-out hole would measure extrapolation, not the model (cross-sim drift seed
    1013: two poses 4 deg apart at 70-74 deg tilt, ranked 10 apart, fell in one fold, and the one whose
    targets carry a direction the others barely see was predicted 0.07 mm off, gap after 1.22 sigma)."""
    from scipy.optimize import linear_sum_assignment

    _, R, _ = meas.poses(geom)
    normal = R[:, :, 2]
    n, k = len(meas), max(2, min(k, len(meas)))
    order = np.argsort(-normal[:, 2], kind="stable")            # most tilted first: the sparse edge
    folds = np.full(n, -1)
    for start in range(0, n, k):
        block = order[start:start + k]
        cos = normal[block] @ normal.T                             # (block, N)
        near = np.array([[np.arccos(np.clip(cos[j, folds == f].max(), -1, 1)) if (folds == f).any() else np.pi
                          for f in range(k)] for j in range(len(block))])
        rows, cols = linear_sum_assignment(1.0 / (near + 1e-3))     # a close pair costs most
        folds[block[rows]] = cols
    return folds


def region_folds(meas: Measurements, geom: Geometry, sectors: int = 4, bands: int = 2) -> np.ndarray:
    """Workspace region of every pose (N,), for held-out checks that hold a region out whole: the azimuth
    of the measured platform normal in ``sectors`` equal sectors times its tilt in ``bands`` bands of
    equal pose count. Unlike :func:`stratified_folds` each fold is a contiguous part of the workspace,
    so its held-out poses are predicted from parameters fitted on the other regions only."""
    _, R, _ = meas.poses(geom)
    normal = R[:, :, 2]
    azimuth = np.arctan2(normal[:, 1], normal[:, 0])
    sector = np.minimum(((azimuth + np.pi) / (2 * np.pi) * sectors).astype(int), sectors - 1)
    tilt_rank = np.argsort(np.argsort(-normal[:, 2], kind="stable"), kind="stable")
    band = tilt_rank * bands // len(meas)
    return sector * bands + band


# ======================================================================================== the steps
def _at_noise(res: IdentResult) -> bool:
    """The fit's chi2/dof is within 1 + 3 sqrt(2/dof) (three standard deviations of chi2/dof for pure
    noise): nothing is left above the noise."""
    return res.info["chi2_per_dof"] <= 1.0 + 3.0 * np.sqrt(2.0 / res.info["dof"])


class _Problem:
    """Everything one diagnosis shares: data with context, noise, model, options, candidate keys."""

    def __init__(self, meas: Measurements, opt: DiagnoseOptions, model: EffectModel):
        geom = model.geom
        self.geom, self.opt = geom, opt
        self.meas, self.time_unit = with_context(meas)
        self.t_rel, self.dtemp = self.meas.extra[T_REL], thermal_delta(self.meas.temp_c)
        self.noise = estimate_noise(meas, geom, opt.sigma_mm)
        self.sigma = self.noise.sigma_mm
        self.base_keys = list(opt.baseline_keys or BASELINES["full"])
        self.model = model
        self.model_keys0: list[str] = []              # the baseline fit's keys (with the ratio)
        self.baseline: IdentResult | None = None
        self.candidates: dict[str, list[str]] = {}
        self.missing: dict[str, str] = {}
        for name in opt.candidates:
            keys = [k for k in VOCABULARY[name].keys if k not in self.base_keys]
            reason = self._missing_context(name)
            if reason or not keys:
                self.missing[name] = reason or "its parameters are already in the baseline model"
            else:
                self.candidates[name] = keys
        self.prior_std = {k: effect_prior_std(k, opt.priors, self.time_unit)
                          for keys in self.candidates.values() for k in keys}

        self.folds = stratified_folds(self.meas, opt.folds, geom)
        self.regions = region_folds(self.meas, geom)
        #: full-data fits met so far: frozenset of effect names -> (fit, Huber-weighted linearisation or
        #: None when the fit does not assemble every pose); filled by the selection, read by the folds
        self.fits: dict[frozenset, tuple[IdentResult, Linearization | None]] = {}
        #: weighted-Bonferroni weights of the candidates (:func:`alpha_weights`, set by the scoreboard)
        self.weights: dict[str, float] = {n: 1.0 for n in self.candidates}
        #: per candidate: its typical-size instances (prior units, one a row) and the conditional information
        #: beyond the baseline they are measured with (set by the scoreboard, :func:`_typical_factor`)
        self.typical_nc: dict[str, tuple[np.ndarray, np.ndarray]] = {}

    def level(self, name: str, in_play: list[str]) -> float:
        """The level ``name`` is tested at among the candidates ``in_play``: its share of ``alpha``."""
        return self.opt.alpha * self.weights[name] / sum(self.weights[n] for n in set(in_play) | {name})

    def remember(self, names: list[str], res: IdentResult, lin: Linearization) -> Linearization | None:
        """Keep the full-data fit of baseline + ``names`` and its Huber-weighted linearisation."""
        ok = bool(np.all(np.isfinite(lin.r)) and np.all(np.isfinite(lin.J)))
        linw = huber_weighted(lin, lin.cols(list(res.names))) if ok else None
        self.fits[frozenset(names)] = (res, linw)
        return linw

    def at(self, names: list[str]) -> Linearization | None:
        """Huber-weighted linearisation at the full-data fit of baseline + ``names`` (None if that fit cannot
        assemble every pose). Fits the selection made are reused; another combination (a fold that
        chose differently) is refitted once, warm-started from the largest remembered subset.

        Why the full-data fit serves every fold: a fold's training fit differs from it by the influence
        of a tenth of the poses, a small step the fold's linear refit takes; the linearisation error is
        second order in that step, whereas at the baseline it is second order in the whole effect."""
        key = frozenset(names)
        if key not in self.fits:
            starts = [k for k in self.fits if k <= key and self.fits[k][1] is not None]
            if not starts:
                return None
            start = max(starts, key=len)
            ordered = [n for n in self.candidates if n in key]
            res = self.refit(self.fits[start][0], ordered)
            self.remember(ordered, res, self.linearize(res, ordered))
        return self.fits[key][1]

    def _missing_context(self, name: str) -> str:
        m = self.meas
        if name == "thermal_expansion" and thermal_delta(m.temp_c) is None:
            return "no temperature per pose (temp_c column)"
        if name == "backlash" and m.approach is None:
            return "no direction of approach per pose (m1_approach, m2_approach columns)"
        return ""

    def identify(self, names: list[str], x0: dict[str, float] | None) -> IdentResult:
        """Nonlinear MAP fit of the baseline plus the effects ``names``."""
        opt = self.opt
        keys = self.base_keys + [k for n in names for k in self.candidates[n]]
        # The ratio's prior is centred on the machine's nominal ratio (machine.toml), not on the shared
        # model's current one, which drifts with the fits before (deep into the stiff limit when the
        # baseline absorbs compliance) and would carry that drift into every later fit's prior.
        options = FullChainOptions(
            keys=keys, fit_stiffness_ratio=opt.fit_stiffness_ratio, priors=opt.priors, sigma_mm=self.sigma,
            max_nfev=opt.max_nfev, extra_prior_std=self.prior_std, x0=x0, stiffness_ratio=self.geom.stiffness_ratio)
        return self._unstall(identify_full(self.meas, self.model, options), options)

    def _unstall(self, res: IdentResult, options: FullChainOptions, factor: float = 5.0,
                 share: float = 0.05) -> IdentResult:
        """A fit left far above the noise by a few poses (pose residuals above ``factor`` times the median
        pose's, at most ``share`` of the poses) has stalled with those poses in another assembly of the
        model: on twin clean seed 1072 the baseline stopped at chi2/dof 1000 (xtol after 25 evaluations,
        the trust region shrunk to nothing) with three poses 2-8 mm off and the others 0.16 mm, while the
        true geometry fits every pose to the noise. Those poses are then fitted out (same start), then all
        poses from there. It replaces the fit only when it reaches the noise (chi2/dof within 1 + 3
        sqrt(2/dof)) at a lower MAP cost: a model that then fits every pose was stalled. With an effect
        left in the data (a compliance campaign's baseline has the same few strained poses far off) the
        better baseline started the compliance refit where it stalled (twin compliance seed 1016: gap
        after 3.2 sigma), so the fit is then left as it was."""
        if _at_noise(res):
            return res
        norms = np.linalg.norm(res.residuals.reshape(len(self.meas), -1), axis=1)
        out = norms > factor * np.median(norms)
        if not out.any() or out.sum() > share * len(norms):
            return res
        try:
            part = identify_full(self.meas.subset(np.flatnonzero(~out)), self.model, options)
            again = identify_full(self.meas, self.model, dataclasses.replace(
                options, x0={k: float(v) for k, v in zip(part.names, part.x)}))
        except UnassembledError:
            return res
        return again if _at_noise(again) and self._map_cost(again) < self._map_cost(res) else res

    def linearize(self, res: IdentResult, named: list[str]) -> Linearization:
        """Linear model at ``res`` with the columns of every candidate not in ``named``."""
        extra = [k for n in self.candidates if n not in named for k in self.candidates[n]]
        return linearize(self.model, self.meas, res, extra, self.sigma, self.prior_std)

    def value_from(self, lin: Linearization, sub: SubFit, name: str) -> EffectValue:
        """Effect value from a linear fit."""
        keys = self.candidates[name]
        cols = lin.cols(keys)
        pos = np.array([list(sub.cols).index(c) for c in cols])
        vals = lin.values(sub)
        x = np.array([vals[k] for k in keys])
        cov_z = np.linalg.inv(sub.info + np.eye(len(sub.cols)))[np.ix_(pos, pos)] * max(sub.rss / sub.dof, 1.0)
        return effect_value(name, keys, x, cov_z * np.outer(lin.scale[cols], lin.scale[cols]), self.time_unit,
                            self.t_rel, self.dtemp)

    def value_final(self, res: IdentResult, name: str, motors: tuple[int, ...] | None = None) -> EffectValue:
        """Effect value from a nonlinear fit (covariance inflated by the residual variance if above 1);
        ``motors`` as in :func:`effect_value`."""
        keys = self.candidates[name]
        idx = [res.names.index(k) for k in keys]
        cov = res.covariance[np.ix_(idx, idx)] * max(res.info["chi2_per_dof"], 1.0)
        return effect_value(name, keys, res.x[idx], cov, self.time_unit, self.t_rel, self.dtemp, motors)

    def polish(self, res: IdentResult, max_steps: int = 4) -> IdentResult:
        """Gauss-Newton (chord) steps with a forward-difference Jacobian after a fit with compliance in the
        model, and the covariance from it. The analytic sensitivities of the preloaded spring model are 5-15 %
        off: the trust-region fit stopped short (steps of ~0.4 sigma left) and its covariance made the
        intervals of K ~35 % too narrow."""
        names, ratio = list(res.names), res.info["stiffness_ratio"]
        s, mean = np.asarray(res.info["prior_std"]), np.asarray(res.info["prior_mean"])
        y = self.meas.targets.ravel()

        def cost(x):
            self.model.set_vector(names, x, ratio)
            T = self.model.targets(self.meas).ravel()
            if not np.all(np.isfinite(T)):                 # a pose the model cannot assemble there
                return np.inf, T
            return float(np.sum(((y - T) / self.sigma) ** 2) + np.sum(((x - mean) / s) ** 2)), T

        x = res.x.copy()
        c0, T0 = cost(x)
        J = np.empty((T0.size, len(names)))
        for i in range(len(names)):
            xi = x.copy()
            h = 1e-3 * max(abs(x[i] - mean[i]), 1e-2 * s[i])
            xi[i] += h
            J[:, i] = (cost(xi)[1] - T0) / h
        if not np.all(np.isfinite(J)):                      # no finite difference Jacobian: keep the fit
            return res
        # Chord steps with that one Jacobian: the steps left are below ~0.5 std, over which the Jacobian
        # changes to second order only (a fresh one per step cost len(names) equilibria each, the bulk
        # of a compliance diagnosis, for the same steps and intervals).
        A = J / self.sigma
        M = A.T @ A + np.diag(1.0 / s**2)
        for _ in range(max_steps):
            step = np.linalg.solve(M, A.T @ ((y - T0) / self.sigma) - (x - mean) / s**2)
            c1, T1 = cost(x + step)
            if not c1 < c0:
                break
            x, c0, T0 = x + step, c1, T1
            if np.max(np.abs(step) * np.sqrt(np.diag(M))) < 0.01:     # below 1 % of a std
                break
        cov = np.linalg.inv(M)
        resid = y - T0
        p_eff = float(np.trace(cov @ (A.T @ A)))
        info = dict(res.info, chi2_per_dof=float(resid @ resid / self.sigma**2 / (len(y) - p_eff)),
                    effective_parameters=p_eff, jacobian=J)
        return dataclasses.replace(res, x=x, residuals=resid, covariance=cov, info=info,
                                   method=res.method + "+fd-polish")

    def refit(self, res: IdentResult, names: list[str], lin: Linearization | None = None,
              sub: SubFit | None = None) -> IdentResult:
        """Nonlinear refit of baseline + ``names``, warm-started from ``res`` and, for the parameters new to
        the fit, the linear step ``sub``. The fitted parameters keep their values: a linear step can move a
        weakly determined one (the stiffness ratio deep in its stiff limit, where the targets barely depend
        on it) by many prior stds, to where the model no longer assembles the measured poses."""
        x0 = {k: float(v) for k, v in zip(res.names, res.x)}
        if sub is not None:
            x0.update({k: v for k, v in lin.values(sub).items() if k not in x0})
        new = self.identify(names, x0)
        if not _at_noise(new) and self._ratio_far(new):
            # Left well above the noise with the stiffness ratio far out: the warm start may sit in the
            # baseline's basin (the ratio pushed deep into its flat stiff limit to absorb the effect). A
            # fit from the prior mean with the effect in finds the other basin when there is one; the
            # lower MAP cost wins.
            fresh = self.identify(names, None)
            if self._map_cost(fresh) < self._map_cost(new):
                new = fresh
        return self.polish(new) if "joint_compliance" in names else new

    def _ratio_far(self, res: IdentResult, n_std: float = 2.0) -> bool:
        """The fitted stiffness ratio lies more than ``n_std`` prior stds from the machine's nominal ratio
        (machine.toml), where every fit's prior is centred (:meth:`identify`)."""
        if LOG_RATIO not in res.names:
            return False
        i = res.names.index(LOG_RATIO)
        return abs(res.x[i] - np.log(self.geom.stiffness_ratio)) > n_std * res.info["prior_std"][i]

    def _map_cost(self, res: IdentResult) -> float:
        """The MAP objective of a fit: whitened residuals plus prior terms."""
        z = (res.x - np.asarray(res.info["prior_mean"])) / np.asarray(res.info["prior_std"])
        return float(np.sum((res.residuals / self.sigma) ** 2) + z @ z)


def _test_round(pb: _Problem, lin: Linearization, model_keys: list[str], names: list[str],
                rows: np.ndarray | None = None, in_play: list[str] | None = None) -> dict[str, tuple]:
    """Test every candidate in ``names`` against the model ``model_keys``, each at its level among the
    candidates ``in_play`` (default ``names``; :meth:`_Problem.level`). Returns name -> (NestedTest,
    EffectValue, passes, level, explained share), the form the selection's history keeps."""
    mcols = lin.cols(model_keys)
    in_play = in_play or names
    out = {}
    for name in names:
        t = nested_test(lin, mcols, lin.cols(pb.candidates[name]), rows)
        v = pb.value_from(lin, t.fit, name)
        n_rows = t.fit.n
        excess = t.base.rss - t.base.dof                      # structure beyond the noise, whitened
        share = t.delta_chi2 / max(excess, t.delta_chi2, 1e-12)
        level = pb.level(name, in_play)
        ok = (t.p_value < level and v.plausible
              and np.sqrt(t.delta_chi2 / n_rows) >= pb.opt.min_rms_sigma and share >= pb.opt.min_explained)
        out[name] = (t, v, ok, level, share)
    return out


def _best(tests: dict[str, tuple]) -> str | None:
    ok = [n for n, t in tests.items() if t[2]]
    return min(ok, key=lambda n: (tests[n][0].p_value, -tests[n][0].F)) if ok else None


def _fold_selection(pb: _Problem, rows: np.ndarray) -> list[str]:
    """Greedy forward selection with backward re-checks on the training ``rows`` of a fold, each round
    linearised at the model already named in that fold (:meth:`_Problem.at`: the full-data nonlinear fit
    of baseline + the fold's names; the fold refits all of it linearly from there). A large nonlinear
    first effect is then part of the model the second one is tested against, not leftover structure."""
    chosen: list[str] = []
    while len(chosen) < pb.opt.max_effects:
        lin = pb.at(chosen)
        if lin is None:
            break
        model = pb.model_keys0 + [k for n in chosen for k in pb.candidates[n]]
        rest = [n for n in pb.candidates if n not in chosen]
        if not rest:
            break
        tests = _test_round(pb, lin, model, rest, rows)
        for n in rest:
            # As in the selection on all poses: a strongly nonlinear effect that the linear test at the
            # current model misses is tested at its nonlinear refit (when the selection made one)
            # against the model without it.
            tried = pb.fits.get(frozenset(chosen + [n]), (None, None))[1]
            if not tests[n][2] and tried is not None:
                tests[n] = _test_round(pb, tried, model, [n], rows, rest)[n]
        best = _best(tests)
        if best is None:
            break
        chosen.append(best)
        lin = pb.at(chosen)
        if lin is None:                              # the refit left the workspace: not this fold's name
            chosen.pop()
            break
        for name in chosen[:-1]:
            others = pb.model_keys0 + [k for n in chosen if n != name for k in pb.candidates[n]]
            if not _test_round(pb, lin, others, [name], rows, rest + [name])[name][2]:
                chosen.remove(name)
    return chosen


def omnibus(lin: Linearization, sub: SubFit, noise: NoiseEstimate, opt: DiagnoseOptions) -> Omnibus:
    """Residual against the noise: chi-square (sigma given) or F against the model-free estimate, and a
    median-based ratio of per-pose sums that heavy-tailed noise does not inflate."""
    r = predict(lin, sub, np.ones(len(lin.r), bool))
    n = len(r)
    dof = max(n - sub.p_eff, 1.0)
    ratio = float(r @ r / dof)
    if noise.source == "given":
        p = float(stats.chi2.sf(ratio * dof, dof))
        scale2 = 1.0
    else:
        p = float(stats.f.sf(ratio, dof, noise.dof))
        scale2 = (noise.free_robust_mm / noise.sigma_mm) ** 2
    per_pose = np.bincount(lin.pose, weights=r * r)
    nu = dof / per_pose.size                         # dof a pose, on average
    robust = float(np.median(per_pose) / stats.chi2.median(nu) / scale2)
    excess = float(noise.sigma_mm * np.sqrt(max(min(ratio, robust) - 1.0, 0.0)))
    structure = p < opt.gate_alpha and excess >= opt.gate_excess * noise.sigma_mm
    return Omnibus(ratio=ratio, robust_ratio=robust, p_value=p, excess_mm=excess, structure=bool(structure))


def _cv(lin: Linearization, cols: np.ndarray, folds: np.ndarray, drop: np.ndarray | None = None) -> np.ndarray:
    """Held-out whitened residuals (n,) of the model ``cols``, each fold refitted on the others (the columns
    ``drop`` taken out of the model, :func:`fit`)."""
    out = np.zeros(len(lin.r))
    for f in np.unique(folds):
        test = lin.rows(np.flatnonzero(folds == f))
        out[test] = predict(lin, fit(lin, cols, ~test, drop), test, drop)
    return out


#: Probability of detection that defines the smallest detectable size of an effect (:func:`detectable_size`).
DETECT_POWER = 0.9


def _typical_draws(pb: _Problem, name: str, n: int = 64) -> np.ndarray:
    """Parameters (n, k) of typical-size instances of an effect, prior units: random phases for the
    eccentricity, random +-size passive errors for overconstraint, the typical value on both motors for
    the other effects."""
    info, keys = VOCABULARY[name], pb.candidates[name]
    s = np.array([pb.prior_std[k] for k in keys])
    rng = np.random.default_rng(0)
    if name == "overconstraint":
        size = info.typical * np.array([np.deg2rad(0.2) if is_angular(k) else 1.0 for k in keys])
        return rng.uniform(-1.0, 1.0, (n, len(keys))) * size / s
    if name == "encoder_eccentricity":
        ph = rng.uniform(0.0, 2 * np.pi, (n, 2))
        x = np.deg2rad(info.typical) * np.stack([np.cos(ph[:, 0]), np.sin(ph[:, 0]), np.cos(ph[:, 1]),
                                                 np.sin(ph[:, 1])], 1)
        return x / s
    if name == "joint_compliance":
        t = np.full(2, 1.0 / info.typical)
    elif name == "thermal_expansion":                      # the uniform member: every group at alpha
        t = np.array([info.typical if k.endswith(".alpha") else 0.0 for k in keys])
    elif name == "zero_offset_drift":                      # the linear member (30 s a pose)
        rate = np.deg2rad(info.typical) / (120.0 if pb.time_unit == "pose" else 1.0)
        t = np.array([rate if k.split(".")[1][0] == "r" else 0.0 for k in keys])
    elif name == "frame_drift":                            # a translation of typical rate, random direction
        v = rng.normal(size=(n, 3))
        v *= info.typical / (120.0 if pb.time_unit == "pose" else 1.0) / np.linalg.norm(v, axis=1, keepdims=True)
        return np.concatenate([v, np.zeros((n, 3))], axis=1) / s
    else:
        t = np.full(len(keys), np.deg2rad(info.typical))
    return (t / s)[None]


def _scoreboard(pb: _Problem, lin: Linearization) -> dict[str, Candidate]:
    """Identifiability of every candidate against the baseline: the share of a typical signature the
    baseline cannot absorb (survival) and the chance to detect a typical size (power, averaged over
    typical instances) with a test of the directions the data determine."""
    out, nc, k = {}, {}, {}
    mcols = lin.cols(pb.model_keys0)
    m = max(len(pb.candidates), 1)
    for name in pb.opt.candidates:
        info = VOCABULARY[name]
        if name in pb.missing:
            out[name] = Candidate(name, False, pb.missing[name], verdict="not identifiable with this campaign",
                                  fix=info.fix)
            continue
        ecols = lin.cols(pb.candidates[name])
        Z = _typical_draws(pb, name)
        S = lin.J[:, ecols]
        I_c = conditional_information(lin, mcols, ecols)
        raw = np.einsum("ni,ij,nj->n", Z, S.T @ S, Z)
        nc[name] = np.einsum("ni,ij,nj->n", Z, I_c, Z)
        pb.typical_nc[name] = (Z, I_c)
        k[name] = max(int(np.sum(np.linalg.eigvalsh(I_c) > 1.0)), 1)
        out[name] = Candidate(name, True, survival=float(nc[name].mean() / raw.mean()) if raw.mean() > 0 else 0.0,
                              fix=info.fix)
    typical = lambda n, level: float(np.mean([power(c, k[n], level) for c in nc[n]]))  # noqa: E731
    pb.weights = alpha_weights({n: typical(n, pb.opt.alpha * pb.opt.easy_share / m) for n in nc},
                               pb.opt.easy_share)
    for n in nc:
        level = pb.level(n, list(pb.candidates))
        out[n].power_typical = typical(n, level)
        out[n].detectable_90 = detectable_size(n, nc[n], k[n], level, pb.time_unit)
    return out


def detectable_size(name: str, nc: np.ndarray, k: int, level: float, time_unit: str = "h",
                    target: float = DETECT_POWER) -> float:
    """The smallest size of an effect this campaign detects with probability ``target`` (averaged over the
    typical instances whose noncentralities at the typical size are ``nc``; a chi-square test of ``k``
    directions at ``level``), in the unit of its value: the noncentrality grows with the size squared.
    Compliance: the largest stiffness K (a stiffer drive deflects less); backlash the full dead band."""
    info = VOCABULARY[name]
    nc = np.asarray(nc, float)
    crit = stats.chi2.isf(level, k)
    prob = lambda f: float(np.mean(stats.ncx2.sf(crit, k, np.maximum(nc * f * f, 1e-12))))  # noqa: E731
    lo, hi = 1e-3, 1e3
    if prob(hi) < target:
        return float("inf") if name != "joint_compliance" else 0.0
    for _ in range(60):                                    # bisection on the size factor (log scale)
        mid = np.sqrt(lo * hi)
        lo, hi = (mid, hi) if prob(mid) < target else (lo, mid)
    size = info.typical * hi
    if name == "joint_compliance":
        return info.typical / hi
    if name == "backlash":
        return 2.0 * size
    if name in ("zero_offset_drift", "frame_drift") and time_unit == "pose":
        return size / 120.0
    return size


def _select(pb: _Problem, base: IdentResult, lin0: Linearization, board: dict[str, Candidate]):
    """Forward selection on all poses (steps c, d). Each round tests the candidates at the current fit
    (linearised, Huber-weighted rows); the most significant one that passes, or, when structure is left
    and none passes, the two that explain most of it (a strongly nonlinear effect can look weak in a
    linear test) are refitted nonlinearly and tested again at the refit, against the model without
    them. Earlier names are re-tested once a new one is in."""
    named: list[str] = []
    res, lin = base, lin0
    history: dict[str, tuple] = {}
    rejected: set[str] = set()
    while len(named) < pb.opt.max_effects:
        rest = [n for n in pb.candidates if n not in named and n not in rejected]
        if not rest:
            break
        in_play = [n for n in pb.candidates if n not in named]
        cols = lin.cols(list(res.names))
        tests = _test_round(pb, huber_weighted(lin, cols), list(res.names), rest, in_play=in_play)
        history.update(tests)
        order = sorted((n for n in rest if tests[n][2]), key=lambda n: (tests[n][0].p_value, -tests[n][0].F))
        if not order and omnibus(lin, fit(lin, cols), pb.noise, pb.opt).structure:
            order = sorted(rest, key=lambda n: -tests[n][0].delta_chi2)[:2]
        accepted = None
        for best in order[:2]:
            trial = pb.refit(res, named + [best], lin, tests[best][0].fit)
            lin_t = pb.linearize(trial, named + [best])
            pb.remember(named + [best], trial, lin_t)
            if not (np.all(np.isfinite(lin_t.r)) and np.all(np.isfinite(lin_t.J))):
                rejected.add(best)                   # the refit left the model's workspace
                board[best].reason = "the nonlinear refit could not assemble every measured pose"
                continue
            model_t = [k for k in trial.names if effect_of_key(k) != best]
            t = _test_round(pb, huber_weighted(lin_t, lin_t.cols(list(trial.names))), model_t, [best],
                            in_play=in_play)[best]
            v = pb.value_final(trial, best)
            history[best] = (t[0], v, t[2] and v.plausible) + t[3:]
            if history[best][2]:
                accepted = (best, trial, lin_t)
                break
            rejected.add(best)
            if not v.plausible:
                board[best].reason = f"after the nonlinear refit: {v.why}"
        if accepted is None:
            break
        best, res, lin = accepted
        named.append(best)
        for n in named[:-1]:                         # re-test the earlier names with the new one in
            model_n = [k for k in res.names if effect_of_key(k) != n]
            t = _test_round(pb, huber_weighted(lin, lin.cols(list(res.names))), model_n, [n], in_play=in_play)[n]
            if not t[2]:
                named.remove(n)
                board[n].reason = f"absorbed once {best} was added"
                res = pb.refit(res, named)
                lin = pb.linearize(res, named)
                pb.remember(named, res, lin)
    return named, res, lin, history


def _verdicts(pb: _Problem, board: dict[str, Candidate], history: dict, named: list[str],
              values: list[EffectValue], counts: dict[str, int], n_folds: int, cv_ran: bool) -> None:
    """The scoreboard's verdict and reason for every candidate."""
    need = int(np.ceil(pb.opt.min_folds * n_folds))
    for n, c in board.items():
        c.cv_folds = counts.get(n, 0)
        if n in history:
            t, v, ok, level, share = history[n]
            c.delta_chi2, c.nu, c.F, c.p_value, c.value, c.share = t.delta_chi2, t.k, t.F, t.p_value, v, share
            c.threshold = level
        if n in named:
            c.verdict, c.value = "named", values[named.index(n)]
            c.reason = c.reason or f"selected in {counts[n]} of {n_folds} cross-validation folds"
        elif not c.available:
            continue
        elif n in history and c.p_value < c.threshold:
            v, rms = c.value, np.sqrt(c.delta_chi2 / max(history[n][0].fit.n, 1))
            if not v.plausible:
                c.verdict, c.reason = "implausible value", c.reason or v.why
            elif rms < pb.opt.min_rms_sigma:
                c.verdict = "too small"
                c.reason = c.reason or (f"changes the measurements by {rms:.2g} sigma RMS "
                                                 f"(less than {pb.opt.min_rms_sigma:g})")
            elif c.share < pb.opt.min_explained:
                c.verdict = "explains only part of the structure"
                c.reason = (f"significant, but explains {100 * c.share:.2g} % of the structure left beyond the "
                            "noise: not forced onto this name")
            elif c.reason.startswith(("leaves structure", "on held-out poses")):
                c.verdict = "explains only part of the structure"
            elif cv_ran and (counts.get(n, 0) < need or c.reason.startswith("does not predict")):
                c.verdict = "not confirmed on held-out poses"
                c.reason = c.reason or f"selected in {counts.get(n, 0)} of {n_folds} cross-validation folds"
            else:
                c.verdict = "not significant once the named effects are in"
        elif c.power_typical < 0.1:
            info = VOCABULARY[n]
            c.verdict = "not identifiable with this campaign"
            c.reason = c.reason or (f"at a typical size ({info.typical:g} {info.unit}) it would be detected "
                                    f"with probability {c.power_typical:.2f}: the baseline absorbs "
                                    f"{100 * (1 - c.survival):.3g} % of its signature")
        else:
            c.verdict = "not significant"


def _confirm(pb: _Problem, lin0: Linearization, named: list[str], res: IdentResult, lin: Linearization,
             board: dict[str, Candidate], cv_before: np.ndarray):
    """Step e: the selection runs again inside every cross-validation fold (training poses only); a name
    stays if at least ``min_folds`` of the folds select it and the named model predicts the held-out
    poses better than the baseline. Returns the fold counts and the (re)fitted model."""
    n_folds = len(np.unique(pb.folds))
    counts = {n: 0 for n in pb.candidates}
    if not named:                                    # nothing named: nothing to confirm
        return counts, named, res, lin
    for f in range(n_folds):
        for n in _fold_selection(pb, ~lin0.rows(np.flatnonzero(pb.folds == f))):
            counts[n] += 1
    need = int(np.ceil(pb.opt.min_folds * n_folds))
    confirmed = [n for n in named if counts[n] >= need]
    if confirmed == named:
        cv_named = _cv(lin, lin.cols(list(res.names)), pb.folds)
        inside = ~lin.rows(_extrapolated(pb, lin, res)[0])   # as the reported gaps
        if cv_named[inside] @ cv_named[inside] >= cv_before[inside] @ cv_before[inside]:
            confirmed = []
            for n in named:
                board[n].reason = "does not predict held-out poses better than the baseline"
    if confirmed != named:
        res = pb.refit(res, confirmed) if confirmed else pb.baseline
        lin = pb.linearize(res, confirmed)
    return counts, confirmed, res, lin


#: The context that defines a family (residual_context names, first one recorded).
FAMILY_CONTEXT = {"thermal_expansion": ("temperature",), "zero_offset_drift": ("time", "row order"),
                  "frame_drift": ("time", "row order")}


def _own_context_left(pb: _Problem, named: list[str], res: IdentResult, lin: Linearization,
                      board: dict[str, Candidate]):
    """A family defined by a context must leave nothing that follows that context: when structure is left
    after the named model and its held-out residual still follows the family's own context (F test per
    pose, p < ``gate_alpha``), the family explains only part of an effect it does not contain (e.g. a
    tracker stand creeping with the temperature, which per-group expansion mimics in part). It is then
    not named, and the residual context says what the structure follows. Returns (named, fit, lin)."""
    ctx_named = [n for n in named if n in FAMILY_CONTEXT]
    if not ctx_named or not omnibus(lin, fit(lin, lin.cols(list(res.names))), pb.noise, pb.opt).structure:
        return named, res, lin
    cv = _cv(lin, lin.cols(list(res.names)), pb.folds) * pb.sigma
    links = {c.context: c for c in characterise(pb.meas, cv.reshape(pb.meas.targets.shape), top=100)}
    drop = []
    for n in ctx_named:
        c = next((links[k] for k in FAMILY_CONTEXT[n] if k in links), None)
        if c is not None and c.p_value < pb.opt.gate_alpha:
            drop.append(n)
            board[n].reason = (f"leaves structure that still follows the {c.context} ({100 * c.share:.0f} % of it, "
                               f"p = {c.p_value:.2g}): it explains only part of a {c.context}-driven effect "
                               "outside the family, not forced onto it")
    if not drop:
        return named, res, lin
    keep = [n for n in named if n not in drop]
    res = pb.refit(res, keep) if keep else pb.baseline
    return keep, res, pb.linearize(res, keep)


def held_out_shares(pb: _Problem, named: list[str], res: IdentResult, lin: Linearization,
                    excess_sd: dict[str, float] | None = None) -> dict[str, float]:
    """Share of the held-out structure each named effect removes: with ``S_without`` the held-out sum of
    squares (whitened, the cross-validation folds, poses predicted by extrapolation left out) of the named
    model without the effect (its columns set to zero, the rest refitted in every fold), ``S_with`` that of
    the named model and ``E`` what noise alone leaves held out (rows + the effective parameter count over
    the training share, each held-out prediction carrying its fit's variance), the share is
    ``(S_without - S_with) / (S_without - E)``: 1 when the effect explains everything beyond the noise on
    rows it was not fitted to, near 0 when it is a significant sliver of a larger structure. 1 when the
    model without it leaves nothing beyond the noise (nothing to measure the share on). ``excess_sd``, if
    given, receives ``(S_without - S_with) / sqrt(2 n)`` per effect (n held-out rows): how clearly the
    effect's own held-out improvement stands out of the noise of a held-out sum of squares (below ~2 the
    share is mostly noise: a 0.01 deg eccentricity, 0.3-1.7)."""
    cols = lin.cols(list(res.names))
    inside = ~lin.rows(_extrapolated(pb, lin, res)[0])
    cv = _cv(lin, cols, pb.folds)
    s_with = float(cv[inside] @ cv[inside])
    k = len(np.unique(pb.folds))
    out = {}
    for n in named:
        drop = lin.cols(pb.candidates[n])
        keep = np.setdiff1d(cols, drop)
        cv0 = _cv(lin, keep, pb.folds, drop)
        s_without = float(cv0[inside] @ cv0[inside])
        p_eff = fit(lin, keep).p_eff
        noise = inside.sum() * (1.0 + p_eff / (len(lin.r) * (1.0 - 1.0 / k)))
        excess = s_without - noise
        out[n] = 1.0 if excess <= 0 else float(min(max((s_without - s_with) / excess, 0.0), 1.0))
        if excess_sd is not None:
            excess_sd[n] = float((s_without - s_with) / np.sqrt(2.0 * inside.sum()))
    return out


def _held_out_sums(lin: Linearization, cols: np.ndarray, folds: np.ndarray, inside: np.ndarray,
                   drop: np.ndarray | None = None) -> tuple[float, float]:
    """Held-out misfit (whitened) over the rows ``inside`` of the model ``cols`` (``drop`` taken out), each
    fold predicted from a fit on the others, standardised by its predictive covariance under noise alone,
    and its expectation then (the number of rows). A held-out row's prediction error under noise is its
    own noise plus what the training rows' noise does to the fit: covariance ``C = I + J M^-1 H M^-1 J^T``
    (``J`` the held-out rows, ``H`` the training information, ``M = H + I`` with the unit priors), so
    ``r^T C^-1 r`` is chi-square with a degree of freedom a row, for any split, also one that holds out
    a region whole and so extrapolates (a few poses at the tilted edge of a region are predicted with
    ~100 times the noise variance there; unstandardised they decide the sum by their one draw). The
    prior's own uncertainty is not noise: a direction the training rows do not determine stays at the
    prior, and what that leaves held out counts as misfit."""
    s = e = 0.0
    for f in np.unique(folds):
        test = lin.rows(np.flatnonzero(folds == f))
        sub = fit(lin, cols, ~test, drop)
        keep = inside[test]
        r = predict(lin, sub, test, drop)[keep]
        J = lin.J[test][:, cols][keep]
        A = np.linalg.solve(sub.info + np.eye(len(cols)), J.T)          # (p, rows)
        C = np.eye(len(r)) + A.T @ sub.info @ A
        s += float(r @ np.linalg.solve(C, r))
        e += float(keep.sum())
    return s, e


@dataclass
class Transfer:
    """How a named effect transfers across the workspace (:func:`transfer_shares`)."""

    share: float        # share of the region-held-out excess of the model without it that it removes
    z_left: float       # region-held-out excess the named model leaves, in standard deviations of noise


def transfer_shares(pb: _Problem, named: list[str], res: IdentResult, lin: Linearization) -> dict[str, Transfer]:
    """Transfer of each named effect across the workspace, reported beside the held-out share (not used to
    decide): with whole regions held out (:func:`region_folds`), ``S_with`` the standardised held-out
    misfit of the named model, ``S_without`` that of the model without the effect and ``n`` the held-out
    rows (:func:`_held_out_sums`), the share is ``(S_without - S_with) / (S_without - n)`` and ``z_left``
    is ``(S_with - n) / sqrt(2 n)``. A physical effect has parameters of the machine: fitted on the other
    regions they predict a region held out. Standardised by the predictive covariance, the cross-sim's
    tracker range error fitted as passive-limb geometry plus thermal parts transfers about as well as it
    is held out in the stratified folds (region shares 0.75-0.95, z_left 1.3-6.9, seeds 1000-1015): the
    region split does not separate that alias reliably (docs/diagnose.md, Decisions)."""
    cols = lin.cols(list(res.names))
    inside = ~lin.rows(_extrapolated(pb, lin, res)[0])
    s_with, e_with = _held_out_sums(lin, cols, pb.regions, inside)
    z_left = (s_with - e_with) / np.sqrt(2.0 * inside.sum())
    out = {}
    for n in named:
        drop = lin.cols(pb.candidates[n])
        s0, e0 = _held_out_sums(lin, np.setdiff1d(cols, drop), pb.regions, inside, drop)
        excess = s0 - e0
        share = 1.0 if excess <= 0 else float(min(max((s0 - s_with) / excess, 0.0), 1.0))
        out[n] = Transfer(share, float(z_left))
    return out


def _typical_factor(pb: _Problem, lin: Linearization, name: str) -> float:
    """How much larger a typical-size instance of ``name`` is than its fit in ``lin``: the square root of the
    ratio of their noncentralities beyond the baseline (the scoreboard's typical draws, the conditional
    information at the baseline), at least 1. A per-motor effect is compared motor by motor: a typical
    instance on one motor against the fit's larger motor part (an eccentricity on one motor is not asked
    to show what one on both motors would)."""
    from pmcal.calib.ocpm.effect_values import MOTOR_PARAMS

    if name not in pb.typical_nc:
        return 1.0
    Z, I_c = pb.typical_nc[name]
    z = lin.z0[lin.cols(pb.candidates[name])]
    parts = [list(idx) for idx in MOTOR_PARAMS[name]] if (
        name in MOTOR_PARAMS and len(z) == len(VOCABULARY[name].keys)) else [list(range(len(z)))]

    def nc(x, idx):                          # noncentrality of the part idx of x (rows: instances)
        xm = np.zeros_like(x)
        xm[..., idx] = x[..., idx]
        return np.einsum("...i,ij,...j->...", xm, I_c, xm)

    nc_typ = float(np.mean([nc(Z, idx).mean() for idx in parts]))
    nc_fit = max(float(nc(z, idx)) for idx in parts)
    return float(np.sqrt(max(nc_typ / nc_fit, 1.0))) if nc_fit > 0 else 1.0


def _earned_on_held_out(pb: _Problem, named: list[str], res: IdentResult, lin: Linearization,
                        board: dict[str, Candidate]):
    """A name is earned on held-out data: every named effect's held-out share (:func:`held_out_shares`, the
    stratified folds) must be what the effect would leave if it were the truth and more than a structure of
    the same size outside it would give (:func:`pmcal.calib.ocpm.held_out_test.held_out_test`: a parametric
    bootstrap on the same poses, linearised at the named fit; the observed share at or above the
    candidate-true 5 % quantile and above the alternative's 95 % quantile). The candidate-true requirement
    is the highest of the 5 % quantiles in the named model, with the candidate alone beside the baseline
    (what other named effects take of it is not excused) and, where the share is measured clearly, at a
    typical size if the fit is smaller (:func:`_typical_factor`: a tracker range error held out by
    passive-limb geometry and thermal expansion together leaves thermal 0.47 against a band from 0.36 at
    its fitted 11e-6/K, what a true small thermal expansion would leave too, but 0.98 at a typical
    23e-6/K), at most ``min_held_out_measured`` (0.75; :attr:`HeldOutBand.need`). How much of a true effect
    survives held out depends on how much of it the geometry absorbs: a 0.02 deg eccentricity leaves
    0.5-0.8 with 0.01 mm noise (cross-sim), an effect the geometry cannot absorb 0.95-1.0; a fixed share
    (0.75 before issue 31) threw the eccentricity away to keep a tracker range error (shares 0.68-0.96 of
    passive-limb geometry, whose candidate-true band lies higher) from being named.

    When structure is left after the named model, a name beside it must in addition remove
    ``min_held_out_left`` (0.9) of a clearly measured held-out excess (its own improvement beyond
    ``measured_sd`` = 2.5 standard deviations of the noise of a held-out sum of squares) and
    ``min_held_out`` (0.5) of one not measured clearly: a name beside an unexplained structure must not be
    a share of it (the passive-limb geometry alone removes 68-85 % of the range error and leaves 0.4 sigma of
    structure).

    One that does not is not named, the weakest first, and the rest are measured again; the structure is
    then reported unexplained with what it follows. The share with whole workspace regions held out
    (:func:`transfer_shares`) is reported beside it (``transfer_share``), not used to decide (docs/diagnose.md,
    Decisions). Returns (named, fit, lin, shares)."""
    shares: dict[str, float] = {}
    transfer: dict[str, Transfer] = {}
    bands: dict = {}
    while named:
        sd: dict[str, float] = {}
        shares.update(held_out_shares(pb, named, res, lin, sd))
        transfer.update(transfer_shares(pb, named, res, lin))
        cols = lin.cols(list(res.names))
        inside = ~lin.rows(_extrapolated(pb, lin, res)[0])
        for n in named:
            ecols = lin.cols(pb.candidates[n])
            # the typical size where the share is measured clearly (a weak effect's is mostly noise: the
            # cross-sim's thermal expansion under invar links, 0.67 with a band from 0.33 at its fitted size)
            typical = _typical_factor(pb, lin, n) if sd[n] > pb.opt.measured_sd else 1.0
            bands[n] = held_out_test(lin, cols, ecols, pb.folds, inside, shares[n], ceiling=pb.opt.min_held_out_measured,
                                     typical_factor=typical)
            if len(named) > 1:                 # were it the only effect: what the baseline alone absorbs of it
                others = lin.cols([k for m in named if m != n for k in pb.candidates[m]])
                alone = held_out_test(lin, np.setdiff1d(cols, others), ecols, pb.folds, inside, shares[n])
                bands[n] = dataclasses.replace(bands[n], alone=alone.candidate[0])
        structure = omnibus(lin, fit(lin, cols), pb.noise, pb.opt).structure
        need = {n: (pb.opt.min_held_out_left if sd[n] > pb.opt.measured_sd else pb.opt.min_held_out)
                if structure else 0.0 for n in named}
        weak = [n for n in named if shares[n] < need[n] or not bands[n].earned]
        if not weak:
            break
        weak = min(weak, key=lambda n: bands[n].observed - bands[n].need)
        b = bands[weak]
        if shares[weak] < need[weak]:
            why = (f"a name beside structure left needs {100 * need[weak]:.0f} %: a part of a larger structure "
                   "outside the family, not forced onto it")
        elif not b.consistent:
            why = (f"were it the truth (at its fitted size, or a typical one if larger) it would remove at least {100 * b.need:.0f} % of it: a "
                   "part of a larger structure outside the family, not forced onto it")
        else:
            why = (f"a structure of the same size outside the family would give up to {100 * b.alternative[2]:.0f} % "
                   "(95 % quantile): not told apart from one")
        board[weak].reason = (f"on held-out poses it removes {100 * shares[weak]:.0f} % of the structure beyond "
                              f"the noise that the model without it leaves; {why}")
        named = [n for n in named if n != weak]
        res = pb.refit(res, named) if named else pb.baseline
        lin = pb.linearize(res, named)
    for n, c in board.items():                  # an earlier pass's measurement stays when this one had none
        c.held_out_share = shares.get(n, c.held_out_share)
        c.held_out_band = bands.get(n, c.held_out_band)
        c.transfer_share = transfer[n].share if n in transfer else c.transfer_share
    return named, res, lin, shares


def _attribute_motors(pb: _Problem, named: list[str], res: IdentResult, lin: Linearization,
                      values: list[EffectValue], board: dict[str, Candidate]) -> list[EffectValue]:
    """Per-motor attribution of the named per-motor effects (backlash, eccentricity, drift): a motor carries
    the effect when its own parameters differ from zero (Wald test at 95 %, :func:`per_motor_values`) and
    either

    - its own part is not consistent with zero on held-out poses by the calibrated held-out test
      (:func:`pmcal.calib.ocpm.held_out_test.held_out_test` with that motor's columns only): its held-out
      improvement exceeds what a structure of the same size outside it gives (95 % quantile); or
    - its own part is significant in the named model at the level a name needs (issue 31, 48 poses):
      the nested test of the motor's columns against the named model without them
      (:func:`pmcal.calib.ocpm.linear_tests.nested_test`: the directions its conditional information
      determines once the geometry and the other motor's part have absorbed what they can, classical F
      and pose-clustered Hotelling both rejecting) at p < :func:`motor_level` (the diagnosis' level
      ``alpha`` shared over the motors tested). The held-out test of one motor's part has little power
      where the geometry absorbs most of it: a true 0.019 deg second-motor eccentricity at 48 poses
      (Wald chi2 35, p 2e-8) gave a held-out band of -1.45..7.08 for the part were it true and up to 1.15
      for an alternative, and its observed -0.34 dropped the motor. The in-sample test at the naming
      level keeps such a part; a leak of the other motor's creeping drift (Wald p 0.004-0.04 on the
      cross-sim) is still judged by the held-out test.

    Also asking that the part's candidate-true 5 % quantile be above zero named fewer campaigns on their
    motors (cross-sim tuning seeds 200-219: 10 against 13 of 20 at 48 poses, 17 against 18 at 128; the same
    18 with drift on the other motor). An effect is reported on one motor only when the other motor's part
    passes neither test; when neither motor's part passes on its own, the Wald test's motors stay (the two
    parts may only be seen together). A drift on motor 1 beside an eccentricity on motor 2 leaves a
    significant drift on motor 2 (Wald) that does not predict held-out poses: it is not reported there."""
    from pmcal.calib.ocpm.effect_values import MOTOR_PARAMS

    cols = lin.cols(list(res.names))
    inside = ~lin.rows(_extrapolated(pb, lin, res)[0])
    out = []
    for n, v in zip(named, values):
        keys = pb.candidates[n]
        if n not in MOTOR_PARAMS or len(v.motors) < 2 or len(keys) != len(VOCABULARY[n].keys):
            out.append(v)
            continue
        parts = {m + 1: lin.cols([keys[i] for i in idx]) for m, idx in enumerate(MOTOR_PARAMS[n])}
        tests = {m: held_out_test(lin, cols, part, pb.folds, inside, float("nan"), seed=m)
                 for m, part in parts.items()}
        robust = huber_weighted(lin, cols)
        p_part = {m: nested_test(robust, np.setdiff1d(cols, part), part).p_value for m, part in parts.items()}
        level = motor_level(pb.opt.alpha, len(parts))
        board[n].motor_bands = tests
        board[n].motor_p_values = p_part
        carry = tuple(m for m in v.motors if tests[m].beyond_alternative or p_part[m] < level)
        if carry and carry != tuple(v.motors):
            v = pb.value_final(res, n, carry)
            off = [m for m in (1, 2) if m not in carry]
            v.note = (v.note + "; " if v.note else "") + (
                f"{n}: reported on motor {carry[0]} only: motor {off[0]}'s own part is consistent with zero on "
                f"held-out poses (improvement {tests[off[0]].observed:.2g} of the held-out excess, a structure of "
                f"its size outside it gives up to {tests[off[0]].alternative[2]:.2g}) and not significant by "
                f"itself at the naming level (p = {p_part[off[0]]:.2g}, needs {level:.2g})")
        out.append(v)
    return out


def motor_level(alpha: float, motors: int) -> float:
    """The level at which a motor's part of a named per-motor effect is significant by itself (per-motor
    attribution, docs/diagnose.md): the diagnosis' family-wise naming level ``alpha`` shared over the
    ``motors`` parts tested (Bonferroni), so that this route attributes a named effect to a motor that
    carries none of it with probability at most ``alpha`` (0.003) per named effect, whatever the
    campaign size (the model being right; the pose-clustered test keeps it under pose-level misfit).

    >>> motor_level(0.003, 2)
    0.0015
    """
    return float(alpha) / max(int(motors), 1)


def _notes(board: dict[str, Candidate], named: list[str], om: Omnibus, opt: DiagnoseOptions) -> list[str]:
    notes = []
    if om.structure:
        rejected = [n for n, c in board.items() if c.verdict in (
            "implausible value", "too small", "not confirmed on held-out poses", "explains only part of the structure")]
        notes.append(f"structure left beyond the noise: {om.excess_mm:.3g} mm RMS (p = {om.p_value:.2g}) "
                     "that no candidate explains" + (f"; rejected candidates: {', '.join(rejected)}" if rejected else ""))
    elif om.p_value < opt.gate_alpha:
        notes.append(f"the residual exceeds the noise a little ({om.excess_mm:.2g} mm RMS by the robust "
                     "measure): heavy-tailed noise or a mismatch too small to matter")
    return notes + [f"{n}: {board[n].reason}" for n in named] + _size_notes(board, named)


def _size_notes(board: dict[str, Candidate], named: list[str]) -> list[str]:
    """A note per family this campaign would miss at a plausible (typical) size: detected with probability
    below :data:`DETECT_POWER` (those below 0.1 are "not identifiable" on the scoreboard, with their fix),
    with the smallest size it detects at 90 % and the measurement that fixes it."""
    out = []
    for n, c in board.items():
        if n in named or not c.available or not 0.1 <= c.power_typical < DETECT_POWER:
            continue
        info = VOCABULARY[n]
        typ = 2 * info.typical if n == "backlash" else info.typical
        reach = "K up to" if n == "joint_compliance" else "from"
        out.append(f"campaign size: {n} of {typ:.3g} {info.unit} (a typical size) would be detected with "
                   f"probability {c.power_typical:.2f}; this campaign detects {reach} {c.detectable_90:.3g} "
                   f"{info.unit} at 90 %: {info.fix}; the 128-pose diagnosis plan to 80 deg (pmcal twin plan "
                   "--for-diagnosis) detects the typical sizes (docs/diagnose.md, campaign size)")
    return out


def diagnose(meas: Measurements, model: EffectModel, options: DiagnoseOptions | None = None,
             on_step=None) -> Diagnosis:
    """Run the diagnosis (module docstring) with the whole-chain ``model`` that carries the effect terms
    (:class:`pmcal.twin.ocpm.effect_model.EffectChainModel`). ``on_step(text)`` reports progress."""
    t_start = time.perf_counter()
    limit_blas_threads()
    opt = options or DiagnoseOptions()
    step = on_step or (lambda text: None)
    pre_notes = _confounding(meas)
    if meas.approach is None and len(meas) > 1:
        meas = dataclasses.replace(meas, approach=approach_from_order(meas.m_cmd_deg)).subset(np.arange(1, len(meas)))
        pre_notes.append("approach inferred from the row order (sign of each motor's last move); the first row, "
                         "whose approach is unknown, is left out; m1_approach/m2_approach columns take precedence")
    pb = _Problem(meas, opt, model)

    step("fitting the baseline model")                               # a
    x0 = None
    if opt.initial:
        x0 = {k: (np.deg2rad(v) if is_angular(k) else v) for k, v in opt.initial.items() if k in pb.base_keys}
    base = pb.baseline = pb.identify([], x0)
    pb.model_keys0 = list(base.names)
    lin0 = pb.linearize(base, [])
    pb.remember([], base, lin0)
    board = _scoreboard(pb, lin0)                                    # b, c
    pre_notes = _confounding_share(pre_notes, pb, lin0)
    om0 = omnibus(lin0, fit(lin0, lin0.cols(pb.model_keys0)), pb.noise, opt)

    step("testing candidate effects")                                # d
    named, res, lin, history = _select(pb, base, lin0, board)

    step("cross-validating")                                         # e
    cv_before = _cv(lin0, lin0.cols(pb.model_keys0), pb.folds)
    cv_ran = bool(named)
    counts, named, res, lin = _confirm(pb, lin0, named, res, lin, board, cv_before)
    while True:                     # each rule re-measured once the other has dropped a name
        before = list(named)
        named, res, lin = _own_context_left(pb, named, res, lin, board)
        named, res, lin, shares = _earned_on_held_out(pb, named, res, lin, board)
        if named == before:
            break

    cv_after = _cv(lin, lin.cols(list(res.names)), pb.folds)       # f
    om1 = omnibus(lin, fit(lin, lin.cols(list(res.names))), pb.noise, opt)
    values = _attribute_motors(pb, named, res, lin, [pb.value_final(res, n) for n in named], board)
    _verdicts(pb, board, history, named, values, counts, len(np.unique(pb.folds)), cv_ran)

    unexplained = om1.structure                                      # g
    context = characterise(pb.meas, (cv_after * pb.sigma).reshape(meas.targets.shape)) if unexplained else []
    if unexplained:
        pre_notes.append(describe(context))
    verdict = ("named+unexplained" if named else "unexplained") if unexplained else ("named" if named else "noise")
    far, lev = _extrapolated(pb, lin, res)
    inside = ~lin.rows(far)
    gap = lambda cv, rows: float(np.sqrt(np.mean(cv[rows] ** 2)) * pb.sigma)  # noqa: E731
    shape = meas.targets.shape
    return Diagnosis(
        effect=named[0] if named else None, effects=named, gap_before=gap(cv_before, inside),
        gap_after=gap(cv_after, inside), noise=pb.noise, verdict=verdict,
        unexplained=unexplained, notes=pre_notes + _notes(board, named, om1, opt)
        + [v.note for v in values if v.note] + _extrapolated_note(pb, lin, far, lev, cv_after),
        candidates=board, named=values,
        extrapolated=[pb.meas.pose_id[i] for i in far], gap_before_all=gap(cv_before, slice(None)),
        gap_after_all=gap(cv_after, slice(None)),
        baseline=base, final=res, omnibus_before=om0, omnibus_after=om1, time_unit=pb.time_unit, meas=pb.meas,
        lin_before=lin0, lin_after=lin, cv_before=(cv_before * pb.sigma).reshape(shape),
        cv_after=(cv_after * pb.sigma).reshape(shape), folds=pb.folds, runtime_s=time.perf_counter() - t_start,
        added_variable=_added_variable(pb, lin, res), unexplained_context=context)


def _extrapolated(pb: _Problem, lin: Linearization, res: IdentResult) -> tuple[np.ndarray, np.ndarray]:
    """Poses (indices, highest leverage first) whose held-out prediction is an extrapolation: each
    determines more than ``max_leverage`` directions of the model ``res`` by itself, at most
    ``max_extrapolated`` of the poses; and every pose's leverage (N,). Such a pose (typically alone at the
    edge of the campaign) is predicted from poses that barely see a direction of the geometry, so its
    held-out residual says little about the model; the gaps are taken without it."""
    lev = pose_leverage(lin, lin.cols(list(res.names)))
    cap = int(pb.opt.max_extrapolated * len(lev))
    return np.array([i for i in np.argsort(-lev)[:cap] if lev[i] > pb.opt.max_leverage], int), lev


def _extrapolated_note(pb: _Problem, lin: Linearization, far: np.ndarray, lev: np.ndarray,
                       cv: np.ndarray) -> list[str]:
    """The note naming the poses ``far`` left out of the gaps (:func:`_extrapolated`), with their held-out
    residual (``cv``, whitened)."""
    if not far.size:
        return []
    m = pb.meas
    per_pose = np.sqrt(np.bincount(lin.pose, weights=cv**2) / np.bincount(lin.pose)) * pb.sigma
    desc = "; ".join(f"{m.pose_id[i]} (motors {m.m_cmd_deg[i, 0]:.1f}/{m.m_cmd_deg[i, 1]:.1f} deg, leverage "
                     f"{lev[i]:.2g}, held-out residual {per_pose[i]:.3g} mm RMS)" for i in far)
    return [f"left out of the held-out gaps: {desc}; each determines more than {pb.opt.max_leverage:g} "
            "direction of the model by itself, so held out it is predicted by extrapolation; measure a "
            "pose beside it to check the model there"]


def _confounding(meas: Measurements) -> list[str]:
    """A note when temperature follows time monotonically: thermal expansion and zero-offset drift then
    have near-identical context and are told apart only by their geometric form."""
    if meas.temp_c is None or not np.all(np.isfinite(meas.temp_c)) or np.ptp(meas.temp_c) == 0:
        return []
    t = meas.time_s if meas.time_s is not None and np.all(np.isfinite(meas.time_s)) else np.arange(len(meas))
    rho = stats.spearmanr(t, meas.temp_c).statistic
    if abs(rho) < 0.9:
        return []
    return [f"temperature follows time monotonically (Spearman {rho:.2f}): thermal expansion and zero-offset "
            "drift are confounded in this campaign; a warm-up then cool-down (or a constant-temperature run) "
            "separates them"]


def _confounding_share(notes: list[str], pb: _Problem, lin: Linearization) -> list[str]:
    """Add to the confounding note how much of a linear drift's signature the thermal family absorbs beyond
    the baseline (1 - trace ratio of the drift's conditional information without and with it); a campaign
    whose temperature is not monotone in time but where that share is over a half gets the note too."""
    if not {"thermal_expansion", "zero_offset_drift"} <= set(pb.candidates):
        return notes
    base = lin.cols(pb.model_keys0)
    drift = lin.cols(["zero_offset_drift.r1", "zero_offset_drift.r2"])
    both = np.concatenate([base, lin.cols(pb.candidates["thermal_expansion"])])
    i0 = np.trace(conditional_information(lin, base, drift))
    share = 1.0 - np.trace(conditional_information(lin, both, drift)) / i0 if i0 > 0 else 0.0
    text = f"the thermal family absorbs {100 * share:.0f} % of a linear drift's signature here"
    out = [n + f" ({text})" if "confounded" in n else n for n in notes]
    if out == notes and share > 0.5:
        out.append(f"thermal expansion and zero-offset drift are confounded in this campaign: {text}")
    return out


def _added_variable(pb: _Problem, lin: Linearization, res: IdentResult) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Added-variable data per available candidate at the final fit, per row (mm): x the candidate's
    signature in the direction of its fitted parameters with the rest of the model projected out, y the
    residual of the model without it. A slope of 1 through the cloud: it explains that part."""
    out = {}
    every = np.ones(len(lin.r), bool)
    for name, keys in pb.candidates.items():
        ecols = lin.cols(keys)
        mcols = lin.cols([k for k in res.names if effect_of_key(k) != name])
        t = nested_test(lin, mcols, ecols)
        J = lin.J[:, mcols]
        S = lin.J[:, ecols] @ (lin.z0[ecols] + t.fit.dz[len(mcols):])
        x = S - J @ np.linalg.solve(J.T @ J + np.eye(len(mcols)), J.T @ S)
        out[name] = (x * pb.sigma, predict(lin, t.base, every, drop=ecols) * pb.sigma)
    return out
