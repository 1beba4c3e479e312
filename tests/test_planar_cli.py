"""The planar machine through the command line and its files: round trip, bad input, demo."""

import json
from argparse import Namespace

import numpy as np
import pytest

from pmcal.calib.planar.identification import identify
from pmcal.mechanism.planar.kinematics import actual_position, forward, mm_vector
from pmcal.apps import planar as app
from pmcal.cli import main
from pmcal.planar.io import read_measurements
from pmcal.twin.planar.config import default_machine
from pmcal.twin.planar.twin import PlanarTwin

M = default_machine()
G = M.geometry


def run(*argv):
    return main(["--quiet", "--machine", "planar_2dof", *argv])


@pytest.fixture
def campaign(tmp_path):
    """A noise-free twin campaign of group 1 at 14 positions (scale and servo noise off)."""
    out = tmp_path / "meas.csv"
    args = Namespace(preset="group1", errors=None, noise=0.0, servo_noise=0.0, poses=14, seed=1,
                     targets=None, output=str(out))
    assert app.twin_measure(args) == 0
    return out


def test_measure_identify_evaluate_round_trip(campaign, tmp_path):
    meas = read_measurements(campaign, G)
    err = M.preset("group1")
    # the file holds what the closed forms say the scale reads (6 decimals in the file)
    length = np.linalg.norm(mm_vector(G.perturbed(err), actual_position(G, err, meas.theta_cmd)), axis=-1)
    assert np.abs(meas.readings - np.diff(length)).max() < 1e-6
    assert np.abs(meas.r - forward(G, meas.theta_cmd)).max() < 1e-9
    params = tmp_path / "params.json"
    assert run("identify", str(campaign), "-o", str(params)) == 0
    doc = json.loads(params.read_text())
    assert doc["mechanism"] == "planar_2dof" and doc["rank"] == 4 and doc["units"]["dtheta1"] == "deg"
    expected = identify(G, meas.r, np.diff(length), noise=M.noise)
    assert doc["params"]["dtheta1"] == pytest.approx(np.rad2deg(expected.x[0]), abs=1e-3)
    assert doc["params"]["drMy"] == pytest.approx(expected.x[3], abs=1e-3)
    full = tmp_path / "full.json"
    # the full model's G has rank 9 of 12 (translating the base with O1, turning about O1 change no reading):
    # success is refused unless the user accepts it, and the null space is reported either way
    assert run("identify", str(campaign), "-o", str(full), "--model", "full", "--method", "tsvd") == 1
    doc = json.loads(full.read_text())
    assert doc["rank"] == 9 and doc["success"] is False and len(doc["null_space"]) == 3
    assert run("identify", str(campaign), "-o", str(full), "--model", "full", "--method", "tsvd",
               "--allow-rank-deficient") == 0
    doc = json.loads(full.read_text())
    assert doc["success"] is True and len(doc["null_space"]) == 3
    # evaluate: the true parameters explain the readings, the nominal machine does not
    truth = tmp_path / "truth.json"
    truth.write_text(json.dumps({"mechanism": "planar_2dof", "params": err.as_interface()}))
    ev = tmp_path / "eval.json"
    assert run("evaluate", str(truth), str(campaign), "--json", str(ev)) == 0
    e = json.loads(ev.read_text())
    assert e["rms_params"] < 1e-5 and e["rms_nominal"] > 0.1


def test_compensate_with_the_true_parameters_reaches_the_targets(tmp_path):
    err = M.preset("group1")
    truth = tmp_path / "truth.json"
    truth.write_text(json.dumps({"mechanism": "planar_2dof", "params": err.as_interface()}))
    targets = tmp_path / "targets.csv"
    targets.write_text("# targets\nname,x_mm,y_mm\na,0,-632\nb,200,-700\nc,-240,-782\n")
    out = tmp_path / "setpoints.csv"
    assert run("compensate", str(truth), "--targets", str(targets), "-o", str(out)) == 0
    lines = [l for l in out.read_text().splitlines() if not l.startswith("#")]
    assert lines[0] == "name,x_mm,y_mm,theta1_deg,theta2_deg"
    theta = np.deg2rad(np.array([[float(v) for v in l.split(",")[3:]] for l in lines[1:]]))
    reached = PlanarTwin(err, M).assemble(theta).r
    assert np.abs(reached - [[0, -632], [200, -700], [-240, -782]]).max() < 1e-6


