"""Tracker-frame campaigns and the tracker frame in the diagnosis (docs/tracker_frame.md).

References: the motor axes' frame from the limb-frame convention of MECHANISM written out by hand; the
Cramér-Rao bound of the frame rotation of an evenly spread campaign; a base-frame campaign carried into
a tracker frame by a known rigid transform (closed form), which the diagnosis must undo.
"""

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pmcal.apps.ocpm.effect_scenarios import hidden_effect_campaign
from pmcal.calib.ocpm.registration import motor_axes_frame
from pmcal.calib.ocpm.tracker_design import (candidate_orientations, design_blocks,
                                             frame_std_deg, tracker_campaign)
from pmcal.cli import main
from pmcal.ocpm.io import write_measurements
from pmcal.mechanism.ocpm.config import default_geometry
from pmcal.mechanism.ocpm.kinematics import PASSIVE_REACH, limb_ik, nominal_pose
from pmcal.mechanism.ocpm.params import ErrorSet, random_errors
from pmcal.twin.ocpm.campaign import nominal_commands, plan_orientations
from pmcal.twin.ocpm.forward import FullChainModel
from pmcal.twin.ocpm.machine import Twin

G = default_geometry()
SIGMA = 0.01


def test_motor_axes_frame_by_hand():
    """y along motor 1's axis Rz(g1) Rx(a1) e_y, z normal to both axes (MECHANISM's limb frames)."""
    a1, g1, a2, g2 = np.deg2rad([0.05, -0.1, 0.2, 0.17])
    e = ErrorSet.from_dict({"L1.dalpha": 0.05, "L1.dgamma": -0.1, "L2.dalpha": 0.2, "L2.dgamma": 0.17})
    Q = motor_axes_frame(e, G)
    ax1 = np.array([-np.sin(g1) * np.cos(a1), np.cos(g1) * np.cos(a1), np.sin(a1)])
    # limb 2 sits at psi = 90 deg: Rz(90) maps (x, y, z) to (-y, x, z)
    ax2 = np.array([-np.cos(g2) * np.cos(a2), -np.sin(g2) * np.cos(a2), np.sin(a2)])
    assert np.allclose(Q.T @ Q, np.eye(3), atol=1e-12) and np.linalg.det(Q) == pytest.approx(1.0)
    assert np.allclose(Q[:, 1], ax1, atol=1e-12)
    assert abs(Q[:, 2] @ ax2) < 1e-12 and Q[2, 2] > 0
    assert np.allclose(motor_axes_frame(ErrorSet(), G), np.eye(3), atol=1e-15)


@pytest.fixture(scope="module")
def model():
    return FullChainModel()


def test_designed_campaign_fixes_the_frame_and_stays_assemblable(model):
    """48 designed poses to 80 deg fix the motor axes' frame at least 2.5 times better (Cramér-Rao) than
    48 spread evenly to 60 deg, the campaign of the issue; the designed poses avoid the wedge where both
    passive limbs are near stretched, and a machine with 0.5 mm / 0.1 deg errors reaches every one."""
    phi, theta = tracker_campaign(model, 48, 80.0, seed=3, sigma_mm=SIGMA)
    assert len(phi) == 48 and theta.max() <= 80.0 and np.all(np.diff(phi) >= 0)
    B, P, reg = design_blocks(model, phi, theta, SIGMA)
    designed = np.linalg.norm(frame_std_deg(B, P, reg))
    pu, tu = plan_orientations(48, 60.0, np.random.default_rng(3))
    Bu, Pu, _ = design_blocks(model, pu, tu, SIGMA)
    uniform = np.linalg.norm(frame_std_deg(Bu, Pu, reg))
    assert designed < uniform / 2.5, (designed, uniform)
    r, R = nominal_pose(np.deg2rad(phi), np.deg2rad(theta))
    assert np.all(np.abs(limb_ik(r, R, limbs=(3, 4)).reach).min(axis=1) <= PASSIVE_REACH)
    cmd = nominal_commands(phi, theta)
    for d in range(3):
        twin = Twin(random_errors(np.random.default_rng(40 + d), 0.5, 0.1))
        assert twin.reach(cmd).converged.all()


def test_candidates_cover_the_cap_outside_the_wedge():
    phi, theta = candidate_orientations(400, 80.0, np.random.default_rng(0))
    assert len(phi) == 400 and theta.max() <= 80.0 and theta.max() > 78.0
    wedge = (phi > 30) & (phi < 55) & (theta > 75)
    assert not wedge.any()


