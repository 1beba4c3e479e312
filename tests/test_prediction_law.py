"""The law of a campaign's compensated RMS error (ChainIdentResult.predicted_task_law, rms_band, share_above,
law_directions) checked against closed forms and against draws from the posterior itself.

A prediction is a posterior standard deviation: one campaign's error is a draw. Where one error direction
carries it, the draw is chi-square with one degree of freedom and one campaign in 7.5 ends above 1.5x the
prediction however good the identification; the band the demo reports says so."""

from types import SimpleNamespace

import numpy as np
import pytest
from scipy import stats

from pmcal.calib.closed_chain import ChainIdentResult, law_directions, rms_band, share_above


def _law(J, P, columns=None):
    return ChainIdentResult.predicted_task_law(SimpleNamespace(error_covariance=P), J, columns)


def _draws(J, P, n=40000, seed=7):
    """RMS over the targets of J delta, delta ~ N(0, P): the campaigns the law describes, drawn in the errors'
    own space (not from the law's weights)."""
    delta = np.random.default_rng(seed).multivariate_normal(np.zeros(len(P)), P, size=n)
    e = np.einsum("ncp,kp->knc", J, delta)
    return np.sqrt(np.mean(np.sum(e ** 2, axis=2), axis=1))


def test_one_direction_is_a_chi_square_with_one_degree_of_freedom():
    rng = np.random.default_rng(1)
    u = rng.normal(size=(30, 2, 1))
    J = u * rng.normal(size=(1, 1, 7))                        # every target sees one combination of 7 errors
    P = np.diag(rng.uniform(0.5, 2.0, 7))
    w = _law(J, P)
    ms = float(np.sum(w))
    assert ms == pytest.approx(np.mean(np.einsum("ncp,pq,ncq->n", J, P, J)))
    assert law_directions(w) == pytest.approx(1.0, abs=1e-9)
    lo, hi = rms_band(w)
    exact = np.sqrt(ms * stats.chi2.ppf([0.05, 0.95], 1))        # 0.0627 and 1.960 (the normal's 97.5 % point)
    assert lo == pytest.approx(exact[0], rel=0.02)
    assert hi == pytest.approx(exact[1], rel=0.005)
    assert share_above(1.5, w) == pytest.approx(2 * stats.norm.sf(1.5), abs=0.003)    # 0.1336


def test_equal_directions_give_their_count_and_a_chi_square_of_as_many_degrees():
    J = np.zeros((12, 1, 12))
    J[np.arange(12), 0, np.arange(12)] = 1.0                  # target i sees error i alone
    w = _law(J, 4.0 * np.eye(12))
    assert np.sum(w) == pytest.approx(4.0)                    # mean over targets of 4
    assert law_directions(w) == pytest.approx(12.0)
    assert rms_band(w) == pytest.approx(tuple(np.sqrt(4.0 / 12 * stats.chi2.ppf([0.05, 0.95], 12))), rel=0.005)
    assert share_above(1.5, w) == pytest.approx(stats.chi2.sf(2.25 * 12, 12), abs=0.002)


def test_mixed_directions_match_draws_in_the_errors_own_space():
    """Band edges and the share above 1.5x against 40 000 campaigns drawn from the posterior over the errors:
    within what 40 000 draws allow (2 % on the edges, 1 point on the share)."""
    rng = np.random.default_rng(2)
    J = rng.normal(size=(40, 3, 9)) * np.array([3.0, 1.5, 1.0, 0.6, 0.3, 0.2, 0.1, 0.05, 0.02])
    A = rng.normal(size=(9, 9))
    P = A @ A.T / 9 + 0.1 * np.eye(9)
    w = _law(J, P)
    rms = _draws(J, P)
    assert np.mean(rms ** 2) == pytest.approx(np.sum(w), rel=0.02)
    assert 1.0 < law_directions(w) < 9.0
    lo, hi = rms_band(w)
    assert np.quantile(rms, 0.05) == pytest.approx(lo, rel=0.02)
    assert np.quantile(rms, 0.95) == pytest.approx(hi, rel=0.02)
    assert np.mean(rms > 1.5 * np.sqrt(np.sum(w))) == pytest.approx(share_above(1.5, w), abs=0.01)


def test_columns_select_a_family():
    rng = np.random.default_rng(3)
    J = rng.normal(size=(20, 3, 5))
    P = np.eye(5)
    w_first = _law(J, P, [0])
    assert np.sum(w_first) == pytest.approx(np.mean(np.sum(J[:, 0, :] ** 2, axis=1)))
    assert np.sum(w_first) < np.sum(_law(J, P))