BAD_MEASUREMENTS = [
    ("pose_id,theta1_cmd_deg,theta2_cmd_deg\nP1,0,180\n", "scale_change_mm", None),
    ("pose_id,theta1_cmd_deg,theta2_cmd_deg,scale_change_mm\nP1,0,180,\nP2,1,181,0.5\nP3,x,181,0.1\n"
     "P4,0,179,0.1\nP5,0,178,0.1\nP6,1,178,0.1\n", "theta1_cmd_deg", 3),
    ("pose_id,theta1_cmd_deg,theta2_cmd_deg,scale_change_mm\nP1,0,180,1.0\nP2,1,181,0.5\nP3,2,181,0.1\n"
     "P4,0,179,0.1\nP5,0,178,0.1\nP6,1,178,0.1\n", "scale_change_mm", 1),
    ("pose_id,theta1_cmd_deg,theta2_cmd_deg,scale_change_mm\nP1,0,3.14,\nP2,0.01,3.15,0.5\nP3,0.02,3.1,0.1\n"
     "P4,0,3.12,0.1\nP5,0,3.13,0.1\nP6,0.01,3.11,0.1\n", "theta1_cmd_deg", 1),
    ("pose_id,theta1_cmd_deg,theta2_cmd_deg,scale_change_mm\nP1,0,180,\nP2,1,181,0.5\n", "pose_id", None),
    ("pose_id,theta1_cmd_deg,theta2_cmd_deg,scale_change_mm\nP1,0,180,\nP1,1,181,0.5\nP3,2,181,0.1\n"
     "P4,0,179,0.1\nP5,0,178,0.1\nP6,1,178,0.1\n", "pose_id", 2),
]


@pytest.mark.parametrize("text,field,row", BAD_MEASUREMENTS)
def test_bad_measurement_files_exit_2_naming_file_row_field(tmp_path, capsys, text, field, row):
    f = tmp_path / "bad.csv"
    f.write_text(text)
    out = tmp_path / "p.json"
    assert run("identify", str(f), "-o", str(out)) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "bad.csv" in err and f"field '{field}'" in err
    if row is not None:
        assert f"row {row}" in err
    assert not out.exists()


@pytest.mark.parametrize("doc,field", [
    ({"mechanism": "ocpm_2dof", "params": {}}, "mechanism"),
    ({"mechanism": "planar_2dof", "params": {"dtheta3": 1.0}}, "params.dtheta3"),
    ({"mechanism": "planar_2dof", "params": {"dtheta1": "a"}}, "params.dtheta1"),
    ({"mechanism": "planar_2dof", "params": {"dtheta1": 200.0}}, "params.dtheta1"),
])
def test_bad_parameter_files(tmp_path, capsys, doc, field):
    p = tmp_path / "params.json"
    p.write_text(json.dumps(doc))
    targets = tmp_path / "t.csv"
    targets.write_text("x_mm,y_mm\n0,-700\n")
    out = tmp_path / "s.csv"
    assert run("compensate", str(p), "--targets", str(targets), "-o", str(out)) == 2
    err = capsys.readouterr().err
    assert "params.json" in err and f"field '{field}'" in err and not out.exists()


def test_bad_targets_and_options(tmp_path, capsys):
    truth = tmp_path / "p.json"
    truth.write_text(json.dumps({"mechanism": "planar_2dof", "params": {}}))
    targets = tmp_path / "t.csv"
    targets.write_text("x_mm,y_mm\n0,-700\n0,700\n")
    out = tmp_path / "s.csv"
    assert run("compensate", str(truth), "--targets", str(targets), "-o", str(out)) == 2
    assert "row 2" in capsys.readouterr().err and not out.exists()
    meas = tmp_path / "m.csv"
    assert run("twin", "measure", "--poses", "5", "-o", str(meas)) == 2
    assert "--poses" in capsys.readouterr().err and not meas.exists()
    assert run("twin", "measure", "--preset", "group9", "-o", str(meas)) == 2
    assert "--preset" in capsys.readouterr().err and not meas.exists()


