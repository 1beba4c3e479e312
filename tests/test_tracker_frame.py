"""Tracker-frame data (issue 16): registration, nest offsets, blocked targets, outliers, bad input.

References independent of the code under test: the registration's Cramér-Rao bound from a finite-
difference Jacobian of the twin (not the fit's analytic Jacobian), the twin's own truth (tracker pose,
nest offsets, outlier rows), the plain Kabsch fit of :mod:`pmcal.mechanism.rigid`.
"""

import csv
import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pmcal.calib.ocpm.registration import GAUGE_KEYS, rigid_fit
from pmcal.calib.ocpm.tracker_fit import identify_tracker
from pmcal.cli import main
from pmcal.ocpm.io import read_measurements, write_measurements
from pmcal.mechanism.ocpm.config import default_geometry
from pmcal.mechanism.ocpm.params import random_errors
from pmcal.mechanism.rigid import fit_pose
from pmcal.twin.ocpm.campaign import MeasurementFaults, plan_campaign, run_campaign
from pmcal.twin.ocpm.forward import FullChainModel
from pmcal.twin.ocpm.machine import Twin
from pmcal.twin.tracker import LaserTracker, random_tracker_pose

SIGMA = 0.01


def gauge_free_errors(seed):
    """Every-limb errors with the base frame on the motor axes (the gauge keys zero)."""
    p = random_errors(np.random.default_rng(seed), 0.5, 0.1)
    p.update({k: 0.0 for k in GAUGE_KEYS})
    return p


@pytest.fixture(scope="module")
def tracker_case():
    twin = Twin(gauge_free_errors(5))
    pose = random_tracker_pose(np.random.default_rng(6))
    faults = MeasurementFaults(nest_error_mm=0.3, blocked=0.05, outliers=1, seed=7)
    meas = run_campaign(twin, plan_campaign(36, 60, seed=8), LaserTracker(SIGMA, np.random.default_rng(9), pose=pose),
                        faults=faults)
    model = FullChainModel()
    res = identify_tracker(meas, model)
    return twin, pose, meas, res, model


def test_twin_faults_match_their_definition(tracker_case):
    _, _, meas, _, _ = tracker_case
    X = default_geometry().targets
    dn = meas.extra["nest_offsets"][0]
    r, R, _ = fit_pose((X + dn)[None], X)                  # shape part only: the frame does not move
    assert np.allclose(r, 0, atol=1e-12) and np.allclose(R, np.eye(3), atol=1e-12)
    assert np.abs(dn).max() > 0.05
    assert (~meas.visible).sum(axis=1).max() == 1          # at most one blocked target a row
    assert (meas.extra["outlier"] != 0).sum() == 1


def test_outlier_named_and_only_it(tracker_case):
    _, _, meas, res, _ = tracker_case
    (i, k, _), = np.argwhere(meas.extra["outlier"] != 0)
    assert [(r["row"], r["target"]) for r in res.info["rejected"]] == [(i + 1, k + 1)]
    assert 0.8 < res.info["chi2_per_dof"] < 1.2


