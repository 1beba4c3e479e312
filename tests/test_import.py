"""``pmcal import`` (issue 23): tracker exports + controller log -> measurement CSV.

References independent of the reader: the numbers typed into the hand-written files in tests/data, and
the twin's own campaign (its Measurements) written out in SA's layout by tests/tracker_files.py.
"""

import json
import re
import shutil

import numpy as np
import pytest

from pmcal.ocpm.calibration import identify
from pmcal.cli import main
from pmcal.ocpm.io import read_measurements, write_measurements
from pmcal.ocpm.io import join
from pmcal.io_tracker import read_controller_log, read_sa_ascii
from pmcal.mechanism.ocpm.params import PAPER_TABLE2
from pmcal.twin.ocpm.campaign import plan_campaign, run_campaign
from pmcal.twin.ocpm.machine import Twin
from pmcal.twin.tracker import LaserTracker, random_tracker_pose
from tests.tracker_files import write_log, write_sa_export

DATA = "tests/data"
SA = f"{DATA}/sa_export_handwritten.txt"
LOG = f"{DATA}/controller_log_handwritten.csv"


def run(*argv):
    return main(list(argv))


def test_handwritten_export_joins_as_typed(tmp_path, capsys):
    out = tmp_path / "m.csv"
    assert run("import", SA, "--log", LOG, "-o", str(out)) == 0
    err = capsys.readouterr().err
    meas = read_measurements(out)
    assert meas.pose_id == ["1", "2", "3", "4", "5"]
    # the re-shot point: the second shot (line 11) kept, the first (x 136.9991) dropped, both lines named
    assert meas.targets[1, 0].tolist() == [136.9482, -85.2386, 458.1845]
    assert f"{SA}:11" in err and f"{SA}:8" in err and "measured again" in err
    # the comma-separated lines (with and without blanks after the commas)
    assert meas.targets[1, 1].tolist() == [-9.8605, -6.0247, 504.812]
    assert meas.targets[3, 1].tolist() == [-190.8847, 10.2481, 449.8734]
    # the blocked nest P003 T2: three empty cells
    assert np.isnan(meas.targets[2, 1]).all() and np.isfinite(meas.targets[2, [0, 2]]).all()
    # the reference point that is not a nest: left out, named with its line
    assert f"{SA}:21" in err and "BASE1" in err
    assert meas.m_cmd_deg[2].tolist() == [-32.8441, -17.373] and meas.temp_c.tolist()[-1] == 21.5
    head = out.read_text().splitlines()[:4]
    assert any("units: mm" in h for h in head) and any(h == "# frame: base" for h in head)
    assert any("OCPM::Base" in h and "2023.1" in h for h in head)


def test_inches_from_header_or_option(tmp_path):
    text = open(SA).read().replace("Millimeters", "Inches")
    (tmp_path / "in.txt").write_text(text)
    exp = read_sa_ascii(tmp_path / "in.txt")
    assert exp.units == "in" and np.allclose(exp.points[0].xyz, np.array([76.7069, 10.4168, 489.4456]) * 25.4)
    assert read_sa_ascii(SA, units="in").points[0].xyz[0] == pytest.approx(76.7069 * 25.4)
    # time stamps: 10:00:01 AM and 10:00:04 AM are 3 s apart
    assert exp.points[1].time_s - exp.points[0].time_s == pytest.approx(3.0)


def test_point_csv_with_column_map(tmp_path):
    rows = ["Point,Xmm,Ymm,Zmm"]
    for p in read_sa_ascii(SA).points[:6]:
        rows.append(f"{p.name.replace(' ', '_')},{p.xyz[0]},{p.xyz[1]},{p.xyz[2]}")
    (tmp_path / "pts.csv").write_text("\n".join(rows) + "\n")
    out = tmp_path / "m.csv"
    assert run("import", str(tmp_path / "pts.csv"), "--log", LOG, "-o", str(out), "--columns",
               "name=Point,x=Xmm,y=Ymm,z=Zmm", "--names", r"OCPM_(?P<pose>P\d+)_(?P<target>T\d)") == 0
    meas = read_measurements(out, check_units=False)
    assert meas.pose_id == ["1", "2"] and meas.targets[0, 2].tolist() == [-72.9301, -76.3543, 480.3567]


