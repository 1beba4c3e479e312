"""Discrepancy diagnosis: statistics, hidden effects, no-effect data, CLI and demo (docs/diagnose.md).

Campaigns come from the twin with an effect switched on at a size a real machine has and hidden from the
diagnosis (:func:`pmcal.apps.ocpm.effect_scenarios.hidden_effect_campaign`). The default suite runs one seed per case on a
96-pose campaign (128 for the eccentricity) and 50 + 30 no-effect seeds on 32-pose campaigns; the rates over many seeds are in
``benchmarks/diagnose_bench.py`` (and the slow test at the end).
"""

import json
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.stats import chi2

from pmcal.mechanism.ocpm.config import default_geometry
from pmcal.calib.ocpm.diagnose import DiagnoseOptions, _Problem, diagnose, limit_blas_threads
from pmcal.calib.ocpm.noise_estimate import estimate_noise, similarity_residuals
from pmcal.mechanism.ocpm.effects import EFFECT_NAMES, PASSIVE_KEYS, with_context
from pmcal.twin.ocpm.effect_model import EffectChainModel
from pmcal.calib.ocpm.fullchain import FullChainOptions, identify_full
from pmcal.calib.ocpm.linear_tests import Linearization, fit, nested_test, pose_leverage, predict
from pmcal.mechanism.ocpm.params import is_angular, random_errors
from pmcal.apps.ocpm.diagnosis import hidden_effect_demo
from pmcal.cli import main
from pmcal.ocpm.io import write_measurements
from pmcal.apps.ocpm.effect_scenarios import diagnosis_plan, hidden_effect_campaign
from pmcal.twin.ocpm.effects import EffectTwin, Effects, plan_effect_campaign
from pmcal.twin.tracker import LaserTracker

SIGMA = 0.01
G = default_geometry()
limit_blas_threads(1)


def run(names, seed=0, n=96, **kw):
    meas, twin = hidden_effect_campaign(names, seed, n, SIGMA, **kw)
    return diagnose(meas, EffectChainModel(), DiagnoseOptions(sigma_mm=SIGMA)), twin, meas


# ---------------------------------------------------------------------------------------- statistics
def test_model_free_noise_estimate():
    """The similarity residuals (2 dof a pose with 3 targets) estimate sigma without any machine model,
    also when the platform expands with temperature."""
    meas, _ = hidden_effect_campaign(["thermal_expansion"], 3, 200, SIGMA)
    res = similarity_residuals(meas.targets, G.targets)
    assert res.shape == meas.targets.shape
    est = estimate_noise(meas, G)
    tol = 3 * SIGMA / np.sqrt(2 * est.dof)                       # 3 std of the estimate
    assert est.source == "estimated" and est.dof == 2 * len(meas)         # a skipped pose leaves fewer rows
    assert abs(est.free_mm - SIGMA) < tol and abs(est.free_robust_mm - SIGMA) < 3 * tol
    assert estimate_noise(meas, G, 0.02).sigma_mm == 0.02


def _synthetic(rng, P=120, q=9, pose_sigma=0.0):
    """A random linear problem: 6 model columns, 2 effect columns, whitened noise. The effect columns and
    the optional pose-level noise move a pose's q coordinates together along one pattern ``v``, as an
    effect and a pose-level disturbance (joint scatter) do on the nine target coordinates of a pose."""
    n = P * q
    v = rng.normal(size=q)
    v /= np.linalg.norm(v)
    J = rng.normal(size=(n, 8)) * 3.0
    J[:, 6:] = (v[None, :, None] * rng.normal(size=(P, 1, 2)) * 3.0).reshape(n, 2)
    r = rng.normal(size=n) + (v[None] * rng.normal(size=(P, 1)) * pose_sigma).reshape(n)
    return Linearization(r=r, J=J, keys=[f"k{i}" for i in range(8)], z0=np.zeros(8), pose=np.repeat(np.arange(P), q),
                         sigma=1.0, scale=np.ones(8), mean=np.zeros(8))


def test_nested_test_holds_its_level_also_with_pose_level_errors():
    """Under the null the test rejects at about its level; with errors shared by a pose's coordinates
    the classical F test alone is anti-conservative, the clustered test (and so the combined) is not."""
    rng = np.random.default_rng(0)
    m, e = np.arange(6), np.array([6, 7])
    for pose_sigma, classic_bad in ((0.0, False), (3.0, True)):
        p = np.array([[t.p_value, t.p_classic] for t in
                      (nested_test(_synthetic(rng, pose_sigma=pose_sigma), m, e) for _ in range(300))])
        # binomial 300 x 0.05: 15 +- 3.8
        assert np.mean(p[:, 0] < 0.05) < 0.05 + 3 * 0.0126
        if classic_bad:
            assert np.mean(p[:, 1] < 0.05) > 0.3
    # and it finds a real effect
    lin = _synthetic(rng)
    lin.r = lin.r + lin.J[:, e] @ np.array([0.3, -0.2])
    assert nested_test(lin, m, e).p_value < 1e-6


