"""One line that names the real cause (issue 33): another machine's file, a table box beyond the reach
(found by probing its corners before the grid), a grid beyond the PLC's 20 000 values (before it is built),
shared option ranges, and a near-miss column name of ocpm_2dof.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

import pmcal.mjcf
from pmcal.cli import main
from tests.conftest import run_quietly_in


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    """A Delta campaign and its parameters, an ocpm_2dof campaign, and a copy of the Delta ('far') whose
    table box reaches 900 mm out in x."""
    d = tmp_path_factory.mktemp("causes")
    far = d / "far"
    shutil.copytree(pmcal.mjcf.machine_dir("delta_3dof"), far)
    toml = (far / "machine.toml").read_text()
    assert "x_mm = [-150.0, 150.0]" in toml
    (far / "machine.toml").write_text(toml.replace("x_mm = [-150.0, 150.0]", "x_mm = [-150.0, 900.0]")
                                      .replace('name = "delta_3dof"', 'name = "far"'))
    return run_quietly_in(d, ["--machine", "delta_3dof", "twin", "measure", "--seed", "3", "-o", "d.csv"],
                          ["--machine", "delta_3dof", "identify", "d.csv", "-o", "dp.json"],
                          ["twin", "measure", "--poses", "24", "--seed", "1", "-o", "o.csv"])


def one_line(capsys, folder: Path, *argv) -> str:
    cwd = os.getcwd()
    os.chdir(folder)
    try:
        capsys.readouterr()
        status = main([str(a) for a in argv])
    finally:
        os.chdir(cwd)
    err = capsys.readouterr().err.strip()
    assert status == 2 and len(err.splitlines()) == 1 and "Traceback" not in err, err
    return err


def test_another_machines_file_is_named_as_such(work, capsys):
    for argv in (["identify", "d.csv", "-o", "x.json"], ["--machine", "hexapod_6dof", "identify", "d.csv", "-o", "x.json"],
                 ["compensate", "dp.json", "--table", "t.json"], ["--machine", "delta_3dof", "identify", "o.csv", "-o", "x.json"]):
        err = one_line(capsys, work, *argv)
        assert "this is a file of machine" in err and "give --machine" in err, err
    assert not list(work.glob("x.json")) and not list(work.glob("t.json"))


def test_a_table_box_beyond_the_reach_is_found_at_its_corners(work, capsys):
    doc = (work / "dp.json").read_text().replace('"mechanism": "delta_3dof"', '"mechanism": "far"')
    (work / "farp.json").write_text(doc)
    err = one_line(capsys, work, "--machine", "./far", "compensate", "farp.json", "--table", "t.json")
    assert "the table box's corner x_mm=900, y_mm=-150, z_mm=-900 is not reachable" in err, err
    assert "field 'table'" in err and not (work / "t.json").exists()


@pytest.mark.parametrize("grid, values", [("100,100,100", 3_000_000), ("30,30,30", 81_000)])
def test_a_grid_beyond_the_plc_is_refused_before_it_is_built(work, capsys, grid, values):
    err = one_line(capsys, work, "--machine", "delta_3dof", "compensate", "dp.json", "--table", "t.json", "--grid", grid)
    assert err == (f"pmcal: error: field '--grid': grid {grid.replace(',', 'x')} x 3 motors = {values} values, more "
                   "than the PLC's 20000: fewer nodes per axis")


@pytest.mark.parametrize("argv, says", [
    (["twin", "measure", "--seed", "-1", "-o", "x.csv"], "field '--seed': a random seed must be a whole number (0..4294967295), got -1"),
    (["--machine", "delta_3dof", "loop", "--seed", "-1"], "field '--seed'"),
    (["demo", "--seed", "-1"], "field '--seed'"),
    (["--machine", "delta_3dof", "identify", "d.csv", "-o", "x.json", "--sigma", "1e300"],
     "field '--sigma': the tracker noise must be a positive number of mm (above 0 and at most 10), got 1e+300"),
    (["twin", "render", "--pose", "nan,30", "-o", "x.png"], "field '--pose': expected 2 comma-separated numbers"),
])
def test_ranges_are_checked_before_work(work, capsys, argv, says):
    assert says in one_line(capsys, work, *argv)


def test_a_near_miss_column_of_ocpm_2dof_is_refused(work, capsys):
    lines = (work / "o.csv").read_text().splitlines()
    out = [line if line.startswith("#") else line + (",temp_C" if line.startswith("pose_id") else ",20.5") for line in lines]
    (work / "tc.csv").write_text("\n".join(out) + "\n")
    err = one_line(capsys, work, "identify", "tc.csv", "-o", "x.json")
    assert "field 'temp_C': unknown column; did you mean temp_c?" in err


def test_an_import_in_metres_is_refused_before_anything_is_written(tmp_path, capsys):
    """Nest distances are frame-free: points in metres are named as such, not blamed on the frame."""
    data = Path(__file__).parent / "data"
    lines = []
    for line in (data / "sa_export_handwritten.txt").read_text().splitlines():
        f = line.split()
        if not line.startswith("//") and len(f) >= 6:
            try:
                f[3:6] = [repr(float(v) / 1000.0) for v in f[3:6]]
            except ValueError:
                pass
            line = " ".join(f)
        lines.append(line)
    (tmp_path / "metres.txt").write_text("\n".join(lines) + "\n")
    err = one_line(capsys, tmp_path, "import", "metres.txt", "--log", data / "controller_log_handwritten.csv",
                   "-o", "m.csv")
    assert "pose 1: targets t1 and t2 are 0.1732 mm apart, the platform has them 173.2 mm apart (values look like " \
           "metres" in err, err
    assert not (tmp_path / "m.csv").exists()


def _campaign(src: Path, dst: Path, rows) -> Path:
    lines = src.read_text().splitlines()
    head = [line for line in lines if line.startswith(("#", "pose_id"))]
    data = [line for line in lines if not line.startswith(("#", "pose_id"))]
    dst.write_text("\n".join(head + rows(data)) + "\n")
    return dst


def _shifted(data: list[str], row: int, mm: float) -> list[str]:
    cells = data[row - 1].split(",")
    cells[4] = repr(float(cells[4]) + mm)                   # t1_x of the Delta (pose_id, m1..m3, t1_x)
    return data[: row - 1] + [",".join(cells)] + data[row:]


@pytest.mark.parametrize("name, rows, why", [
    ("two", lambda d: d[:2], "the campaign determines 12 of the 42 error combinations"),
    ("same", lambda d: [f"S{i}," + d[0].split(",", 1)[1] for i in range(48)], "1 distinct poses (47 rows repeat a pose)"),
    ("outlier", lambda d: _shifted(d, 5, 3.0), "gross outlier: row 5 (P5): target t1 is 3"),
])
def test_a_weak_campaign_of_a_folder_machine_is_flagged_and_refused(work, capsys, name, rows, why):
    """The Delta: identify says NOT usable and why; compensate (targets, table) refuses without --force; a
    table forced out of it carries the verdict, and push refuses it before any link."""
    _campaign(work / "d.csv", work / f"{name}.csv", rows)
    cwd = os.getcwd()
    os.chdir(work)
    try:
        capsys.readouterr()
        assert main(["--machine", "delta_3dof", "identify", f"{name}.csv", "-o", f"{name}.json"]) == 0
        cap = capsys.readouterr()
        assert "; NOT usable" in cap.out.splitlines()[0] and why in cap.err, cap
        assert main(["--machine", "delta_3dof", "targets", "-o", "tg.csv", "--quiet"]) == 0
    finally:
        os.chdir(cwd)
    err = one_line(capsys, work, "--machine", "delta_3dof", "compensate", f"{name}.json", "--targets", "tg.csv",
                   "-o", "s.csv")
    assert "calibration flagged not usable" in err and why in err and "--force" in err
    one_line(capsys, work, "--machine", "delta_3dof", "compensate", f"{name}.json", "--table", f"{name}_t.json")
    if name == "two":                                        # forced: the table carries the verdict to push
        os.chdir(work)
        try:
            assert main(["--quiet", "--machine", "delta_3dof", "compensate", "two.json", "--table", "two_t.json",
                         "--force"]) == 0
        finally:
            os.chdir(cwd)
        err = one_line(capsys, work, "--machine", "delta_3dof", "push", "two_t.json", "--modbus", "127.0.0.1:1",
                       "--dry-run")
        assert "field 'quality'" in err and "--force" in err