@pytest.mark.parametrize("columns", ["name=Point,name=Xmm,x=Xmm,y=Ymm,z=Zmm",
                                     "name=Point,pose=Point,target=Point,x=Xmm,y=Ymm,z=Zmm"])
def test_ambiguous_column_map_is_refused(tmp_path, capsys, columns):
    """A key given twice, or name with pose/target, was read silently (the last one, or name ignored)."""
    (tmp_path / "pts.csv").write_text("Point,Xmm,Ymm,Zmm\nP001_T1,76.7,10.4,489.4\n")
    assert run("import", str(tmp_path / "pts.csv"), "--log", LOG, "-o", str(tmp_path / "m.csv"),
               "--columns", columns) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "field '--columns'" in err[0], err


def test_bad_time_in_point_csv_names_the_row(tmp_path, capsys):
    (tmp_path / "pts.csv").write_text("Point,X,Y,Z,T\nP001 T1,76.7,10.4,489.4,0\nP001 T2,-72.7,96.7,474.0,soon\n")
    assert run("import", str(tmp_path / "pts.csv"), "--log", LOG, "-o", str(tmp_path / "m.csv"),
               "--columns", "name=Point,x=X,y=Y,z=Z,time=T") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "pts.csv row 2, field 'T'" in err[0], err


def test_join_by_time_and_ambiguity(tmp_path):
    meas = run_campaign(Twin(), plan_campaign(6, 40, seed=2), LaserTracker(0.01, np.random.default_rng(3)))
    write_sa_export(tmp_path / "t.txt", meas, units="mm", names="Target")   # no pose in the names
    write_log(tmp_path / "log.csv", meas, posix_time=True)
    exp, log = read_sa_ascii(tmp_path / "t.txt"), read_controller_log(tmp_path / "log.csv")
    res = join(exp, log, time_tolerance_s=10.0)          # points 0, 3, 6 s after each pose; poses 30 s apart
    assert res.warnings == [] and "time" in res.join
    assert np.allclose(res.meas.targets, meas.targets, atol=5e-7)
    res = join(exp, log, time_tolerance_s=25.0)          # T3, 6 s after its pose, is 24 s before the next
    assert any("ambiguous" in w for w in res.warnings)
    with pytest.raises(Exception, match="no point of the export matches"):
        join(exp, log)                                   # no tolerance: nothing can be joined


def test_many_stray_points_are_one_warning_line(tmp_path, capsys):
    """An export with thousands of points of poses the log does not have printed one warning line each (a 57 MB
    export: thousands of lines, 77 s): now one line with the count and the first three by name and line."""
    meas = run_campaign(Twin(), plan_campaign(6, 40, seed=2), LaserTracker(0.01, np.random.default_rng(3)))
    write_sa_export(tmp_path / "t.txt", meas, units="mm", collection="OCPM")
    write_log(tmp_path / "log.csv", meas)
    with open(tmp_path / "t.txt", "a", encoding="utf-8") as fh:
        fh.writelines(f"OCPM P{900 + i} T{i % 3 + 1} 1.0 2.0 3.0\n" for i in range(2000))
    first = len((tmp_path / "t.txt").read_text().splitlines()) - 2000 + 1
    capsys.readouterr()
    assert run("import", str(tmp_path / "t.txt"), "--log", str(tmp_path / "log.csv"), "-o",
               str(tmp_path / "m.csv")) == 0
    warnings = [line for line in capsys.readouterr().err.splitlines() if line.startswith("pmcal: warning:")]
    assert len(warnings) == 1, warnings[:5]
    assert warnings[0] == (f"pmcal: warning: {tmp_path / 't.txt'}: 2000 points name a pose that is not in the log: "
                           f"left out ('OCPM P900 T1' ({tmp_path / 't.txt'}:{first}), 'OCPM P901 T2' "
                           f"({tmp_path / 't.txt'}:{first + 1}), 'OCPM P902 T3' ({tmp_path / 't.txt'}:{first + 2}) "
                           "and 1997 more)")
    assert len(read_measurements(tmp_path / "m.csv")) == 6