def test_pose_leverage_closed_forms():
    """One column ``a`` on every row (a common offset, prior 1): each of P poses with q rows has leverage
    q a^2 / (P q a^2 + 1). A second column that only pose 7 sees (size c; the first then left off pose 7):
    pose 7 alone determines it, leverage c^2 / (c^2 + 1) -> 1, the others q a^2 / ((P - 1) q a^2 + 1)."""
    P, q, a, c = 40, 9, 3.0, 30.0
    pose = np.repeat(np.arange(P), q)
    J = np.zeros((P * q, 2))
    J[:, 0] = a
    lin = Linearization(r=np.zeros(P * q), J=J, keys=["k0", "k1"], z0=np.zeros(2), pose=pose, sigma=1.0,
                        scale=np.ones(2), mean=np.zeros(2))
    assert np.allclose(pose_leverage(lin, np.array([0])), q * a**2 / (P * q * a**2 + 1.0), rtol=1e-12)
    J[pose == 7] = [0.0, c / np.sqrt(q)]
    h = pose_leverage(lin, np.array([0, 1]))
    assert np.isclose(h[7], c**2 / (c**2 + 1.0), rtol=1e-12)
    assert np.allclose(np.delete(h, 7), q * a**2 / ((P - 1) * q * a**2 + 1.0), rtol=1e-12)


def test_held_out_misfit_is_chi_square_when_regions_are_held_out_whole():
    """A polynomial in a pose coordinate x (well determined, unit priors) fitted on noise alone: with the
    poses held out in contiguous blocks of x (a region whole, the far blocks predicted by extrapolation)
    the held-out misfit standardised by its predictive covariance (:func:`_held_out_sums`) is chi-square
    with a degree of freedom a row: over 200 draws its mean ratio to the rows is 1 within 0.015 (a draw
    scatters by ~4.5 %, the mean by ~0.3 %) and its spread that of chi-square (sqrt(2/n) within 20 %),
    whereas the plain held-out sum of squares is ~2.7 % high (the extrapolated blocks). A signal outside
    the columns adds its held-out misfit (3 sin(4x): ~40 % above)."""
    from pmcal.calib.ocpm.diagnose import _cv, _held_out_sums

    rng = np.random.default_rng(3)
    P, q = 120, 9
    pose = np.repeat(np.arange(P), q)
    x = np.repeat(np.linspace(-1, 1, P), q)
    J = 30.0 * np.stack([np.ones_like(x), x, x**2, x**3], 1)
    cols, folds, inside = np.arange(4), np.arange(P) * 6 // P, np.ones(P * q, bool)
    ratios, plain = [], []
    for _ in range(200):
        lin = Linearization(r=J @ rng.normal(0, 0.05, 4) + rng.normal(size=P * q), J=J, keys=list("abcd"),
                            z0=np.zeros(4), pose=pose, sigma=1.0, scale=np.ones(4), mean=np.zeros(4))
        s, n = _held_out_sums(lin, cols, folds, inside)
        ratios.append(s / n)
        cv = _cv(lin, cols, np.repeat(folds, q))
        plain.append(cv @ cv / n)
    assert abs(np.mean(ratios) - 1.0) < 0.015 and np.mean(plain) > 1.015
    assert abs(np.std(ratios) / np.sqrt(2.0 / (P * q)) - 1.0) < 0.2
    lin.r = lin.r + 3.0 * np.sin(4 * x)                      # a shape the cubic does not hold
    s, n = _held_out_sums(lin, cols, folds, inside)
    assert s > 1.2 * n