def test_twin_plan_frame_tracker_cli(tmp_path, capsys):
    out = tmp_path / "plan.csv"
    assert main(["--quiet", "twin", "plan", "--frame", "tracker", "--poses", "24", "--seed", "2", "-o", str(out)]) == 0
    lines = [ln for ln in out.read_text().splitlines() if not ln.startswith("#")]
    assert lines[0] == "step,phi_deg,theta_deg,m1_cmd_deg,m2_cmd_deg" and len(lines) == 25
    rows = np.array([[float(v) for v in ln.split(",")] for ln in lines[1:]])
    assert np.allclose(rows[:, 3:], nominal_commands(rows[:, 1], rows[:, 2]), atol=1e-5)
    meas = tmp_path / "m.csv"       # the plan is a targets file for the twin
    assert main(["--quiet", "twin", "measure", "--targets", str(out), "--tracker-pose", "random", "-o", str(meas)]) == 0
    rc = main(["--quiet", "twin", "plan", "--frame", "tracker", "--for-diagnosis", "-o", str(tmp_path / "x.csv")])
    assert rc == 2 and not (tmp_path / "x.csv").exists()
    assert "not both" in capsys.readouterr().err


# ----------------------------------------------------------------------------- diagnosis
def _blocked_row(cmd: np.ndarray) -> int:
    """A row in the middle whose leaving-out would change the next row's approach if the approach were
    inferred after leaving it out (the sign of a motor's last move differs with and without it)."""
    for i in range(len(cmd) // 3, len(cmd) - 1):
        if np.any(np.sign(cmd[i + 1] - cmd[i - 1]) != np.sign(cmd[i + 1] - cmd[i])):
            return i
    raise AssertionError("no such row")


@pytest.fixture(scope="module")
def backlash(tmp_path_factory):
    """The diagnosis campaign as `pmcal twin plan --for-diagnosis` then `pmcal twin measure` log it (128
    poses to 80 deg, random time order, no approach columns) on a machine with backlash, in the
    base frame; the same file with one target blocked in the middle; and the campaign seen by a tracker at
    a known pose with that target blocked and a 2 mm outlier in row 20."""
    meas, _ = hidden_effect_campaign(["backlash"], 6, 128, SIGMA)
    assert meas.approach is None and len(meas) > 120
    blocked = _blocked_row(meas.m_cmd_deg)
    tmp = tmp_path_factory.mktemp("trdiag")
    base, base_blocked, tracker = tmp / "base.csv", tmp / "base_blocked.csv", tmp / "tracker.csv"
    write_measurements(base, meas)
    bb = meas.subset(np.arange(len(meas)))
    bb.targets = meas.targets.copy()
    bb.targets[blocked, 1] = np.nan
    write_measurements(base_blocked, bb)
    R = Rotation.from_rotvec([0.3, -0.2, 2.1]).as_matrix()
    t = np.array([1800.0, -650.0, 120.0])
    tr = meas.subset(np.arange(len(meas)))
    tr.targets = meas.targets @ R.T + t
    tr.targets[blocked, 1] = np.nan
    tr.targets[19, 2, 0] += 2.0
    write_measurements(tracker, tr)
    return base, tracker, (R, t), blocked, base_blocked, meas.m_cmd_deg


def test_approach_inferred_from_the_whole_campaign_before_rows_are_left_out(backlash):
    """Each motor's approach is the sign of its last move in the whole campaign (the machine starts at
    home), also for the row after a row that is left out (blocked target; in the tracker frame also the
    rejected outlier), in either frame."""
    from argparse import Namespace

    from pmcal.apps.ocpm.diagnose_frame import frame_input
    from pmcal.mechanism.ocpm.kinematics import HOME_BETA

    _, tracker, _, blocked, base_blocked, cmd = backlash
    last_move = np.sign(np.diff(np.vstack([[HOME_BETA, HOME_BETA], cmd]), axis=0))    # by hand, from home
    for path, frame in ((base_blocked, "base"), (tracker, "tracker")):
        args = Namespace(measurements=str(path), frame=frame, nest_tolerance=None, model=None)
        meas, doc, _ = frame_input(args, G, SIGMA, 24)
        ids = [ln.split(",")[0] for ln in path.read_text().splitlines() if ln[:1] == "P"]
        rows = np.array([ids.index(p) for p in meas.pose_id])
        assert blocked not in rows and blocked + 1 in rows and 0 not in rows, frame
        assert np.array_equal(meas.approach, last_move[rows]), frame
        assert {r["row"] for r in doc["rows_left_out"]} >= {blocked + 1}


def test_diagnose_tracker_frame_gives_the_base_frame_answer(tmp_path, backlash):
    base, tracker, (R, t), blocked, _, _ = backlash
    docs = {}
    for name, src, extra in (("base", base, []), ("tracker", tracker, ["--frame", "tracker"])):
        out = tmp_path / f"{name}.json"
        assert main(["--quiet", "diagnose", str(src), "--json", str(out), *extra]) == 0
        docs[name] = json.loads(out.read_text())
    b, tr = docs["base"], docs["tracker"]
    assert b["effect"] == tr["effect"] == "backlash"
    vb, vt = b["named"][0], tr["named"][0]
    width = vb["interval"][1] - vb["interval"][0]
    assert abs(vt["value"] - vb["value"]) < width, (vb, vt)      # two rows fewer: same within the interval
    frame = tr["measurement_frame"]
    left = {r["row"]: r["why"] for r in frame["rows_left_out"]}
    assert left == {blocked + 1: "blocked target", 20: "rejected outlier"}
    assert [(r["row"], r["target"]) for r in frame["rejected"]] == [(20, 3)]
    # a pose at the workspace's edge the registration's model could not assemble is named, not fatal
    for r in frame.get("registration_left_out", []):
        assert "cannot assemble" in r["why"] and any(f"rows {r['row']}" in n or f", {r['row']}" in n
                                                    for n in tr["notes"])
    reg = frame["registration"]
    rot = Rotation.from_matrix(np.asarray(reg["R"]) @ R.T).as_rotvec(degrees=True)
    assert np.all(np.abs(rot) < 5 * np.asarray(reg["std_rot_deg"]) + 1e-4), (rot, reg["std_rot_deg"])
    assert np.all(np.abs(np.asarray(reg["t_mm"]) - t) < 5 * np.asarray(reg["std_t_mm"]))


def test_diagnosis_registration_leaves_out_a_pose_outside_the_workspace(backlash, tmp_path, capsys):
    """A pose no machine reaches is left out of the registration and the diagnosis, named in the JSON's
    frame part and in a warning line (piped too), never a traceback."""
    from argparse import Namespace

    from pmcal.apps.ocpm.diagnose_frame import frame_input

    _, tracker, _, blocked, _, _ = backlash
    lines = tracker.read_text().splitlines()
    i = [k for k, ln in enumerate(lines) if ln[:1] == "P"][29]            # row 30
    f = lines[i].split(",")
    f[1] = f[2] = "60.0"
    lines[i] = ",".join(f)
    bad = tmp_path / "outside.csv"
    bad.write_text("\n".join(lines) + "\n")
    capsys.readouterr()
    meas, doc, _ = frame_input(Namespace(measurements=str(bad), frame="tracker", nest_tolerance=None,
                                         model=None), G, SIGMA, 24)
    left = {r["row"]: r["why"] for r in doc["rows_left_out"]}
    assert "cannot assemble" in left[30] and left[blocked + 1] == "blocked target"
    assert f[0] not in meas.pose_id
    assert f"pmcal: warning: row 30 ({f[0]}) left out" in capsys.readouterr().err


def test_twin_tracker_frame_with_effects_then_diagnose_cli(tmp_path, capsys):
    """End to end from the CLI: the diagnosis plan, measured on a twin with backlash by a tracker at a
    known pose with a blocked target and an outlier (`twin measure --effect ... --tracker-pose ...`), then
    `diagnose --frame tracker`: backlash named at its planted value, the planted outlier the one rejected,
    the tracker pose recovered."""
    plan, m, out = tmp_path / "plan.csv", tmp_path / "m.csv", tmp_path / "d.json"
    assert main(["--quiet", "twin", "plan", "--for-diagnosis", "-o", str(plan)]) == 0
    assert main(["--quiet", "twin", "measure", "--targets", str(plan), "--effect", "backlash=0.0125",
                 "--tracker-pose", "1500,-800,200,1,-1,120", "--blocked", "0.03", "--outliers", "1",
                 "-o", str(m)]) == 0
    text = m.read_text()
    assert "targets in the tracker frame" in text and ",,," in text
    line = next(x for x in text.splitlines() if x.startswith("# truth outlier"))
    row, target = int(line.split("row ")[1].split()[0]), int(line.split("target t")[1].split()[0])
    capsys.readouterr()
    assert main(["diagnose", str(m), "--frame", "tracker", "--json", str(out)]) == 0
    assert f"rejected outlier: row {row} " in capsys.readouterr().err
    doc = json.loads(out.read_text())
    assert doc["effect"] == "backlash"
    lo, hi = doc["named"][0]["interval"]
    band = 2 * 0.0125                                   # the diagnosis reports the full dead band 2b
    assert lo <= band <= hi or abs(doc["named"][0]["value"] - band) < 2 * (hi - lo), doc["named"][0]
    frame = doc["measurement_frame"]
    assert [(r["row"], r["target"]) for r in frame["rejected"]] == [(row, target)]
    reg = frame["registration"]
    assert np.all(np.abs(np.asarray(reg["t_mm"]) - [1500, -800, 200]) < 5 * np.asarray(reg["std_t_mm"]) + 0.05)
    R = Rotation.from_rotvec([1, -1, 120], degrees=True).as_matrix()
    rot = Rotation.from_matrix(np.asarray(reg["R"]) @ R.T).as_rotvec(degrees=True)
    assert np.all(np.abs(rot) < 5 * np.asarray(reg["std_rot_deg"]) + 1e-4), (rot, reg["std_rot_deg"])