def test_tracker_frame_detected_and_recorded(tmp_path, capsys):
    pose = random_tracker_pose(np.random.default_rng(4))
    meas = run_campaign(Twin(), plan_campaign(6, 40, seed=2), LaserTracker(0.01, np.random.default_rng(3), pose=pose))
    write_sa_export(tmp_path / "t.txt", meas, units="mm", frame="OCPM::Base")   # header claims base: check fails
    write_log(tmp_path / "log.csv", meas)
    out = tmp_path / "m.csv"
    assert run("import", str(tmp_path / "t.txt"), "--log", str(tmp_path / "log.csv"), "-o", str(out)) == 0
    assert "--frame tracker" in capsys.readouterr().err
    assert any(line.startswith("# frame: tracker") for line in out.read_text().splitlines())
    meas0 = run_campaign(Twin(), plan_campaign(6, 40, seed=2), LaserTracker(0.01, np.random.default_rng(3)))
    write_sa_export(tmp_path / "w.txt", meas0, units="mm", frame="OCPM::Tracker1")   # named frame not the base
    res = join(read_sa_ascii(tmp_path / "w.txt"), read_controller_log(tmp_path / "log.csv"))
    assert res.frame == "tracker" and "Tracker1" in res.comments[2]


@pytest.mark.parametrize("text,where,field", [
    ("OCPM P001 T1 76.7 10.4 abc\n", ":1", "x"),
    ("// Frame: Base\nOCPM P001 T1 76.7 10.4 489.4 0.05 0.01 13/45/2026 99:00:01 XM\n", ":2", "time"),
    ("// only comments\n", "", None),
    ("OCPM P001 T1 nan 10.4 489.4 0.05 0.01\n", ":1", "x"),                        # not read as a fourth name field
    ("// Units: Meters\nOCPM P001 T1 0.0767 0.0104 0.4894\n", ":1", "units"),     # was read as mm
    ("OCPM P001 T1 76.7 10.4 489.4 0.05 0.01\nOCPM P001 T2 -72.7 inf 474.0 0.05 0.01\n", ":2", "y"),
])
def test_bad_export_one_line(tmp_path, capsys, text, where, field):
    (tmp_path / "bad.txt").write_text(text)
    assert run("import", str(tmp_path / "bad.txt"), "--log", LOG, "-o", str(tmp_path / "m.csv")) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"bad.txt{where}" in err[0] and (field is None or f"field '{field}'" in err[0])
    assert not (tmp_path / "m.csv").exists()


@pytest.mark.filterwarnings("error::RuntimeWarning")
def test_astronomic_coordinates_one_line(tmp_path, capsys):
    """1e300 mm is refused by the nests' distance check, without numpy's overflow warnings on stderr first."""
    text = open(SA, encoding="utf-8").read().replace("76.7069", "1e300")
    (tmp_path / "bad.txt").write_text(text)
    assert run("import", str(tmp_path / "bad.txt"), "--log", LOG, "-o", str(tmp_path / "m.csv")) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "bad.txt" in err[0] and "pose 1" in err[0], err
    assert not (tmp_path / "m.csv").exists()


def test_bad_log_and_options(tmp_path, capsys):
    (tmp_path / "log.csv").write_text("pose_id,m1_cmd_deg,m2_cmd_deg\n1,-43.1,-37.7\n2,x,-54.2\n")
    assert run("import", SA, "--log", str(tmp_path / "log.csv"), "-o", str(tmp_path / "m.csv")) == 2
    assert "log.csv, row 2, field 'm1_cmd_deg'" in capsys.readouterr().err
    (tmp_path / "log.csv").write_text("pose_id,m1_cmd_deg,m2_cmd_deg\n1,-43.1,-37.7\n2,1e300,-54.2\n")
    assert run("import", SA, "--log", str(tmp_path / "log.csv"), "-o", str(tmp_path / "m.csv")) == 2   # was exit 1
    assert "log.csv, row 2, field 'm1_cmd_deg'" in capsys.readouterr().err
    (tmp_path / "ids.csv").write_text("pose_id,m1_cmd_deg,m2_cmd_deg\n101,-43.1,-37.7\n102,-33.6,-54.2\n")
    assert run("import", SA, "--log", str(tmp_path / "ids.csv"), "-o", str(tmp_path / "m.csv")) == 2
    assert "ids.csv" in capsys.readouterr().err          # which log has no such pose: both files named
    assert run("import", SA, "--log", LOG, "-o", str(tmp_path / "m.csv"), "--columns", "x=X") == 2
    assert "--columns" in capsys.readouterr().err
    assert run("import", SA, "--log", LOG, "-o", str(tmp_path / "m.csv"), "--names", "(?P<pose>P") == 2