def test_region_folds_are_contiguous_parts_of_the_workspace():
    """Four azimuth sectors of the platform normal times two tilt bands of equal pose count: eight regions,
    each pose in one, each region's azimuths inside its sector, the bands split at the median tilt."""
    from pmcal.calib.ocpm.diagnose import region_folds

    meas, _ = hidden_effect_campaign([], 1000, 128, SIGMA)
    reg = region_folds(meas, G)
    _, R, _ = meas.poses(G)
    nrm = R[:, :, 2]
    az, tilt = np.arctan2(nrm[:, 1], nrm[:, 0]), np.arccos(np.clip(nrm[:, 2], -1, 1))
    assert set(reg) == set(range(8))
    for r in range(8):
        sector = np.minimum(((az[reg == r] + np.pi) // (np.pi / 2)).astype(int), 3)
        assert np.all(sector == r // 2)
    flat = reg % 2 == 0                                    # band 0: the less tilted half
    assert tilt[flat].max() <= tilt[~flat].min() and abs(flat.sum() - len(meas) / 2) <= 1


def test_weighted_bonferroni_spends_the_level_where_it_buys_power():
    """The levels of the candidates in play add up to alpha (family-wise level); the easily detected
    ones share ``easy_share`` of it; naming one hands its share to the rest."""
    from pmcal.calib.ocpm.linear_tests import alpha_weights

    w = alpha_weights({"a": 1.0, "b": 0.9995, "c": 0.5, "d": 0.2}, 0.1)
    assert w == {"a": 0.05, "b": 0.05, "c": 0.45, "d": 0.45}
    assert alpha_weights({"a": 1.0, "b": 1.0}, 0.1) == {"a": 0.5, "b": 0.5}
    assert alpha_weights({"c": 0.5, "d": 0.2}, 0.1) == {"c": 0.5, "d": 0.5}
    pb = SimpleNamespace(opt=DiagnoseOptions(alpha=0.003), weights=w)
    level = lambda n, play: _Problem.level(pb, n, play)  # noqa: E731
    assert np.isclose(sum(level(n, list(w)) for n in w), 0.003)
    assert np.isclose(level("c", list(w)), 0.00135) and np.isclose(level("a", list(w)), 0.00015)
    assert np.isclose(sum(level(n, ["a", "b", "d"]) for n in ("a", "b", "d")), 0.003)   # c named


def test_diagnosis_plan_covers_the_rim_outside_the_strained_wedge():
    """`pmcal twin plan --for-diagnosis` poses: within the tilt limit, at least half on the rim band
    (68..80 deg; the spiral adds its own rim poses), spread in azimuth there (every 30 deg sector outside
    the wedge holds some), none where both passive limbs are near their stretched-link singularity
    (|K / rho| > 0.88, from the limb IK), and in an order that moves every motor both ways."""
    from pmcal.apps.ocpm.diagnosis_plan import diagnosis_campaign
    from pmcal.mechanism.ocpm.kinematics import limb_ik, nominal_pose

    c = diagnosis_campaign(128, 80.0, 5)
    phi, theta = c["phi_deg"], c["theta_deg"]
    assert len(phi) == 128 and theta.max() <= 80.0 and theta.min() >= 0.0
    rim = theta >= 68.0
    assert rim.mean() >= 0.5
    sectors = np.bincount((phi[rim] // 30).astype(int), minlength=12)
    assert (np.delete(sectors, 1) >= 3).all()                  # sector 1 (30..60 deg) holds the wedge
    r, R = nominal_pose(np.deg2rad(phi), np.deg2rad(theta), G)
    assert np.abs(limb_ik(r, R, None, G, (3, 4)).reach).min(axis=1).max() <= 0.88
    moves = np.sign(np.diff(np.c_[c["m1_cmd_deg"], c["m2_cmd_deg"]], axis=0))
    assert all((moves[:, j] > 0).sum() > 40 and (moves[:, j] < 0).sum() > 40 for j in (0, 1))


def test_effect_model_reproduces_the_twin_and_its_derivatives():
    """EffectChainModel with the true parameters predicts the effect twin's targets; its effect columns
    are the derivatives of that prediction (central differences)."""
    rng = np.random.default_rng(5)
    params = random_errors(rng, 0.5, 0.1, limbs=(1, 2))
    eff = Effects(joint_compliance=(5e4, 3e4), backlash=(0.01, 0.02), encoder_eccentricity=(0.01, 0.02),
                  encoder_phase_deg=(30.0, 100.0), thermal_expansion=23e-6, zero_offset_drift=(0.02, -0.01),
                  frame_drift=(0.2, -0.1, 0.05, 0.002, -0.001, 0.003))
    plan = plan_effect_campaign(10, 60, 3, payloads=(0.0, 10.0), temp_c=(15.0, 30.0))
    meas, _ = with_context(EffectTwin(params, eff).measure(plan, LaserTracker(0.0)))
    a, ph = np.deg2rad([0.01, 0.02]), np.deg2rad([30.0, 100.0])
    x = {**{k: np.deg2rad(v) if is_angular(k) else v for k, v in params.items()},
         "joint_compliance.c1": 1 / 5e4, "joint_compliance.c2": 1 / 3e4,
         "backlash.b1": np.deg2rad(0.01), "backlash.b2": np.deg2rad(0.02),
         "encoder_eccentricity.s1": a[0] * np.cos(ph[0]), "encoder_eccentricity.c1": a[0] * np.sin(ph[0]),
         "encoder_eccentricity.s2": a[1] * np.cos(ph[1]), "encoder_eccentricity.c2": a[1] * np.sin(ph[1]),
         "thermal_expansion.alpha": 23e-6, "zero_offset_drift.r1": np.deg2rad(0.02),
         "zero_offset_drift.r2": np.deg2rad(-0.01), "frame_drift.vx": 0.2, "frame_drift.vy": -0.1,
         "frame_drift.vz": 0.05, "frame_drift.wx": np.deg2rad(0.002), "frame_drift.wy": np.deg2rad(-0.001),
         "frame_drift.wz": np.deg2rad(0.003)}
    keys = list(x)
    x0 = np.array([x[k] for k in keys])
    model = EffectChainModel()
    model.set_vector(keys, x0, G.stiffness_ratio)
    T, dT = model.predict_meas(meas, keys)
    # thermal by exact scaling vs per-pose scaled models under gravity: ~1e-4 mm
    assert np.abs(T - meas.targets).max() < 2e-4
    for key in ("backlash.b2", "encoder_eccentricity.c1", "zero_offset_drift.r1", "thermal_expansion.alpha",
                "joint_compliance.c2", "L1.dbx", "frame_drift.vy", "frame_drift.wz"):
        c = keys.index(key)
        h = 1e-3 * abs(x[key])
        xp, xm = x0.copy(), x0.copy()
        xp[c] += h
        xm[c] -= h
        model.set_vector(keys, xp, G.stiffness_ratio)
        tp, _ = model.predict_meas(meas, keys)
        model.set_vector(keys, xm, G.stiffness_ratio)
        tm, _ = model.predict_meas(meas, keys)
        fd = (tp - tm) / (2 * h)
        # compliance: a forward difference of its own; geometry under springs: Gauss-Newton sensitivities
        tol = 0.2 if key == "L1.dbx" else 0.02
        assert np.abs(fd - dT[..., c]).max() <= tol * np.abs(fd).max(), key


# ---------------------------------------------------------------------------------------- hidden effects
HIDDEN = [["joint_compliance"], ["backlash"], ["encoder_eccentricity"], ["thermal_expansion"],
          ["zero_offset_drift"], ["overconstraint"], ["backlash", "thermal_expansion"]]


def truth(twin, name, hours):
    """The hidden value in the diagnosis' convention: per-motor effects the mean over the motors (backlash:
    the full dead band, twice the twin's half-width b)."""
    v = getattr(twin.effects, name)
    v = float(np.mean(v)) if isinstance(v, tuple) else float(v)
    return 2.0 * v if name == "backlash" else v


@pytest.mark.parametrize("names", HIDDEN, ids=["+".join(h) for h in HIDDEN])
def test_hidden_effect_is_named_and_closes_the_gap(names):
    """One seed per case at the realistic sizes (rates over seeds: benchmark). Eccentricity (0.01 deg) on the
    benchmark's 128 poses: 96 poses up to 80 deg name it in ~70 % of the seeds (docs/diagnose.md).
    Eccentricity runs seed 1: on the diagnosis plan logged in move order, seed 0 names it with 0.022 deg,
    95 % interval 0.016-0.028 against the true 0.01 (99.6 % of its signature absorbed by the geometry,
    one phase direction barely determined): the one miss in twenty a 95 % interval allows; the coverage
    over 20 seeds is the benchmark's (diagnose_bench: 20 of 20)."""
    ecc = names == ["encoder_eccentricity"]
    d, twin, meas = run(names, seed=1 if ecc else 0, n=128 if ecc else 96)
    assert set(d.effects) == set(names) and d.verdict == "named"
    assert d.gap_after <= 1.2 * SIGMA and d.gap_after < d.gap_before
    hours = (meas.time_s[-1] - meas.time_s[0]) / 3600.0
    for v in d.named:
        if v.name == "overconstraint":
            # the passive-limb keys hold their true values within the fit's covariance (Mahalanobis)
            idx = [d.final.names.index(k) for k in PASSIVE_KEYS]
            cov = d.final.covariance[np.ix_(idx, idx)] * max(d.final.info["chi2_per_dof"], 1.0)
            true = np.array([np.deg2rad(twin.passive_errors[k]) if is_angular(k) else twin.passive_errors[k]
                             for k in PASSIVE_KEYS])
            diff = d.final.x[idx] - true
            assert diff @ np.linalg.solve(cov, diff) < chi2.ppf(0.999, len(idx))
        else:
            t = truth(twin, v.name, hours)
            lo, hi = v.interval
            assert (lo is None or lo <= t) and (hi is None or t <= hi), (v.name, t, v.interval)
    doc = json.loads(json.dumps(d.to_json()))
    assert doc["effect"] in names and doc["unit"] == "mm" and doc["gap_after"] == d.gap_after
    # written into the twin: the diagnosed machine reproduces the measurements to the noise
    twin_d = EffectTwin(d.params(), Effects.from_named(doc["named"]), stiffness_ratio=doc["model"]["stiffness_ratio"])
    m = d.meas                      # logged without approach columns: the rows with the inferred approach
    st = twin_d.reach(m.m_cmd_deg, m.approach, m.time_s, m.temp_c, m.payload_kg)
    assert np.sqrt(np.mean((st.targets - m.targets) ** 2)) < 1.1 * SIGMA


def test_an_effect_outside_the_vocabulary_is_flagged_not_named():
    """Stick-slip scatter of the joints (0.004 deg per pose): structure, but no candidate explains it."""
    d, _, _ = run([], seed=1, n=64, joint_jitter_deg=0.004)
    assert d.effect is None and d.unexplained and d.verdict == "unexplained"
    assert d.gap_before > 1.5 * SIGMA


def test_a_campaign_that_cannot_see_an_effect_says_what_would():
    """One approach direction: backlash is a zero offset; no temperature column: thermal cannot be
    tested. Neither is named, and the scoreboard says which measurement would fix it."""
    plan = plan_effect_campaign(48, 70, 2, randomize_approach=False)
    meas, twin = hidden_effect_campaign(["backlash"], 2, plan=plan)
    d = diagnose(meas, EffectChainModel(), DiagnoseOptions(sigma_mm=SIGMA))
    assert d.effect is None and not d.unexplained
    bl, th = d.candidates["backlash"], d.candidates["thermal_expansion"]
    assert bl.verdict == "not identifiable with this campaign" and "approach" in bl.fix
    assert th.verdict == "not identifiable with this campaign" and not th.available and "temp_c" in th.reason
    assert bl.survival < 1e-6


@pytest.mark.slow        # a false-name-rate study (the acceptance rates: benchmarks/diagnose_bench.py)
def test_no_effect_data_gives_at_most_one_false_name_in_50_seeds():
    named = [diagnose(hidden_effect_campaign([], s, 32, SIGMA)[0], EffectChainModel(), DiagnoseOptions(sigma_mm=SIGMA)).effects
             for s in range(50)]
    assert sum(bool(n) for n in named) <= 1, named


@pytest.mark.slow        # a false-name-rate study (the acceptance rates: benchmarks/diagnose_bench.py)
def test_no_effect_heavy_tailed_noise_gives_at_most_one_false_name_in_30_seeds():
    """Student-t (3 dof) tracker noise, sigma estimated from the data."""
    named = [diagnose(hidden_effect_campaign([], s, 32, SIGMA, heavy_tails=True)[0], EffectChainModel(), DiagnoseOptions()).effects
             for s in range(100, 130)]
    assert sum(bool(n) for n in named) <= 1, named


def test_linearised_cross_validation_agrees_with_a_nonlinear_refit():
    """Held-out predictions come from fold refits linearised at the full-data fit; a nonlinear refit of
    one fold predicts the same to well below the noise. (On the stratified cap of
    :func:`plan_effect_campaign`: on the diagnosis plan's uniform random cap, seed 4, one pose at 78.6 deg
    near the stretched-link edge differs by 0.5 sigma, the other 44 coordinates of that fold by < 0.005 sigma.)"""
    plan = plan_effect_campaign(48, 80.0, 4, payloads=(0.0, 10.0), temp_c=(18.0, 28.0))
    meas, _ = hidden_effect_campaign([], 4, 48, SIGMA, plan=plan)
    pb = _Problem(meas, DiagnoseOptions(sigma_mm=SIGMA), EffectChainModel(G))
    base = pb.identify([], None)
    lin = pb.linearize(base, [])
    cols = lin.cols(list(base.names))
    test = lin.rows(np.flatnonzero(pb.folds == 0))
    lin_pred = predict(lin, fit(lin, cols, ~test), test) * SIGMA
    train = pb.meas.subset(np.flatnonzero(pb.folds != 0))
    x0 = dict(zip(base.names, base.x))
    res = identify_full(train, pb.model, FullChainOptions(keys=pb.base_keys, fit_stiffness_ratio=True, sigma_mm=SIGMA,
                                                           x0=x0))
    pb.model.set_vector(list(res.names), res.x, res.info["stiffness_ratio"])
    held = pb.meas.subset(np.flatnonzero(pb.folds == 0))
    T, _ = pb.model.predict_meas(held, [])
    assert np.abs((held.targets - T).ravel() - lin_pred).max() < 0.1 * SIGMA


def test_folds_span_the_tilt_range_and_hold_no_neighbours_out_together(tmp_path):
    """Each fold takes one pose of every block of 10 poses ranked by tilt, and no two poses of a fold lie
    close together (on a cross-sim campaign the closest same-fold pair is >= 3x the median nearest-
    neighbour angle, ~5.5 deg; ranked by tilt alone 3-13 % of the poses shared a fold with their nearest
    neighbour, the closest same-fold pairs 3-7 deg apart)."""
    from pmcal.calib.ocpm.diagnose import stratified_folds
    from pmcal.ocpm.io import read_measurements
    from tests.crosssim.campaign import hidden_campaign, write_csv

    for seed in (1001, 1013):
        write_csv(tmp_path / "x.csv", hidden_campaign([], seed, 128)[0])
        meas = read_measurements(tmp_path / "x.csv")
        folds = stratified_folds(meas, 10, G)
        _, R, _ = meas.poses(G)
        n = R[:, :, 2]
        by_tilt = np.argsort(-n[:, 2], kind="stable")
        for start in range(0, 120, 10):
            assert sorted(folds[by_tilt[start:start + 10]]) == list(range(10))
        ang = np.degrees(np.arccos(np.clip(n @ n.T, -1.0, 1.0)))
        np.fill_diagonal(ang, np.inf)
        same = folds[:, None] == folds[None, :]
        assert ang[same].min() > 3.0 * np.median(ang.min(axis=1))


def test_a_baseline_stalled_by_a_few_poses_is_refitted():
    """Twin clean seed 1072 (128 poses): the baseline fit from the prior mean stalled at chi2/dof ~1000
    with three poses 2-8 mm off (the true geometry fits every pose to the noise), and compliance or
    over-constraint was named. Refitted without those poses, then with all, it fits to the noise."""
    d, _, _ = run([], 1072, 128)
    assert d.baseline.info["chi2_per_dof"] < 1.0 + 3.0 * np.sqrt(2.0 / d.baseline.info["dof"])
    assert d.effects == []


# ---------------------------------------------------------------------------------------- CLI
@pytest.fixture(scope="module")
def backlash_csv(tmp_path_factory):
    # with its approach columns (the plan's, from the move order), which the bad-input cases edit
    meas, _ = hidden_effect_campaign(["backlash"], 6, 48, SIGMA, plan=diagnosis_plan(48, 6))
    assert meas.approach is not None
    path = tmp_path_factory.mktemp("diag") / "meas.csv"
    write_measurements(path, meas)
    return path


def test_plan_measured_on_the_twin_keeps_its_order_and_context(tmp_path, capsys):
    """`twin plan --for-diagnosis` then `twin measure --targets plan.csv`: the twin drives the plan's rows
    in its order with its payload, temperature, times and approach signs (compared with the plan's
    columns as written, 6 significant digits), and the diagnosis of the result names the hidden effect;
    an option that contradicts the plan is refused with one line and exit 2, nothing written."""
    from pmcal.csvio import read_csv
    from pmcal.ocpm.io import read_measurements

    plan, m = tmp_path / "plan.csv", tmp_path / "m.csv"
    assert main(["--quiet", "twin", "plan", "--for-diagnosis", "--poses", "64", "-o", str(plan)]) == 0
    assert main(["--quiet", "twin", "measure", "--targets", str(plan), "--preset", "paper-table2",
                 "--effect", "thermal_expansion=23e-6", "-o", str(m)]) == 0
    p, meas = read_csv(plan), read_measurements(m)
    assert len(meas) == 64
    for column, got in (("m1_cmd_deg", meas.m_cmd_deg[:, 0]), ("temp_c_planned", meas.temp_c),
                        ("payload_kg", meas.payload_kg), ("time_s", meas.time_s),
                        ("m2_approach", meas.approach[:, 1])):
        want = p.numbers(column)
        assert np.allclose(got, want, rtol=1e-5, atol=1e-3), column
    d = diagnose(meas, EffectChainModel(), DiagnoseOptions(sigma_mm=SIGMA))
    assert d.effects == ["thermal_expansion"]
    capsys.readouterr()
    for extra in (["--temperature", "18,28"], ["--payload", "0,5"], ["--shuffle"]):
        assert main(["twin", "measure", "--targets", str(plan), "-o", str(tmp_path / "x.csv")] + extra) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and extra[0] in err[0] and not (tmp_path / "x.csv").exists()


def test_cli_diagnose_writes_json_report_and_model(tmp_path, capsys, backlash_csv):
    out, rep = tmp_path / "out.json", tmp_path / "report"
    rc = main(["diagnose", str(backlash_csv), "--json", str(out), "--report", str(rep)])
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    doc = json.loads(out.read_text())
    assert doc["effect"] == "backlash" and doc["effects"] == ["backlash"] and doc["unit"] == "mm"
    assert doc["gap_after"] < doc["gap_before"] and doc["noise"]["source"] == "estimated"
    assert {c["name"] for c in doc["candidates"]} == set(EFFECT_NAMES)
    html = (rep / "index.html").read_text()
    assert html.count("data:image/png;base64,") >= 5 and "Scoreboard" in html and "Added-variable" in html
    # the calibrated held-out test (issue 31): the named effect's bands in the JSON, the card and the table
    test = next(c for c in doc["candidates"] if c["name"] == "backlash")["held_out_test"]
    assert test["consistent"] and test["beyond_alternative"] and test["draws"] == 400
    floors = [test["candidate_true"][0]] + [v for v in (test["alone_5"], test["typical_5"]) if v is not None]
    assert test["need"] == min(max(floors), 0.75) <= test["observed"]
    assert test["alternative"][2] < test["observed"] and "per_motor" in str(doc) and doc["named"][0]["motors"]
    assert "held-out test: removes" in html and "[alternative 5–95 %]" in html
    params = json.loads((rep / "params.json").read_text())
    assert "backlash" in params["effects"] and params["params"]["L1.dtheta"] != 0.0
    assert json.loads((rep / "diagnosis.json").read_text()) == doc
    # stdout: the result line, then one line per output (docs/formats.md, "What the commands print")
    lines = cap.out.splitlines()
    assert len(lines) == 3 and lines[0].startswith("missing effect: backlash (both motors) = ") \
        and "held-out gap" in lines[0], lines
    assert lines[1:] == [f"pmcal: wrote {out}", f"pmcal: wrote {rep}/"]
    # --quiet: nothing but errors, the same files
    out2, rep2 = tmp_path / "quiet.json", tmp_path / "quiet"
    assert main(["diagnose", str(backlash_csv), "--json", str(out2), "--report", str(rep2), "--quiet"]) == 0
    cap = capsys.readouterr()
    assert cap.out == "" and cap.err == ""
    assert json.loads(out2.read_text())["effects"] == ["backlash"] and (rep2 / "index.html").exists()


def _bad_files(tmp, src):
    lines = src.read_text().splitlines()
    head = [i for i, l in enumerate(lines) if not l.startswith("#")][0]
    hdr = lines[head].split(",")
    files = {}
    files["few"] = tmp / "few.csv"
    files["few"].write_text("\n".join(lines[: head + 11]) + "\n")
    rows = [l.split(",") for l in lines[head + 1:]]
    a = hdr.index("m2_approach")
    rows[4][a] = "2"
    files["approach"] = tmp / "approach.csv"
    files["approach"].write_text("\n".join([lines[head]] + [",".join(r) for r in rows]) + "\n")
    rows = [l.split(",") for l in lines[head + 1:]]
    t = hdr.index("temp_c")
    rows[2][t] = ""
    files["temp"] = tmp / "temp.csv"
    files["temp"].write_text("\n".join([lines[head]] + [",".join(r) for r in rows]) + "\n")
    files["params"] = tmp / "p.json"
    files["params"].write_text(json.dumps({"params": {"L9.dbx": 1.0}}))
    return files


@pytest.mark.parametrize("case, extra, message", [
    ("missing", [], "file not found"),
    ("sigma", ["--sigma", "-1"], "tracker noise must be a positive"),
    ("few", [], "too few"),
    ("approach", [], "row 5, field 'm2_approach'"),
    ("temp", [], "row 3, field 'temp_c'"),
    ("params", ["--params", "{params}"], "unknown limb"),
])
def test_cli_diagnose_bad_input_exits_2_and_writes_nothing(tmp_path, capsys, backlash_csv, case, extra, message):
    files = _bad_files(tmp_path, backlash_csv)
    src = {"missing": tmp_path / "nope.csv", "sigma": backlash_csv, "params": backlash_csv}.get(case) or files[case]
    extra = [e.format(params=files["params"]) for e in extra]
    out, rep = tmp_path / "out.json", tmp_path / "rep"
    rc = main(["--quiet", "diagnose", str(src), "--json", str(out), "--report", str(rep), *extra])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and message in err[0], err
    assert not out.exists() and not rep.exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_hidden_effect_demo_diagnoses_blind(tmp_path, capsys, monkeypatch):
    out = tmp_path / "demo"
    assert hidden_effect_demo(SimpleNamespace(hidden_effect="thermal_expansion", seed=3, out=str(out), poses=64)) == 0
    cap = capsys.readouterr()           # the result line on stdout, also when piped
    assert cap.out.startswith("hidden: thermal_expansion; diagnosed: thermal_expansion (missing effect: ")
    answer = json.loads((out / "answer.json").read_text())
    doc = json.loads((out / "diagnosis.json").read_text())
    assert answer["hidden_effect"] == "thermal_expansion" and doc["effect"] == "thermal_expansion"
    assert "thermal" not in (out / "measurements.csv").read_text()          # nothing gives it away
    assert (out / "report" / "index.html").exists()
    with pytest.raises(Exception, match="unknown effect"):
        hidden_effect_demo(SimpleNamespace(hidden_effect="gremlins", seed=1, out=str(tmp_path / "x")))
    assert not (tmp_path / "x").exists()


# ---------------------------------------------------------------------------------------- slow study
@pytest.mark.slow
@pytest.mark.parametrize("name", EFFECT_NAMES)
def test_naming_rate_over_seeds(name):
    """>= 90 % right, no other name in >= 95 % (10 seeds, 128 poses; more in the benchmark)."""
    runs = [run([name], seed=s, n=128)[0] for s in range(10)]
    assert np.mean([r.effects == [name] for r in runs]) >= 0.9
    assert np.mean([set(r.effects) <= {name} for r in runs]) >= 0.95


def _sections(html: str) -> dict[str, str]:
    """The report's sections by heading."""
    parts = html.split("<h2>")[1:]
    return {p.split("</h2>")[0]: p.split("</h2>", 1)[1] for p in parts}


def test_report_one_figure_when_nothing_is_named_and_no_empty_panels(tmp_path, capsys):
    """docs/reports.md: baseline = result drawn once; contexts the campaign does not vary get a note, not
    an empty panel; the headline box names the method; axes in mm and deg."""
    m = tmp_path / "m.csv"
    assert main(["--quiet", "twin", "measure", "--preset", "paper-table2", "--poses", "24", "--seed", "1",
                 "-o", str(m)]) == 0
    assert main(["--quiet", "diagnose", str(m), "--json", str(tmp_path / "d.json"), "--report",
                 str(tmp_path / "rep")]) == 0
    assert json.loads((tmp_path / "d.json").read_text())["effects"] == []
    html = (tmp_path / "rep" / "index.html").read_text()
    sec = _sections(html)
    assert "Held-out disagreement" in sec and "Held-out disagreement, before and after" not in sec
    for name in ("Held-out disagreement", "Residual against context", "Per-pose residuals"):
        assert sec[name].count("<img") == 1, name
    assert "baseline = result (nothing named)" in html
    assert "No data: this campaign does not vary temperature or payload" in sec["Residual against context"]
    assert "method: discrepancy diagnosis against the baseline, whole closed chain" in sec["Verdict"]
    assert "mm or rad" not in html and " um" not in html and "µm" not in html


def test_report_named_effect_before_and_after(tmp_path, backlash_csv):
    main(["--quiet", "diagnose", str(backlash_csv), "--json", str(tmp_path / "d.json"), "--report",
          str(tmp_path / "rep")])
    sec = _sections((tmp_path / "rep" / "index.html").read_text())
    assert "Held-out disagreement, before and after" in sec
    assert sec["Residual against context"].count("<img") == 2 and sec["Per-pose residuals"].count("<img") == 1
    assert "with backlash" in sec["Per-pose residuals"] or "with backlash" in sec["Residual against context"]
    assert "Named: backlash" in sec["Verdict"] and "method: discrepancy diagnosis" in sec["Verdict"]