def test_registration_to_the_cramer_rao_bound(tracker_case):
    """Reported registration std equals the bound from a finite-difference Fisher matrix of the twin
    (within 15 %), and the error against the twin's true tracker pose is within it (chi2, 6 dof)."""
    _, pose, meas, res, model = tracker_case
    reg = res.info["registration"]
    keep = meas.visible.copy()
    for r in res.info["rejected"]:
        keep[r["row"] - 1, r["target"] - 1] = False
    keys, x = res.names, res.x
    Rg, tg = reg["R"], reg["t_mm"]
    X = model.geom.targets
    dn = res.info["nests"]["offsets_mm"]

    def predict(dx, w, dt, dq):
        model.set_vector(keys, x + dx, res.info["stiffness_ratio"])
        T, _ = model.predict(meas.m_cmd_deg)
        _, Rp, _ = fit_pose(T, X)
        P = T + np.einsum("nij,kj->nki", Rp, dn + dq)
        return (P @ (Rotation.from_rotvec(w).as_matrix() @ Rg).T + tg + dt)[keep].reshape(-1)

    base = predict(np.zeros(len(x)), np.zeros(3), np.zeros(3), np.zeros((3, 3)))
    cols, prior = [], []
    for j in range(len(x)):
        h = 1e-5
        dx = np.zeros(len(x))
        dx[j] = h
        cols.append((predict(dx, np.zeros(3), np.zeros(3), np.zeros((3, 3))) - base) / h)
        prior.append(1 / res.info["prior_std"][j] ** 2)
    for a in range(6):
        h = 1e-6 if a < 3 else 1e-3
        v = np.zeros(6)
        v[a] = h
        cols.append((predict(np.zeros(len(x)), v[:3], v[3:], np.zeros((3, 3))) - base) / h)
        prior.append(0.0)
    N = np.linalg.svd(np.array([[*e, *np.cross(r, X[i] - X.mean(0))] for i in range(3)
                                for e, r in zip(np.eye(3), np.eye(3))]).reshape(3, 3, 6).reshape(9, 6))[0][:, 6:]
    for a in range(N.shape[1]):
        h = 1e-4
        cols.append((predict(np.zeros(len(x)), np.zeros(3), np.zeros(3), h * N[:, a].reshape(3, 3)) - base) / h)
        prior.append(1 / 0.5**2)
    J = np.array(cols).T / SIGMA
    cov = np.linalg.inv(J.T @ J + np.diag(prior))
    C = cov[len(x):len(x) + 6, len(x):len(x) + 6]
    std_fd = np.sqrt(np.diag(C))
    std_rep = np.r_[np.deg2rad(reg["std_rot_deg"]), reg["std_t_mm"]]
    assert np.allclose(std_rep, std_fd, rtol=0.15)
    err = np.r_[Rotation.from_matrix(Rg @ pose[0].T).as_rotvec(), tg - pose[1]]
    chi2 = err @ np.linalg.solve(C, err)
    assert chi2 < 22.5                                      # chi2(6) at 0.999


def test_nest_offsets_within_three_sigma(tracker_case):
    _, _, meas, res, _ = tracker_case
    n = res.info["nests"]
    truth = meas.extra["nest_offsets"][0]
    z = np.abs(n["offsets_mm"] - truth)[:, :2] / n["std_mm"][:, :2]    # in-plane: the shape coordinates
    assert z.max() < 3.0
    assert np.abs(n["offsets_mm"] - truth).max() < 0.01             # 0.3 mm offsets found to 10 um


def test_rigid_fit_is_kabsch():
    rng = np.random.default_rng(1)
    P = rng.normal(size=(10, 3))
    R = Rotation.random(random_state=2).as_matrix()
    R2, t2 = rigid_fit(P @ R.T + [1, 2, 3], P)
    assert np.allclose(R2, R) and np.allclose(t2, [1, 2, 3])


# ---------------------------------------------------------------- files and the command line
@pytest.fixture(scope="module")
def base_campaign(tmp_path_factory):
    d = tmp_path_factory.mktemp("frame")
    twin = Twin(gauge_free_errors(11))
    meas = run_campaign(twin, plan_campaign(36, 60, seed=12), LaserTracker(SIGMA, np.random.default_rng(13)))
    write_measurements(d / "meas.csv", meas)
    test = plan_campaign(12, 55.0, seed=14)
    with open(d / "targets.csv", "w", newline="") as fh:
        csv.writer(fh).writerows([["phi_deg", "theta_deg"], *zip(test.phi_deg, test.theta_deg)])
    return d, meas


def commands(d, params):
    out = d / f"sp_{params}.csv"
    assert main(["--quiet", "compensate", str(d / params), "--targets", str(d / "targets.csv"), "-o", str(out)]) == 0
    rows = list(csv.DictReader(line for line in open(out) if not line.startswith("#")))
    return np.array([[float(r["m1_deg"]), float(r["m2_deg"])] for r in rows])