@pytest.mark.filterwarnings("error::RuntimeWarning")
def test_an_astronomic_target_is_one_line_without_a_numpy_warning(tmp_path, capsys):
    truth = tmp_path / "p.json"
    truth.write_text(json.dumps({"mechanism": "planar_2dof", "params": {}}))
    targets = tmp_path / "t.csv"
    targets.write_text("x_mm,y_mm\n0,-700\n1e300,-632\n")      # was an overflow RuntimeWarning on stderr first
    out = tmp_path / "s.csv"
    assert run("compensate", str(truth), "--targets", str(targets), "-o", str(out)) == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and "row 2" in err and "out of the robot's reach" in err and not out.exists()


def test_demo_writes_report_and_json(tmp_path):
    out = tmp_path / "demo"
    assert app.demo(Namespace(out=str(out), seed=2, runs=2, max_iterations=4, picture=False,
                              hidden_effect=None)) == 0
    res = json.loads((out / "results.json").read_text())
    assert res["condition"]["kappa1"][0] == pytest.approx(475.34, abs=5e-3)
    assert res["rank"] == {**res["rank"], "simplified_K6": 4, "full_K14": 9}
    g1 = res["groups"]["group1"]["seed"]
    assert g1["dp0_before_mm"] == pytest.approx(10.933, abs=2e-3)
    html = (out / "report.html").read_text()
    assert "Table 3" in html and "Table 5" in html and "Fig. 9" in html and "data:image/png;base64" in html
    assert (out / "measurements_group1.csv").exists() and (out / "params_group1.json").exists()


def test_machine_configuration_is_validated(tmp_path):
    from pmcal.errors import InputError
    from pmcal.twin.planar.config import CONFIG_TOML, load_machine

    text = CONFIG_TOML.read_text()
    bad = tmp_path / "machine.toml"
    bad.write_text(text.replace("L = [375.0, 375.0]", "L = [-375.0, 375.0]"))
    with pytest.raises(InputError) as exc:
        load_machine(bad)
    assert exc.value.field == "[geometry] L" and exc.value.file == str(bad)
    bad.write_text(text.replace("dtheta1 = 2.0", "dtheta9 = 2.0", 1))
    with pytest.raises(InputError) as exc:
        load_machine(bad)
    assert exc.value.field == "[presets.group1] dtheta9"


def test_twin_measure_with_an_error_file(tmp_path):
    errors = tmp_path / "errors.json"
    errors.write_text(json.dumps({"dtheta1": 0.3, "drMx": 0.5}))        # flat form accepted for the twin
    out = tmp_path / "m.csv"
    assert run("twin", "measure", "--errors", str(errors), "--poses", "6", "--noise", "0", "-o", str(out)) == 0
    assert len(read_measurements(out, G).ids) == 6


def test_chain_model_finds_the_rank_9_of_the_full_model(campaign, tmp_path):
    """``--model chain``: the paper's 12 errors on the generic closed-chain core. It finds by itself what
    docs/planar.md derives by hand: rank 9 (translating the base with O1 in x and y, turning the robot
    about O1 change no reading), the three combinations named; the fit explains the readings."""
    params = tmp_path / "chain.json"
    assert run("identify", str(campaign), "-o", str(params), "--model", "chain") == 0
    doc = json.loads(params.read_text())
    assert doc["model"] == "chain" and doc["rank"] == 9 and len(doc["unidentifiable"]) == 3
    assert set(doc["params"]) == set(M.preset("group1").as_interface())
    assert len(set(doc["params"]) - set(doc["identifiable"])) == 3
    ev = tmp_path / "eval.json"
    assert run("evaluate", str(params), str(campaign), "--json", str(ev)) == 0
    e = json.loads(ev.read_text())
    # noise-free readings; the fit assumes the paper's servo noise (0.0024 deg: ~0.02 mm per reading)
    assert e["rms_params"] < 0.05 * e["rms_nominal"] and e["rms_params"] == pytest.approx(doc["residual_rms_mm"],
                                                                                        rel=1e-3)
    out = tmp_path / "s.csv"
    targets = tmp_path / "t.csv"
    targets.write_text("x_mm,y_mm\n0,-700\n100,-650\n")
    assert run("compensate", str(params), "--targets", str(targets), "-o", str(out)) == 0
