"""`pmcal identify | compensate | evaluate | demo` for ocpm_2dof: outputs and bad input (exit 2)."""

import csv
import json

import numpy as np
import pytest

from pmcal.bridge.comptable import CompTable
from pmcal.mechanism.ocpm.kinematics import nominal_ik
from pmcal.mechanism.ocpm.params import PAPER_TABLE2
from pmcal.mechanism.rotations import pointing_error, tilt_torsion
from pmcal.cli import main
from pmcal.ocpm.io import write_measurements
from pmcal.twin.ocpm.campaign import plan_campaign, run_campaign
from pmcal.twin.ocpm.machine import Twin
from pmcal.twin.tracker import LaserTracker


@pytest.fixture(scope="module")
def twin():
    return Twin(PAPER_TABLE2)


@pytest.fixture(scope="module")
def files(tmp_path_factory, twin):
    d = tmp_path_factory.mktemp("cli")
    meas = run_campaign(twin, plan_campaign(24, 60.0, seed=1), LaserTracker(0.01, np.random.default_rng(0)))
    write_measurements(d / "meas.csv", meas)
    test = run_campaign(twin, plan_campaign(24, 60.0, seed=77), LaserTracker(0.01, np.random.default_rng(1)))
    write_measurements(d / "test.csv", test)
    plan = plan_campaign(12, 60.0, seed=5)
    with open(d / "targets.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["phi_deg", "theta_deg"])
        w.writerows(zip(plan.phi_deg, plan.theta_deg))
    assert main(["identify", str(d / "meas.csv"), "-o", str(d / "params.json"), "--model", "paper"]) == 0
    (d / "nominal.json").write_text(json.dumps({"mechanism": "ocpm_2dof", "params": {}}))
    return d


def read_rows(path):
    with open(path) as fh:
        return list(csv.DictReader(line for line in fh if not line.startswith("#")))


def test_identify_writes_interface_json(files):
    doc = json.loads((files / "params.json").read_text())
    assert doc["mechanism"] == "ocpm_2dof" and doc["model"] == "paper" and doc["method"] == "hga"
    assert set(doc["params"]) == {k for k in PAPER_TABLE2 if k not in ("L1.day", "L2.dax")}
    ident = doc["identifiability"]
    assert ident["unidentifiable"] == ["L1.day", "L2.dax"] and ident["condition_number"] > 1e3
    assert "platform revolute axis" in ident["explanations"]["L1.day"]
    assert doc["uncertainty"]["L1.day"] is None and doc["uncertainty"]["L1.dalpha"] > 0
    # well-determined parameters match the truth within 3 CRLB (deg, mm at the interface)
    for k in ("L1.dby", "L1.dgamma", "L2.dbx", "L2.dalpha", "L2.dgamma"):
        assert abs(doc["params"][k] - PAPER_TABLE2[k]) < 3 * doc["uncertainty"][k], k
    assert 0.5 < doc["fit"]["residual_rms_sigma"] < 1.5
    assert doc["position_map"]["degree"] >= 1


def test_compensate_setpoints_and_table(files, twin):
    out, table = files / "setpoints.csv", files / "table.json"
    assert main(["compensate", str(files / "params.json"), "--targets", str(files / "targets.csv"),
                 "-o", str(out), "--table", str(table), "--grid", "37,16", "--table-version", "7"]) == 0
    rows = read_rows(out)
    targets = read_rows(files / "targets.csv")
    assert [list(r)[:2] for r in rows] == [["phi_deg", "theta_deg"]] * len(targets)
    np.testing.assert_allclose([float(r["phi_deg"]) for r in rows], [float(t["phi_deg"]) for t in targets],
                               atol=1e-6)
    m = np.array([[float(r["m1_deg"]), float(r["m2_deg"])] for r in rows])
    phi = np.array([float(r["phi_deg"]) for r in rows])
    theta = np.array([float(r["theta_deg"]) for r in rows])
    # the compensated commands bring the twin to the targets: pointing error far below the uncompensated
    before = pointing_error(twin.reach(np.rad2deg(nominal_ik(np.deg2rad(phi), np.deg2rad(theta)))).R,
                            tilt_torsion(np.deg2rad(phi), np.deg2rad(theta)))
    after = pointing_error(twin.reach(m).R, tilt_torsion(np.deg2rad(phi), np.deg2rad(theta)))
    assert np.mean(after) < np.mean(before) / 10          # Table 2: 38x (demo); identify_bench: median 21x, min 8x
    t = CompTable.load(table).validate()
    assert (t.n_phi, t.n_theta, t.version) == (37, 16, 7)
    assert table.with_suffix(".csv").exists()
    assert (t.phi_min_deg, t.phi_max_deg, t.theta_min_deg, t.theta_max_deg) == (0.0, 360.0, 0.0, 60.0)
    # node values are the exact compensation at the node orientations  (format 2: reference + correction)
    nodes = [(3, 0), (10, 5), (20, 15), (36, 7)]
    node_targets = files / "nodes.csv"
    node_targets.write_text("phi_deg,theta_deg\n" + "".join(
        f"{float(t.phi_nodes_deg()[i])!r},{float(t.theta_nodes_deg()[j])!r}\n" for i, j in nodes))
    assert main(["compensate", str(files / "params.json"), "--targets", str(node_targets),
                 "-o", str(files / "nodes_out.csv")]) == 0
    at_nodes = np.array([[float(r["m1_deg"]), float(r["m2_deg"])] for r in read_rows(files / "nodes_out.csv")])
    np.testing.assert_allclose(at_nodes, [t.commands_at_nodes()[i, j] for i, j in nodes], atol=2e-6)
    # between nodes: bilinear, within the curvature bound of a 10 x 4 deg grid
    assert np.max(np.abs(t.interpolate(phi, theta) - m)) < 0.3


def test_nominal_parameters_give_the_nominal_ik(files):
    out = files / "nominal_setpoints.csv"
    assert main(["compensate", str(files / "nominal.json"), "--targets", str(files / "targets.csv"), "-o", str(out)]) == 0
    rows = read_rows(out)
    phi = np.deg2rad([float(r["phi_deg"]) for r in rows])
    theta = np.deg2rad([float(r["theta_deg"]) for r in rows])
    m = np.array([[float(r["m1_deg"]), float(r["m2_deg"])] for r in rows])
    np.testing.assert_allclose(m, np.rad2deg(nominal_ik(phi, theta)), atol=1e-6)


def test_evaluate(files, capsys):
    out_nom, out_cal = files / "eval_nom.json", files / "eval_cal.json"
    assert main(["evaluate", str(files / "nominal.json"), str(files / "test.csv"), "--json", str(out_nom)]) == 0
    assert main(["evaluate", str(files / "params.json"), str(files / "test.csv"), "--json", str(out_cal)]) == 0
    nom, cal = json.loads(out_nom.read_text()), json.loads(out_cal.read_text())
    assert nom["n_poses"] == cal["n_poses"] == 24 and len(cal["per_pose"]) == 24
    assert cal["pointing_error_deg"]["rms"] < nom["pointing_error_deg"]["rms"] / 10
    assert nom["pointing_error_deg"]["max"] > 0.3      # Table 2 errors tilt the platform by ~1 deg
    assert cal["motor_residual_deg"]["m1"]["rms"] < 0.01
    assert "pointing error" in capsys.readouterr().out


# ---------------------------------------------------------------------- bad input
def edit(src, dst, fn):
    lines = [l for l in src.read_text().splitlines() if not l.startswith("#")]
    header, rows = lines[0].split(","), [l.split(",") for l in lines[1:]]
    header, rows = fn(header, rows)
    dst.write_text("\n".join(",".join(r) for r in [header] + rows) + "\n")
    return dst


def set_cell(row, col, value):
    def fn(h, rows):
        rows[row][h.index(col)] = value
        return h, rows
    return fn


def drop_column(col):
    def fn(h, rows):
        k = h.index(col)
        return h[:k] + h[k + 1:], [r[:k] + r[k + 1:] for r in rows]
    return fn


def scale_columns(prefix, factor):
    def fn(h, rows):
        for r in rows:
            for k, name in enumerate(h):
                if name.startswith(prefix):
                    r[k] = f"{float(r[k]) * factor:.9g}"
        return h, rows
    return fn


def lift_row(row, dz):
    def fn(h, rows):
        for k, name in enumerate(h):
            if name.endswith("_z"):
                rows[row][k] = f"{float(rows[row][k]) + dz:.5f}"
        return h, rows
    return fn


def duplicate_id(h, rows):
    rows[4][0] = rows[2][0]
    return h, rows


BAD_MEAS = [
    ("missing column", drop_column("t2_y"), "t2_y", None),
    ("nan", set_cell(2, "m1_cmd_deg", "nan"), "m1_cmd_deg", 3),
    ("not a number", set_cell(6, "t1_x", "12,5"), None, 7),
    ("duplicate id", duplicate_id, "pose_id", 5),
    ("metres", scale_columns("t", 1e-3), "metres", 1),
    ("radians", scale_columns("m", np.pi / 180), "radians", 1),
    ("outside workspace", set_cell(3, "m1_cmd_deg", "170"), "m1_cmd_deg", 4),
    ("not an angle", set_cell(3, "m2_cmd_deg", "1e12"), "m2_cmd_deg", 4),     # was a LinAlgError, exit 1
    ("unreachable pose", lift_row(8, 250.0), "out of reach", 9),
]


@pytest.mark.parametrize("name, fn, needle, row", BAD_MEAS, ids=[b[0] for b in BAD_MEAS])
def test_identify_bad_measurements(files, tmp_path, capsys, name, fn, needle, row):
    bad = edit(files / "meas.csv", tmp_path / "bad.csv", fn)
    out = tmp_path / "p.json"
    assert main(["identify", str(bad), "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "bad.csv" in err
    if needle:
        assert needle in err, err
    if row is not None:
        assert f"row {row}" in err, err
    assert not out.exists()


@pytest.mark.parametrize("argv, needle", [
    (["--method", "simplex"], "--method"),
    (["--model", "full", "--method", "pso"], "--method"),
    (["--sigma", "-1"], "--sigma"),
])
def test_identify_bad_options(files, tmp_path, capsys, argv, needle):
    out = tmp_path / "p.json"
    assert main(["identify", str(files / "meas.csv"), "-o", str(out)] + argv) == 2
    assert needle in capsys.readouterr().err and not out.exists()


def test_identify_too_few_poses(files, tmp_path, capsys):
    few = edit(files / "meas.csv", tmp_path / "few.csv", lambda h, rows: (h, rows[:8]))
    out = tmp_path / "p.json"
    assert main(["identify", str(few), "-o", str(out), "--model", "paper"]) == 2
    assert "cannot determine" in capsys.readouterr().err and not out.exists()


def test_compensate_bad_input(files, tmp_path, capsys):
    out = tmp_path / "s.csv"
    bad_t = tmp_path / "t.csv"
    bad_t.write_text("phi_deg,theta_deg\n10,20\n30,95\n")
    assert main(["compensate", str(files / "params.json"), "--targets", str(bad_t), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "row 2" in err and "theta_deg" in err and not out.exists()
    bad_p = tmp_path / "p.json"
    bad_p.write_text(json.dumps({"mechanism": "ocpm_2dof", "params": {"L1.dfoo": 1.0}}))
    assert main(["compensate", str(bad_p), "--targets", str(files / "targets.csv"), "-o", str(out)]) == 2
    assert "L1.dfoo" in capsys.readouterr().err and not out.exists()
    bad_p.write_text(json.dumps({"mechanism": "ocpm_2dof", "model": "banana", "params": {}}))
    assert main(["compensate", str(bad_p), "--targets", str(files / "targets.csv"), "-o", str(out)]) == 2
    assert "field 'model'" in capsys.readouterr().err and not out.exists()
    assert main(["compensate", str(files / "params.json"), "--targets", str(files / "targets.csv")]) == 2
    assert "-o" in capsys.readouterr().err
    # t.csv beside t.json is the user's targets file: the table's CSV would replace it (issue 33)
    assert main(["compensate", str(files / "params.json"), "--table", str(tmp_path / "t.json")]) == 2
    assert "t.csv would be written beside" in capsys.readouterr().err and bad_t.exists()
    table = tmp_path / "table.json"
    for grid in ("10", "1,5", "a,b"):
        assert main(["compensate", str(files / "params.json"), "--table", str(table), "--grid", grid]) == 2
        assert "--grid" in capsys.readouterr().err and not table.exists()
    # a bad table option must not leave the setpoints half-done either
    assert main(["compensate", str(files / "params.json"), "--targets", str(files / "targets.csv"), "-o", str(out),
                 "--table", str(table), "--table-version", "0"]) == 2
    assert not out.exists() and not table.exists()


def test_evaluate_missing_params(files, tmp_path, capsys):
    out = tmp_path / "e.json"
    assert main(["evaluate", str(tmp_path / "none.json"), str(files / "test.csv"), "--json", str(out)]) == 2
    assert "none.json" in capsys.readouterr().err and not out.exists()


def test_demo_small(tmp_path, monkeypatch, capsys):
    """The demo end to end with the fast methods only (the full demo: `pmcal demo`, benchmarked)."""
    from pmcal.studies.ocpm import demo as demo_study

    monkeypatch.setattr(demo_study.DemoStudy, "METHODS_COMPARED", ("hga", "lm", "tikhonov", "tsvd"))
    out = tmp_path / "demo"
    capsys.readouterr()
    assert main(["demo", "--out", str(out)]) == 0
    lines = capsys.readouterr().out.splitlines()          # piped: the result line, then one line per output
    assert lines[1:] == [f"pmcal: wrote {out}/"] and lines[0].startswith(f"pmcal demo: {out}/report.html in ")
    html = (out / "report.html").read_text()
    for heading in ("Identified vs predefined", "paper Fig. 5", "Algorithm comparison", "Regularisation",
                    "Identifiability", "Pose selection", "Compensation table"):
        assert heading in html
    assert html.count("data:image/png;base64") >= 4 and "http" not in html.split("<body>")[1].split("Generated")[0]
    s = json.loads((out / "summary.json").read_text())
    assert s["after_mean_deg"] < s["before_mean_deg"] / 10
    assert f"{s['before_mean_deg']:.4f} -> {s['after_mean_deg']:.4f} deg" in lines[0]
    # the tracker-frame run: outlier named, registration within its reported uncertainty, pointing of the
    # order the frame uncertainty allows (mean 1.25 sigma per axis, docs/tracker_frame.md)
    tr = s["tracker_frame"]
    assert "Tracker in its own frame" in html and tr["outliers_named"] and tr["outliers_planted"]
    assert tr["registration_rotation_error_deg"] < 4 * tr["registration_rotation_std_deg"]
    assert tr["registration_translation_error_mm"] < 4 * tr["registration_translation_std_mm"]
    assert tr["after_mean_deg"] < 4 * tr["registration_rotation_std_deg"] + 0.003
    assert json.loads((out / "params_tracker.json").read_text())["frame"] == "tracker"
    CompTable.load(out / "comp_table.json").validate()
    assert json.loads((out / "params.json").read_text())["mechanism"] == "ocpm_2dof"