def test_twin_export_in_inches_calibrates_as_native(tmp_path):
    """Acceptance: SA layout, inches, two blocked points: identify gives the native CSV's accuracy."""
    twin = Twin(PAPER_TABLE2)
    meas = run_campaign(twin, plan_campaign(24, 60, seed=11), LaserTracker(0.01, np.random.default_rng(12)))
    write_measurements(tmp_path / "native.csv", meas)
    write_sa_export(tmp_path / "sa.txt", meas, units="in", blocked={(3, 1), (17, 2)}, reshoot={(5, 0)},
                    separator=",")
    write_log(tmp_path / "log.csv", meas)
    assert run("import", str(tmp_path / "sa.txt"), "--log", str(tmp_path / "log.csv"),
               "-o", str(tmp_path / "imported.csv")) == 0
    imported = read_measurements(tmp_path / "imported.csv")
    assert (~imported.visible).sum() == 2 and np.isnan(imported.targets[3, 1]).all()
    assert np.nanmax(np.abs(imported.targets - meas.targets)) < 3e-5       # 1e-6 in: 2.5e-5 mm
    native = identify(read_measurements(tmp_path / "native.csv"))
    cal = identify(imported)
    keys = sorted(set(native.params) | set(cal.params))
    err = lambda c: np.array([c.params.get(k, 0.0) - PAPER_TABLE2.get(k, 0.0) for k in keys])  # noqa: E731
    std = np.array([native.document["uncertainty"].get(k, 1.0) for k in keys])
    # same accuracy: the two fits differ by far less than their uncertainty (two of 72 points missing)
    assert np.max(np.abs(err(cal) - err(native)) / std) < 0.5
    ratio = np.sqrt(np.mean((err(cal) / std) ** 2)) / np.sqrt(np.mean((err(native) / std) ** 2))
    assert 0.8 < ratio < 1.25


def test_group_target_names_space_separated(tmp_path):
    meas = run_campaign(Twin(), plan_campaign(5, 40, seed=4), LaserTracker(0.01, np.random.default_rng(5)))
    write_sa_export(tmp_path / "gt.txt", meas, units="mm", names="Group Target", stamps=False, blocked={(2, 0)})
    write_log(tmp_path / "log.csv", meas)
    res = join(read_sa_ascii(tmp_path / "gt.txt"), read_controller_log(tmp_path / "log.csv"))
    assert res.warnings == [] and res.blocked == ["pose 3 T1"] and res.frame == "base"
    assert np.allclose(res.meas.targets[np.isfinite(res.meas.targets)], meas.targets[np.isfinite(res.meas.targets)],
                       atol=5e-7)