def test_base_campaign_same_compensation_with_either_frame(base_campaign):
    d, _ = base_campaign
    assert main(["--quiet", "identify", str(d / "meas.csv"), "-o", str(d / "base.json")]) == 0
    assert main(["--quiet", "identify", str(d / "meas.csv"), "--frame", "tracker", "-o", str(d / "trk.json")]) == 0
    doc = json.loads((d / "trk.json").read_text())
    reg = doc["registration"]
    rot = np.linalg.norm(Rotation.from_matrix(np.array(reg["R"])).as_rotvec(degrees=True))
    std_rot = np.linalg.norm(reg["std_rot_deg"])
    assert rot < 4 * std_rot                                  # the registration is the identity
    assert np.linalg.norm(reg["t_mm"]) < 4 * np.linalg.norm(reg["std_t_mm"])
    diff = np.abs(commands(d, "base.json") - commands(d, "trk.json"))
    assert diff.max() < 4 * std_rot                           # commands agree to the frame's uncertainty


def test_blocked_targets_round_trip_and_identify(base_campaign, tmp_path):
    d, meas = base_campaign
    m = meas.subset(np.arange(len(meas)))
    m.targets = m.targets.copy()
    m.targets[3, 1] = np.nan
    m.targets[7, 2] = np.nan
    write_measurements(tmp_path / "b.csv", m)
    text = (tmp_path / "b.csv").read_text()
    assert ",,," in text and "nan" not in text
    back = read_measurements(tmp_path / "b.csv")
    assert (~back.visible).sum() == 2 and not back.visible[3, 1]
    assert main(["--quiet", "identify", str(tmp_path / "b.csv"), "-o", str(tmp_path / "p.json")]) == 0
    doc = json.loads((tmp_path / "p.json").read_text())
    assert {(b["row"], b["target"]) for b in doc["blocked_targets"]} == {(4, 2), (8, 3)}
    assert doc["rejected"] == []


def rewrite(src, dst, edit):
    lines = [line for line in open(src) if not line.startswith("#")]
    rows = [line.rstrip("\n").split(",") for line in lines]
    edit(rows)
    dst.write_text("\n".join(",".join(r) for r in rows) + "\n")


@pytest.mark.parametrize("case, expect", [
    ("half", "row 3, field 't2_y'"), ("one", "row 5, field 't1_x'"), ("all", "bad campaign"),
    ("outside", "cannot assemble 1 measured pose(s) at its starting parameters (rows 4)")])
def test_bad_input_exit_2_one_line_nothing_written(base_campaign, tmp_path, capsys, case, expect):
    d, _ = base_campaign
    bad = tmp_path / "bad.csv"

    def edit(rows):
        h = rows[0]
        if case == "half":
            rows[3][h.index("t2_y")] = ""
        elif case == "one":
            for c in ("t1_x", "t1_y", "t1_z", "t2_x", "t2_y", "t2_z"):
                rows[5][h.index(c)] = ""
        elif case == "outside":                           # commands no machine reaches
            rows[4][h.index("m1_cmd_deg")] = rows[4][h.index("m2_cmd_deg")] = "60.0"
        else:                                             # every row has a 1.5 mm outlier
            rng = np.random.default_rng(0)
            for r in rows[1:]:
                c = h.index(f"t{rng.integers(1, 4)}_{'xyz'[rng.integers(0, 3)]}")
                r[c] = f"{float(r[c]) + 1.5 * rng.choice([-1, 1]):.5f}"
    rewrite(d / "meas.csv", bad, edit)
    out = tmp_path / "p.json"
    capsys.readouterr()
    args = ["identify", str(bad), "-o", str(out)] + (["--frame", "tracker"] if case in ("all", "outside") else [])
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and expect in err and "Traceback" not in err
    assert not out.exists()


