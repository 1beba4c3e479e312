"""The calibrated held-out test (calib/ocpm/held_out_test.py, issue 31) on a synthetic linear problem: its
statistic is the held-out share of diagnose's folds, its candidate-true band holds shares of a true effect
at the nominal rate, and its alternative side refuses an effect that is not there at about its rate."""

import numpy as np
from scipy import stats

from pmcal.calib.ocpm.diagnose import _cv
from pmcal.calib.ocpm.held_out_test import held_out_test
from pmcal.calib.ocpm.linear_tests import Linearization, fit

N_POSES, ROWS, P_BASE, P_EFF, FOLDS = 60, 3, 6, 2, 10


def _problem(rng, effect_size: float):
    """Whitened data of a baseline (P_BASE columns) and an effect (P_EFF columns, RMS signature
    ``effect_size`` per row) with unit noise, linearised at the MAP fit of both (unit priors)."""
    n = N_POSES * ROWS
    J = rng.standard_normal((n, P_BASE + P_EFF))
    J[:, :P_BASE] *= 3.0                                        # well determined baseline directions
    z_eff = rng.standard_normal(P_EFF)
    z_eff *= effect_size * np.sqrt(n) / np.linalg.norm(J[:, P_BASE:] @ z_eff)
    y = J[:, :P_BASE] @ rng.standard_normal(P_BASE) * 0.1 + J[:, P_BASE:] @ z_eff + rng.standard_normal(n)
    dz = np.linalg.solve(J.T @ J + np.eye(J.shape[1]), J.T @ y)
    keys = [f"b{i}" for i in range(P_BASE)] + [f"e{i}" for i in range(P_EFF)]
    pose = np.repeat(np.arange(N_POSES), ROWS)
    m = len(keys)
    return Linearization(r=y - J @ dz, J=J, keys=keys, z0=dz, pose=pose, sigma=1.0, scale=np.ones(m),
                         mean=np.zeros(m))


def _test(lin, draws=200, seed=0):
    folds = np.arange(N_POSES) % FOLDS
    cols, ecols = np.arange(P_BASE + P_EFF), np.arange(P_BASE, P_BASE + P_EFF)
    return held_out_test(lin, cols, ecols, folds, np.ones(len(lin.r), bool), float("nan"), draws=draws, seed=seed)


def test_statistic_is_the_held_out_share_of_the_folds():
    """The statistic is the share (S_without - S_with) / (S_without - E) computed with diagnose's own fold
    residuals (_cv) where that lies in 0..1 with an excess above the noise's scatter, and 1 where the
    improvement exceeds the excess (12 campaigns, both branches met)."""
    folds = np.arange(N_POSES) % FOLDS
    cols, ecols = np.arange(P_BASE + P_EFF), np.arange(P_BASE, P_BASE + P_EFF)
    keep = np.setdiff1d(cols, ecols)
    branches = set()
    for seed in range(12):
        lin = _problem(np.random.default_rng(seed), 0.4)
        s_with = float(np.sum(_cv(lin, cols, folds) ** 2))
        s_without = float(np.sum(_cv(lin, keep, folds, ecols) ** 2))
        n = len(lin.r)
        e = n * (1.0 + fit(lin, keep).p_eff / (n * (1.0 - 1.0 / FOLDS)))
        excess, gain = s_without - e, s_without - s_with
        observed = _test(lin, draws=20).observed
        if excess > max(gain, np.sqrt(2 * n)) and gain > 0:
            assert abs(observed - gain / excess) < 1e-9
            branches.add("share")
        elif gain > excess and gain > np.sqrt(2 * n):
            assert abs(observed - 1.0) < 1e-9
            branches.add("one")
    assert branches == {"share", "one"}


def test_true_effect_is_consistent_at_the_nominal_rate_and_beyond_the_alternative():
    """Campaigns with a true effect of 0.3 noise RMS a row: the observed statistic is at or above the
    candidate-true 5 % quantile in about 95 % of them (40 campaigns: 38 expected; fewer than 33 has
    probability < 1 % under the nominal rate plus the quantile's own error from 200 draws), and above the
    alternative's 95 % quantile in at least 30 (observed statistics 0.1-1.0 of the held-out excess against
    alternative 95 % quantiles of 0.01-0.16: 35 of 40 with these seeds; below 30 has P < 1 % at a 90 %
    rate)."""
    rng = np.random.default_rng(11)
    bands = [_test(_problem(rng, 0.3), seed=k) for k in range(40)]
    consistent = sum(b.candidate[0] <= b.observed for b in bands)
    assert consistent >= 33, consistent
    assert stats.binom.cdf(32, 40, 0.95) < 0.01
    assert sum(b.beyond_alternative for b in bands) >= 30
    assert stats.binom.cdf(29, 40, 0.9) < 0.01


def test_absent_effect_is_not_beyond_the_alternative_often():
    """Campaigns without the effect (its columns fitted to noise): the observed held-out improvement exceeds
    the alternative's 95 % quantile rarely. The alternative carries a structure of the size of the chance
    in-sample improvement that the candidate cannot absorb on all poses, so its band is about that of no
    effect: 40 campaigns, nominal 2 (5 %); at most 7 (P < 1 % at a 5 % rate, and well below the half that
    would pass a test with no calibration)."""
    rng = np.random.default_rng(5)
    bands = [_test(_problem(rng, 0.0), seed=k) for k in range(40)]
    passed = sum(b.beyond_alternative for b in bands)
    assert passed <= 7, passed
    assert stats.binom.sf(7, 40, 0.05) < 0.01


def test_typical_size_raises_the_requirement_of_a_small_fit():
    """A small fitted effect is asked what a typical-size one would leave held out (capped): the 5 %
    quantile at 4 times the fitted parameters is higher than at the fitted ones, and ``need`` takes it up to
    the ceiling."""
    rng = np.random.default_rng(7)
    lin = _problem(rng, 0.12)
    folds = np.arange(N_POSES) % FOLDS
    cols, ecols = np.arange(P_BASE + P_EFF), np.arange(P_BASE, P_BASE + P_EFF)
    inside = np.ones(len(lin.r), bool)
    fitted = held_out_test(lin, cols, ecols, folds, inside, float("nan"), draws=200, ceiling=0.75)
    typical = held_out_test(lin, cols, ecols, folds, inside, float("nan"), draws=200, ceiling=0.75,
                            typical_factor=4.0)
    assert typical.typical > fitted.candidate[0] + 0.2
    assert typical.need == min(max(typical.typical, typical.candidate[0]), 0.75)