def test_machine_folder_campaign_imports_and_identifies_as_native(tmp_path, capsys):
    """``pmcal --machine DIR import`` on a copy of the Delta: its twin campaign written as SA ASCII in inches
    (nests named by their machine.toml site names, one point blocked, one re-shot) and a controller log with
    the machine's three motor columns joins back to the campaign within the export's rounding (6 decimals
    of an inch: 1.3e-5 mm), and identifies as the native file (with the same point blanked) does."""
    from pmcal.io_chain import read_measurements as read_chain, write_measurements as write_chain
    from pmcal.machines import Machine
    from pmcal.mjcf import machine_dir

    folder = tmp_path / "my_delta"
    shutil.copytree(machine_dir("delta_3dof"), folder)
    spec = Machine.from_folder(folder).spec
    native = tmp_path / "native.csv"
    argv = ["--quiet", "--machine", str(folder)]
    assert run(*argv, "twin", "measure", "--poses", "24", "--seed", "4", "-o", str(native)) == 0
    meas = read_chain(native, spec)
    write_sa_export(tmp_path / "t.txt", meas, units="in", frame="DELTA::Base", blocked=[(3, 1)], reshoot=[(5, 2)],
                    collection="DELTA", targets=list(spec.targets))
    write_log(tmp_path / "log.csv", meas, motor_columns=spec.motor_columns)
    out = tmp_path / "m.csv"
    capsys.readouterr()
    assert run("--machine", str(folder), "import", str(tmp_path / "t.txt"), "--log", str(tmp_path / "log.csv"),
               "-o", str(out)) == 0
    err = capsys.readouterr().err
    assert "measured again" in err and "not in the machine's base frame" not in err
    got = read_chain(out, spec)
    assert len(got) == 24 and np.isnan(got.targets[3, 1]).all()
    ok = np.isfinite(got.targets)
    assert np.abs(got.targets[ok] - meas.targets[ok]).max() < 1.3e-5
    assert np.abs(got.commands - meas.commands).max() < 1e-6
    meas.targets[3, 1] = np.nan                 # the native file with the point the export blocked
    write_chain(native, spec, meas)
    for name, path in (("native", native), ("imported", out)):
        assert run(*argv, "identify", str(path), "-o", str(tmp_path / f"{name}.json")) == 0
    # the two fits are compared by what they predict (the nests at fresh poses): a base set is chosen per
    # campaign by pivoted QR and may name other representatives of the same combinations
    mach = Machine.from_folder(folder)
    a, b = (json.loads((tmp_path / f"{n}.json").read_text())["params"] for n in ("native", "imported"))
    cmd = mach.twin.sample_commands(30, np.random.default_rng(2))
    d = np.linalg.norm(mach.twin.targets(cmd, a) - mach.twin.targets(cmd, b), axis=2)
    assert d.max() < 2e-4           # mm: the export's rounding (1.3e-5 mm per coordinate) through the fit


def test_machine_folder_log_command_outside_the_motor_range_names_the_log(tmp_path, capsys):
    """Was imported (1e300 deg written to the output), and identify then blamed the output file."""
    from pmcal.mjcf import machine_dir

    folder = tmp_path / "my_delta"
    shutil.copytree(machine_dir("delta_3dof"), folder)
    (tmp_path / "t.txt").write_text("DELTA P001 nest1 179.2 3.3 -816.1\nDELTA P001 nest2 104.3 46.8 -816.3\n")
    (tmp_path / "log.csv").write_text("pose_id,m1_cmd_deg,m2_cmd_deg,m3_cmd_deg\n1,12.9,31.1,32.0\n2,1e300,31.1,32.0\n")
    assert run("--machine", str(folder), "import", str(tmp_path / "t.txt"), "--log", str(tmp_path / "log.csv"),
               "-o", str(tmp_path / "m.csv")) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "log.csv, row 2, field 'm1_cmd_deg'" in err[0], err
    assert not (tmp_path / "m.csv").exists()


def test_machine_folder_log_whose_time_goes_backwards_is_refused(tmp_path, capsys):
    """A controller log whose time_s decreases was imported (the time join and drift then read a wrong order):
    refused naming the log, the row and time_s, nothing written; equal times (a clock of 1 s steps) are kept."""
    from pmcal.mjcf import machine_dir

    folder = tmp_path / "my_delta"
    shutil.copytree(machine_dir("delta_3dof"), folder)
    (tmp_path / "t.txt").write_text("DELTA P001 nest1 179.2 3.3 -816.1\nDELTA P001 nest2 104.3 46.8 -816.3\n")
    argv = ["--machine", str(folder), "import", str(tmp_path / "t.txt"), "--log", str(tmp_path / "log.csv"), "-o"]
    log = "pose_id,m1_cmd_deg,m2_cmd_deg,m3_cmd_deg,time_s\n1,12.9,31.1,32.0,{}\n2,12.9,31.1,32.0,{}\n"
    (tmp_path / "log.csv").write_text(log.format(60.0, 30.0))
    capsys.readouterr()
    assert run(*argv, str(tmp_path / "m.csv")) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "log.csv, row 2, field 'time_s': time goes backwards" in err[0], err
    assert not (tmp_path / "m.csv").exists()
    (tmp_path / "log.csv").write_text(log.format(30.0, 30.0))
    assert run(*argv, str(tmp_path / "m.csv")) == 0