def test_frame_option_errors(base_campaign, tmp_path, capsys):
    d, _ = base_campaign
    (tmp_path / "T.json").write_text('{"R": [[1, 0, 0], [0, 1, 0]], "t_mm": [0, 0, 0]}')
    for frame, msg in (("sideways", "unknown frame"), (f"tracker:{tmp_path / 'T.json'}", "field 'R'")):
        assert main(["identify", str(d / "meas.csv"), "--frame", frame, "-o", str(tmp_path / "p.json")]) == 2
        assert msg in capsys.readouterr().err
    assert not (tmp_path / "p.json").exists()


def test_twin_measure_tracker_campaign_end_to_end(tmp_path, capsys):
    """`pmcal twin measure` with every tracker option, then `pmcal identify --frame tracker`: the outlier
    the twin wrote into the file's comments is the one rejected, the registration is the twin's."""
    m = tmp_path / "t.csv"
    assert main(["--quiet", "twin", "measure", "--preset", "paper-table2", "--poses", "30", "--seed", "4",
                 "--tracker-pose", "1500,-800,200,1,-1,120", "--nest-error", "0.3", "--blocked", "0.1",
                 "--outliers", "1:3", "-o", str(m)]) == 0
    text = m.read_text()
    assert ",,," in text
    line = next(x for x in text.splitlines() if x.startswith("# truth outlier"))
    row, target = int(line.split("row ")[1].split()[0]), int(line.split("target t")[1].split()[0])
    capsys.readouterr()
    assert main(["identify", str(m), "--frame", "tracker", "-o", str(tmp_path / "p.json")]) == 0
    out, err = capsys.readouterr()            # piped: the rejected target is a warning on stderr
    warned = [x for x in err.splitlines() if x.startswith("pmcal: warning: rejected outlier")]
    assert len(warned) == 1 and f"row {row} " in warned[0] and f"target t{target}," in warned[0], err
    assert "warning" not in out and f"pmcal: wrote {tmp_path / 'p.json'}" in out.splitlines()
    doc = json.loads((tmp_path / "p.json").read_text())
    assert [(r["row"], r["target"]) for r in doc["rejected"]] == [(row, target)]
    assert doc["frame"] == "tracker" and set(doc["gauge"]["held_at_zero"]) == set(GAUGE_KEYS)
    assert not set(GAUGE_KEYS) & set(doc["params"])
    reg = doc["registration"]
    assert np.allclose(reg["t_mm"], [1500, -800, 200], atol=4 * max(reg["std_t_mm"]) + 0.5)
    # paper-table2 tilts motor 1's axis: the registration carries that rotation (tenths of a degree)
    true_rot = Rotation.from_rotvec([1, -1, 120], degrees=True).as_matrix()
    assert np.linalg.norm(Rotation.from_matrix(np.array(reg["R"]) @ true_rot.T).as_rotvec(degrees=True)) < 0.5
    assert main(["twin", "measure", "--poses", "5", "--blocked", "2", "-o", str(tmp_path / "x.csv")]) == 2
    assert "--blocked" in capsys.readouterr().err and not (tmp_path / "x.csv").exists()


def test_warnings_go_to_stderr_unless_quiet(capsys):
    """docs/formats.md: warnings (a rejected target) are shown piped, on stderr; --quiet hides them."""
    from pmcal import progress

    try:
        progress.set_quiet(False)
        progress.warning("rejected outlier: row 3")
        progress.set_quiet(True)
        progress.warning("rejected outlier: row 4")
    finally:
        progress.set_quiet(False)
    out, err = capsys.readouterr()
    assert out == "" and err == "pmcal: warning: rejected outlier: row 3\n"


def test_api_reads_and_identifies_the_tracker_frame(tracker_case, tmp_path):
    import pmcal

    _, _, meas, _, _ = tracker_case
    write_measurements(tmp_path / "t.csv", meas)
    back = pmcal.read_measurements(tmp_path / "t.csv", frame="tracker")
    assert np.array_equal(back.visible, meas.visible)
    cal = pmcal.identify(back, frame="tracker")
    assert cal.document["frame"] == "tracker" and len(cal.document["rejected"]) == 1
    assert cal.setpoints([30.0], [20.0]).shape == (1, 2)
