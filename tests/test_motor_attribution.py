"""Per-motor attribution of a named per-motor effect (calib/ocpm/diagnose.py ``_attribute_motors``, issue 31)
on a synthetic linear problem shaped like an eccentricity at 48 poses: each motor's two columns are mostly a
combination of the geometry's (the geometry absorbs ~98 % of a first harmonic), with unit noise. A motor
whose part is true and clearly significant in the named model keeps the effect even where its held-out
test has no power; a motor without the effect is attributed at about the held-out test's rate."""

import dataclasses
from types import SimpleNamespace

import numpy as np
from scipy import stats

from pmcal.calib.ocpm import diagnose
from pmcal.calib.ocpm.diagnose import DiagnoseOptions, _attribute_motors, motor_level
from pmcal.calib.ocpm.linear_tests import Linearization, conditional_information

N_POSES, ROWS, P_BASE, FOLDS = 48, 3, 12, 10
EFFECT = "encoder_eccentricity"
KEYS = ["E.s1", "E.c1", "E.s2", "E.c2"]


def _campaign(rng, nc: tuple[float, float]) -> Linearization:
    """Whitened data: geometry (P_BASE columns) and the four eccentricity columns, each motor's part of
    noncentrality ``nc[m]`` once the geometry and the other motor's part have absorbed what they can
    (:func:`conditional_information`), linearised at the MAP fit of all columns (unit priors)."""
    n = N_POSES * ROWS
    Jb = 3.0 * rng.standard_normal((n, P_BASE))
    # ~98 % absorbed; what the geometry leaves is seen mostly at a few poses (the edge of the workspace,
    # per-pose scale lognormal): held out, those poses are predicted by extrapolation
    edge = np.repeat(np.exp(1.5 * rng.standard_normal(N_POSES)), ROWS)[:, None]
    S = Jb @ rng.standard_normal((P_BASE, 4)) + edge * rng.standard_normal((n, 4)) / 3.0
    J = np.hstack([Jb, S])
    keys = [f"b{i}" for i in range(P_BASE)] + KEYS
    m = len(keys)
    lin0 = Linearization(r=np.zeros(n), J=J, keys=keys, z0=np.zeros(m), pose=np.repeat(np.arange(N_POSES), ROWS),
                         sigma=1.0, scale=np.ones(m), mean=np.zeros(m))
    z = np.zeros(4)
    for k in (0, 1):
        part = P_BASE + np.array([2 * k, 2 * k + 1])
        other = P_BASE + np.array([2 - 2 * k, 3 - 2 * k])
        Ic = conditional_information(lin0, np.r_[np.arange(P_BASE), other], part)
        d = rng.standard_normal(2)
        z[2 * k:2 * k + 2] = d * np.sqrt(nc[k] / (d @ Ic @ d)) if nc[k] > 0 else 0.0
    y = Jb @ rng.standard_normal(P_BASE) * 0.1 + S @ z + rng.standard_normal(n)
    dz = np.linalg.solve(J.T @ J + np.eye(m), J.T @ y)
    return Linearization(r=y - J @ dz, J=J, keys=keys, z0=dz, pose=lin0.pose, sigma=1.0, scale=np.ones(m),
                         mean=np.zeros(m))


def _motors(lin: Linearization) -> tuple[tuple[int, ...], dict]:
    """The motors ``_attribute_motors`` reports for an effect the Wald test put on both, and its tests."""
    opt = DiagnoseOptions()
    opt.max_extrapolated = 0.0                         # no pose left out of the held-out sums
    pb = SimpleNamespace(candidates={EFFECT: KEYS}, folds=np.arange(N_POSES) % FOLDS, opt=opt,
                         value_final=lambda res, n, motors: SimpleNamespace(motors=tuple(motors), note=""))
    board = {EFFECT: SimpleNamespace(motor_bands={}, motor_p_values={})}
    res = SimpleNamespace(names=list(lin.keys))
    v = _attribute_motors(pb, [EFFECT], res, lin, [SimpleNamespace(name=EFFECT, motors=(1, 2), note="")], board)[0]
    return tuple(v.motors), board[EFFECT]


def test_motor_level_is_the_naming_level_over_the_motors():
    assert motor_level(0.003, 2) == 0.0015 and motor_level(0.003, 1) == 0.003


def _held_out_blind_on_motor_2(monkeypatch):
    """Motor 2's held-out test sees nothing (its observed improvement below any alternative), as where the
    geometry absorbs most of its part and a few extrapolated poses decide its held-out sums (cross-sim seed
    5011 at 48 poses: -0.34 against an alternative band up to 1.15 for a true 0.019 deg part)."""
    real = diagnose.held_out_test

    def blind(*args, seed=0, **kw):
        band = real(*args, seed=seed, **kw)
        return dataclasses.replace(band, observed=-np.inf) if seed == 2 else band
    monkeypatch.setattr(diagnose, "held_out_test", blind)


def test_a_true_part_significant_in_the_named_model_keeps_its_motor(monkeypatch):
    """Both motors carry the effect, each part of noncentrality 40 (two directions), motor 2's held-out test
    blind: the nested test at the naming level over two motors (0.0015) keeps motor 2 with probability
    ncx2.sf(chi2.isf(0.0015, 2), 2, 40) = 0.98, so in 20 campaigns in at least 17 (P < 1 % below that).
    The held-out test alone (the rule before) reported motor 1 only in all of them."""
    power = stats.ncx2.sf(stats.chi2.isf(motor_level(0.003, 2), 2), 2, 40.0)
    assert power > 0.975 and stats.binom.cdf(16, 20, power) < 0.01
    _held_out_blind_on_motor_2(monkeypatch)
    rng = np.random.default_rng(48)
    both = sum(_motors(_campaign(rng, (40.0, 40.0)))[0] == (1, 2) for _ in range(20))
    assert both >= 17, both


def test_a_motor_without_the_effect_is_kept_at_most_at_the_naming_level(monkeypatch):
    """Only motor 1 carries the effect (noncentrality 60), motor 2's columns fit noise and its held-out test
    is blind: motor 2 is kept only by the nested test, at its level 0.0015 (the pose-clustered test holds
    it): at most 1 of 40 campaigns (P = 0.2 % at that rate)."""
    assert stats.binom.sf(1, 40, 0.0015) < 0.002
    _held_out_blind_on_motor_2(monkeypatch)
    rng = np.random.default_rng(31)
    kept = 0
    for _ in range(40):
        motors, c = _motors(_campaign(rng, (60.0, 0.0)))
        kept += 2 in motors
        assert 1 in motors
    assert kept <= 1, kept


def test_a_motor_without_the_effect_is_rarely_kept():
    """Only motor 1 carries the effect (noncentrality 60), motor 2's columns fit noise: motor 2 is kept when
    its part is beyond the held-out test's alternative (about 5 %) or significant at 0.0015 (0.15 %): at most
    7 of 40 campaigns (P < 1 % at a 5.15 % rate)."""
    assert stats.binom.sf(7, 40, 0.0515) < 0.01
    rng = np.random.default_rng(31)
    kept = sum(2 in _motors(_campaign(rng, (60.0, 0.0)))[0] for _ in range(40))
    assert kept <= 7, kept