def test_machine_folder_nest_distances_are_checked_as_ocpm_2dofs(tmp_path, capsys):
    """The nests of one pose 1.5 times as far apart as the Delta's (a wrong point, a unit slip) were imported;
    ocpm_2dof's import refuses that. Now the folder's import does the same check (the same code and limit),
    naming the export and the pose; nothing is written."""
    from pmcal.io_chain import read_measurements as read_chain
    from pmcal.machines import Machine
    from pmcal.mjcf import machine_dir

    folder = tmp_path / "my_delta"
    shutil.copytree(machine_dir("delta_3dof"), folder)
    spec = Machine.from_folder(folder).spec
    assert run("--quiet", "--machine", str(folder), "twin", "measure", "--poses", "6", "-o",
               str(tmp_path / "n.csv")) == 0
    meas = read_chain(tmp_path / "n.csv", spec)
    centre = meas.targets[2].mean(axis=0)
    meas.targets[2] = centre + 1.5 * (meas.targets[2] - centre)
    write_sa_export(tmp_path / "t.txt", meas, units="mm", frame="Base", targets=list(spec.targets))
    write_log(tmp_path / "log.csv", meas, motor_columns=spec.motor_columns)
    capsys.readouterr()
    assert run("--machine", str(folder), "import", str(tmp_path / "t.txt"), "--log", str(tmp_path / "log.csv"),
               "-o", str(tmp_path / "m.csv")) == 2
    err = capsys.readouterr().err.strip().splitlines()
    pose = int("".join(c for c in meas.pose_id[2] if c.isdigit()))
    assert len(err) == 1 and f"{tmp_path / 't.txt'}: pose {pose}: targets t1 and t2 are" in err[0], err
    assert "the platform has them" in err[0] and "check the export's unit" in err[0], err
    assert not (tmp_path / "m.csv").exists()


def test_machine_folder_points_off_the_base_frame_are_said(tmp_path, capsys):
    """Points 120 mm away from where the Delta's commands put its nests (a tracker frame): imported, with
    one warning saying so and what to do."""
    from pmcal.io_chain import read_measurements as read_chain
    from pmcal.machines import Machine
    from pmcal.mjcf import machine_dir

    folder = tmp_path / "my_delta"
    shutil.copytree(machine_dir("delta_3dof"), folder)
    spec = Machine.from_folder(folder).spec
    assert run("--quiet", "--machine", str(folder), "twin", "measure", "--poses", "6", "-o", str(tmp_path / "n.csv")) == 0
    meas = read_chain(tmp_path / "n.csv", spec)
    meas.targets += [120.0, 0.0, 0.0]
    write_sa_export(tmp_path / "t.txt", meas, units="mm", frame="Base", targets=list(spec.targets))
    write_log(tmp_path / "log.csv", meas, motor_columns=spec.motor_columns)
    capsys.readouterr()
    assert run("--machine", str(folder), "import", str(tmp_path / "t.txt"), "--log", str(tmp_path / "log.csv"),
               "-o", str(tmp_path / "m.csv")) == 0
    err = capsys.readouterr().err
    found = re.search(r"not in the machine's base frame \(the nests are (\d+) mm \(median\)", " ".join(err.split()))
    assert found and 110 <= int(found[1]) <= 130, err        # 120 mm shift, the machine's errors a few mm
    assert "transform them into the base frame" in err


def test_identifying_a_folder_machine_loads_no_seeded_machines_code(tmp_path):
    """``pmcal --machine delta_3dof identify`` runs on the generic core alone: no module of ocpm_2dof's or
    planar_2dof's wings (their mechanism, twin, identification, file formats, calibration) is imported."""
    import subprocess
    import sys

    from pmcal import chain
    from pmcal.io_chain import write_measurements
    from pmcal.machines import Machine

    machine = Machine.builtin("delta_3dof")
    meas, _ = chain.campaign(machine, 24, seed=1)
    write_measurements(tmp_path / "m.csv", machine.spec, meas)
    code = ("import sys\nfrom pmcal.cli import main\n"
            f"rc = main(['--quiet', '--machine', 'delta_3dof', 'identify', {str(tmp_path / 'm.csv')!r}, '-o', "
            f"{str(tmp_path / 'p.json')!r}])\n"
            "print(rc)\nprint(' '.join(m for m in sys.modules if m.startswith('pmcal')))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                         env={**__import__("os").environ, "MUJOCO_GL": "egl"})
    rc, loaded = out.stdout.strip().splitlines()[-2:]
    assert rc == "0", out.stderr
    from layering import wing_of

    wings = [m for m in loaded.split() if wing_of(m)]
    assert not wings, wings
