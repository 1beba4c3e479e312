"""`pmcal twin measure|render`: valid output, and one clear error with exit 2 for bad arguments."""

import json

import numpy as np
import pytest

from pmcal.mechanism.ocpm.params import PAPER_TABLE2
from pmcal.cli import main
from pmcal.ocpm.io import read_measurements
from pmcal.twin.ocpm.machine import Twin


def run(argv, capsys):
    rc = main(argv)
    err = capsys.readouterr().err
    return rc, err


def test_measure_paper_table2_writes_a_valid_campaign(tmp_path, capsys):
    out = tmp_path / "m.csv"
    rc, err = run(["--quiet", "twin", "measure", "--preset", "paper-table2", "--poses", "24", "--seed", "1",
                   "-o", str(out)], capsys)
    assert rc == 0, err
    meas = read_measurements(out)
    assert len(meas) == 24 and meas.targets.shape == (24, 3, 3)
    _, _, rms = meas.poses()
    # k = 3 targets: E[rms^2] = sigma^2 (3k - 6) / k = sigma^2
    assert np.sqrt(np.mean(rms**2)) == pytest.approx(0.01, rel=0.35)
    # the same commands on the same machine without noise: differences are the tracker's noise
    truth = Twin(PAPER_TABLE2).reach(meas.m_cmd_deg).targets
    assert np.std(meas.targets - truth) == pytest.approx(0.01, rel=0.2)
    assert np.abs(meas.targets - truth).max() < 6 * 0.01
    # reproducible with the seed
    out2 = tmp_path / "m2.csv"
    assert main(["--quiet", "twin", "measure", "--preset", "paper-table2", "--poses", "24", "--seed", "1",
                 "-o", str(out2)]) == 0
    assert out.read_text().splitlines()[1:] == out2.read_text().splitlines()[1:]


@pytest.mark.parametrize("args, message", [
    (["--errors", "{json_unknown}"], "unknown limb parameter 'L1.dxx'"),
    (["--errors", "{json_broken}"], "not valid JSON"),
    (["--errors", "{missing}"], "file not found"),
    (["--noise", "-0.01"], "noise must be a non-negative"),
    (["--poses", "0"], "must be 1..2000"),
    (["--poses", "2001"], "must be 1..2000"),
    (["--theta-max", "95"], "outside the workspace"),
    (["--targets", "{targets_unreachable}"], "row 2, field 'theta_deg'"),
    (["--preset", "table3"], "unknown preset"),
    (["--stiffness-ratio", "-5"], "stiffness ratio must be a positive"),
])
def test_bad_arguments_exit_2_with_one_line_and_no_file(tmp_path, capsys, args, message):
    files = {
        "json_unknown": tmp_path / "e.json", "json_broken": tmp_path / "b.json",
        "missing": tmp_path / "nope.json", "targets_unreachable": tmp_path / "t.csv",
    }
    files["json_unknown"].write_text(json.dumps({"params": {"L1.dxx": 1.0}}))
    files["json_broken"].write_text("{not json")
    files["targets_unreachable"].write_text("phi_deg,theta_deg\n0,10\n30,89\n")
    args = [a.format(**{k: str(v) for k, v in files.items()}) for a in args]
    out = tmp_path / "out.csv"
    rc, err = run(["--quiet", "twin", "measure", *args, "-o", str(out)], capsys)
    assert rc == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and message in lines[0]
    assert not out.exists()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".out")] == []


def test_render_writes_a_png(tmp_path, capsys):
    out = tmp_path / "pm.png"
    rc, err = run(["--quiet", "twin", "render", "--preset", "paper-table2", "--pose", "45,30",
                   "--width", "320", "--height", "240", "-o", str(out)], capsys)
    if rc == 1 and "offscreen rendering is unavailable" in err:
        pytest.skip(err)
    assert rc == 0, err
    data = out.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000


def test_render_rejects_a_bad_pose(tmp_path, capsys):
    rc, err = run(["twin", "render", "--pose", "10", "-o", str(tmp_path / "x.png")], capsys)
    assert rc == 2 and "PHI,THETA" in err and not (tmp_path / "x.png").exists()
