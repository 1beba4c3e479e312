"""A machine of one's own through the command line: ``--machine DIR`` on copies of the built-in machine
folders placed outside ``mjcf/`` (as a user would), its files, and one line + exit 2 for every bad folder
or file.

Run in-process through :func:`pmcal.cli.main`. The acceptance chain (measure, identify, targets,
compensate) is checked against the twin's own truth in :mod:`tests.test_machine_folder_chain`.
"""

import argparse
import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from pmcal.cli import _named_subparsers, build_parser, main
from pmcal.mjcf import machine_dir

NEW_MACHINES = [m for m in ("delta_3dof", "hexapod_6dof") if (machine_dir(m) / "machine.toml").is_file()]


def run(capsys, *argv) -> tuple[int, str, str]:
    capsys.readouterr()
    status = main([str(a) for a in argv])
    cap = capsys.readouterr()
    assert "Traceback" not in cap.err
    return status, cap.out, cap.err


def one_line_error(capsys, *argv, says=(), status=2) -> str:
    got, _, err = run(capsys, *argv)
    assert got == status, err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    for text in ([says] if isinstance(says, str) else says):
        assert text in lines[0], lines[0]
    return lines[0]


def copy_machine(src: str, dest) -> Path:
    """A copy of a built-in machine folder under another folder name (the TOML's name kept)."""
    out = dest / f"my_{src}"
    shutil.copytree(machine_dir(src), out)
    return out


@pytest.fixture(scope="module")
def delta(tmp_path_factory):
    """A copy of the Delta's folder outside mjcf/, a campaign, targets and a parameters file on it."""
    d = tmp_path_factory.mktemp("folder")
    folder = copy_machine("delta_3dof", d)
    for argv in (["twin", "measure", "--poses", "12", "--seed", "3", "-o", d / "m.csv"],
                 ["targets", "--count", "5", "-o", d / "tg.csv"]):
        assert main(["--quiet", "--machine", str(folder), *map(str, argv)]) == 0, argv
    (d / "nominal.json").write_text(json.dumps({"mechanism": "delta_3dof", "params": {}}))
    return folder, d


# ---------------------------------------------------------------- the parser, built from data
@pytest.mark.parametrize("machine", NEW_MACHINES)
def test_every_argument_of_a_folder_machine_has_help(machine, tmp_path):
    for value in (machine, str(copy_machine(machine, tmp_path))):
        parser = build_parser(value)
        missing = [f"{name} {a.dest}" for name, sp in _named_subparsers(parser) for a in sp._actions
                   if not isinstance(a, (argparse._HelpAction, argparse._SubParsersAction)) and not a.help]
        assert not missing


def test_help_speaks_of_the_machines_own_columns_and_defaults(capsys, tmp_path):
    folder = copy_machine("delta_3dof", tmp_path)
    with pytest.raises(SystemExit):
        main(["--machine", str(folder), "compensate", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert "x_mm, y_mm, z_mm" in out and "m1_deg, m2_deg, m3_deg" in out and "(machine delta_3dof)" in out
    with pytest.raises(SystemExit):
        main(["--machine", str(folder), "twin", "measure", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert "default 48" in out and "0.01 mm" in out and "--payload" not in out
    with pytest.raises(SystemExit):
        main(["--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert "delta_3dof" in out and "NAME|DIR" in out
    with pytest.raises(SystemExit):
        main(["--machine", str(folder), "--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert "loop twin in the loop: the task site's position error" in out and "the whole job on delta_3dof" in out


def test_options_a_folder_machine_does_not_have_are_refused(capsys, delta):
    folder, d = delta
    with pytest.raises(SystemExit) as exc:
        main(["--machine", str(folder), "twin", "measure", "--payload", "0,10", "-o", str(d / "x.csv")])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and "--payload is not an option of machine" in err and not (d / "x.csv").exists()


@pytest.mark.parametrize("value, says", [
    ("no_such_machine", "neither a built-in name"),
    ("{tmp}/missing_folder", "neither a built-in name"),
    ("{tmp}/a_file.txt", "is a file"),
    ("{tmp}", "machine.toml"),
])
def test_a_machine_that_is_no_machine_folder_is_one_line(capsys, tmp_path, value, says):
    (tmp_path / "a_file.txt").write_text("x")
    one_line_error(capsys, "--machine", value.format(tmp=tmp_path), "targets", "-o", tmp_path / "t.csv",
                   says=says)
    assert not (tmp_path / "t.csv").exists()


# ---------------------------------------------------------------- bad machine folders
def _break(folder, file, old, new):
    p = folder / file
    text = p.read_text()
    assert old in text, old
    p.write_text(text.replace(old, new))
    return folder


def _measure(folder, measure):
    return _break(folder, "machine.toml", 'measure = "position"', f'measure = "{measure}"')


def _drop_equalities(path):
    path.write_text(re.sub(r"<equality>.*?</equality>", "", path.read_text(), flags=re.S))


BAD_FOLDERS = {
    "missing TOML": (lambda f: (f / "machine.toml").unlink(), ["machine.toml"]),
    "bad key": (lambda f: _break(f, "machine.toml", "sigma_mm = 0.01", "sigma_mm = 0.01\nsigmaa = 2"),
                ["machine.toml", "tracker.sigmaa", "unknown key"]),
    "unknown joint": (lambda f: _break(f, "machine.toml", 'joint = "arm2_motor"', 'joint = "hip2"'),
                      ["machine.toml", "motors[2].joint", "hip2"]),
    "no equality constraints": (lambda f: _drop_equalities(f / "delta_3dof.xml"),
                                ["delta_3dof.xml", "no loop to close"]),
    "MJCF that MuJoCo rejects": (lambda f: _break(f, "delta_3dof.xml", "<joint ", '<joint foo="1" '),
                                 ["delta_3dof.xml", "foo"]),
    # onshape-to-robot's sdf option: the pip wheel has no sdflib, MuJoCo's parser stops at the declaration
    "a plugin this MuJoCo lacks": (lambda f: _break(f, "delta_3dof.xml", '<mujoco model="delta_3dof">',
                                                    '<mujoco model="delta_3dof"><extension><plugin '
                                                    'plugin="mujoco.sdf.sdflib"><instance name="sdf"/></plugin>'
                                                    '</extension>'),
                                   ["delta_3dof.xml", "mujoco.sdf.sdflib", 'type="mesh"', "no collision"]),
    # was "field 'motors[1].joint': 'arm1_motor' is not a joint of delta_3dof.xml (joints: )", blaming the TOML
    "a URDF in place of the MJCF": (lambda f: (f / "delta_3dof.xml").write_text('<robot name="delta"/>'),
                                    ["delta_3dof.xml", "<robot>", "not <mujoco>"]),
    # a user's input, not a bug (was exit 1, 'RuntimeError: ... a bug: please report it')
    "motor ranges no pose of the workspace meets": (
        lambda f: _break(f, "machine.toml", "range = [-35.0, 80.0]", "range = [0.0, 1.0]"),
        ["machine.toml", "field 'workspace'", "outside its range [0, 1]", "[[motors]] range"]),
    # was "machine.toml, field 'machine.model': model file not found: .../parts.xml", blaming the TOML
    "an include of a missing file": (lambda f: _break(f, "delta_3dof.xml", '<mujoco model="delta_3dof">',
                                                      '<mujoco model="delta_3dof"><include file="parts.xml"/>'),
                                     ["delta_3dof.xml: cannot read", "includes file='parts.xml', which is no file"]),
    # was "MuJoCo cannot compile the model: SVD did not converge", naming neither the keyframe nor the NaN
    "a NaN in the home keyframe": (lambda f: _break(f, "delta_3dof.xml", 'home" qpos="0 ', 'home" qpos="nan '),
                                   ["delta_3dof.xml", "field 'keyframe'", "'home': qpos value 1 of", "is nan"]),
    # sites on the wrong part: was a demo reporting 0 mm before and after (task site on the base), a nest that
    # reads the base, a task frame taken at home from a moving part (then a minute to a [workspace] line)
    "a task site on the fixed base": (lambda f: _break(f, "machine.toml", 'site = "tcp"', 'site = "base_origin"'),
                                      ["machine.toml", "field 'task.site'", "'base_origin' is on the fixed base"]),
    "a nest on the fixed base": (lambda f: _break(f, "machine.toml", 'targets = ["nest1"', 'targets = ["base_origin"'),
                                 ["machine.toml", "field 'tracker.targets[1]'", "'base_origin' is on the fixed base"]),
    "a task frame on a moving part": (
        lambda f: _break(f, "machine.toml", 'site = "tcp"', 'site = "tcp"\nframe = "nest2"'),
        ["machine.toml", "field 'task.frame'", "'nest2' is on body platform, which moves"]),
    "a pose fit over two parts": (
        lambda f: _measure(_break(f, "machine.toml", '"nest3"]', '"rod1a_tip"]'), "pose"),
        ["machine.toml", "field 'tracker.targets'", "'rod1a_tip' on body rod1a"]),
    "a scale on one part": (lambda f: _measure(_break(f, "machine.toml", ', "nest3"]', ']'), "distance"),
                            ["machine.toml", "field 'tracker.targets'", "on one rigid part (body platform)"]),
    # was 6.5 minutes of continuation walks per campaign (each target hundreds of box sizes from home)
    "a workspace in metres": (lambda f: _break(f, "machine.toml", "z_mm = [-950.0, -650.0]", "z_mm = [-0.95, -0.65]"),
                              ["machine.toml", "field 'workspace'", "box sizes", "in metres?"]),
}


@pytest.mark.parametrize("case", BAD_FOLDERS)
def test_a_bad_machine_folder_is_one_line_naming_file_and_key(capsys, tmp_path, case):
    folder = copy_machine("delta_3dof", tmp_path)
    spoil, says = BAD_FOLDERS[case]
    spoil(folder)
    one_line_error(capsys, "--machine", folder, "targets", "-o", tmp_path / "t.csv", says=says)
    assert not (tmp_path / "t.csv").exists()


def test_errors_too_large_for_the_workspace_point_at_their_sizes(capsys, tmp_path):
    # 10 deg frame errors: the erroneous Delta assembles none of the drawn poses on the nominal branch; the one
    # line says where the sizes come from, not only that poses are missing
    folder = copy_machine("delta_3dof", tmp_path)
    _break(folder, "machine.toml", "angle_deg = 0.1", "angle_deg = 10.0")
    one_line_error(capsys, "--machine", folder, "twin", "measure", "--poses", "12", "-o", tmp_path / "m.csv",
                   status=1, says=["assembles too few", "[errors] sizes in machine.toml"])
    assert not (tmp_path / "m.csv").exists()


@pytest.mark.parametrize("old, new, says", [
    ("angle_deg = 0.1", "angle_deg = 10.0", "[errors] sizes in machine.toml"),
    ('joint = "arm1_motor"', 'joint = "arm1_motor"\nsigma = 10.0', "[[motors]] sigma"),
])
def test_demo_with_errors_too_large_points_at_their_sizes(capsys, tmp_path, old, new, says):
    # the demo's planned poses: the line said "its errors are too large for this workspace" without saying where
    # their sizes come from (10 deg frame errors, or a 10 deg motion error: the largest allowed); and nothing of
    # the demo's folder is written
    folder = copy_machine("delta_3dof", tmp_path)
    _break(folder, "machine.toml", old, new)
    one_line_error(capsys, "--machine", folder, "demo", "--out", tmp_path / "demo", status=1,
                   says=["planned poses cannot be assembled", says])
    assert not (tmp_path / "demo").exists()


def test_a_workspace_off_the_machine_stops_after_the_first_draws(capsys, tmp_path):
    # the hexapod's legs reach x = 5 m, 10 times past their range: was 20 rounds of draws before the one line
    # (demo's 288 poses: 11520 solves, minutes); now it stops once 200 drawn poses reached none
    folder = copy_machine("hexapod_6dof", tmp_path)
    _break(folder, "machine.toml", "x_mm = [-40.0, 40.0]", "x_mm = [5000.0, 6000.0]")
    one_line_error(capsys, "--machine", folder, "targets", "-o", tmp_path / "t.csv",
                   says=["machine.toml", "field 'workspace'", "only 0 of 12", "(216 drawn;", "outside its range"])
    assert not (tmp_path / "t.csv").exists()


@pytest.mark.parametrize("command", [["demo", "--out", "out"], ["twin", "plan", "--poses", "12", "-o", "out.csv"]])
def test_errors_that_select_none_are_one_line(capsys, tmp_path, command):
    # was exit 1, "ValueError: cannot reshape array of size 0 ... (a bug: please report it)" from demo and
    # "field '--poses': cannot reshape array ..." from twin plan
    folder = copy_machine("delta_3dof", tmp_path)
    _break(_break(folder, "machine.toml", 'frames = "all"', "frames = []"), "machine.toml", "motor_zero = true",
           "motor_zero = false")
    one_line_error(capsys, "--machine", folder, *command[:-1], tmp_path / command[-1],
                   says=["machine.toml", "field 'errors'", "leaves no error to identify"])
    assert sorted(p.name for p in tmp_path.iterdir()) == [folder.name]


def test_a_copy_of_a_seeded_machine_says_to_use_its_name(capsys, tmp_path):
    folder = copy_machine("ocpm_2dof", tmp_path)
    one_line_error(capsys, "--machine", folder, "targets", "-o", tmp_path / "t.csv",
                   says=["machine.toml", "machine.kind", "--machine ocpm_2dof"])
    assert not (tmp_path / "t.csv").exists()


# ---------------------------------------------------------------- its files
def test_files_have_the_machines_columns(delta):
    folder, d = delta
    lines = [x for x in (d / "m.csv").read_text().splitlines() if not x.startswith("#")]
    assert lines[0].split(",") == (["pose_id", "m1_cmd_deg", "m2_cmd_deg", "m3_cmd_deg"]
                                   + [f"t{k}_{a}" for k in (1, 2, 3) for a in "xyz"] + ["time_s"])
    assert len(lines) == 13
    lines = [x for x in (d / "tg.csv").read_text().splitlines() if not x.startswith("#")]
    assert lines[0] == "x_mm,y_mm,z_mm" and len(lines) == 6


def _edit_csv(src, dest, edit):
    comments = [x for x in src.read_text().splitlines() if x.startswith("#")]
    lines = [x.split(",") for x in src.read_text().splitlines() if not x.startswith("#")]
    edit(lines)
    dest.write_text("\n".join(comments + [",".join(r) for r in lines]) + "\n")
    return dest


def _rename(old, new):
    def edit(lines):
        lines[0][lines[0].index(old)] = new
    return edit


def _cell(row, column, value):
    def edit(lines):
        lines[row][lines[0].index(column)] = value
    return edit


def _scale(columns, factor):
    def edit(lines):
        for c in columns:
            k = lines[0].index(c)
            for r in lines[1:]:
                r[k] = repr(float(r[k]) * factor)
    return edit


def _add_column(name, value):
    def edit(lines):
        lines[0].append(name)
        for r in lines[1:]:
            r.append(value)
    return edit


BAD_MEASUREMENTS = {
    "unknown column": (_add_column("speed", "1"), ["field 'speed'", "unknown column"]),
    "a fourth motor": (_add_column("m4_cmd_deg", "1"), ["field 'm4_cmd_deg'", "3 motors"]),
    "a fourth target": (_add_column("t4_x", "1"), ["field 't4_x'", "3 tracker targets"]),
    "motor in the wrong unit": (_rename("m2_cmd_deg", "m2_cmd_mm"), ["field 'm2_cmd_mm'", "m2_cmd_deg"]),
    "missing column": (lambda lines: [r.pop(lines[0].index("t2_y")) for r in lines[::-1]],
                       ["field 't2_y'", "missing column"]),
    "not a number": (_cell(4, "m3_cmd_deg", "abc"), ["row 4", "field 'm3_cmd_deg'"]),
    "not finite": (_cell(5, "t1_z", "inf"), ["row 5", "field 't1_z'", "not finite"]),
    "radians": (_scale(["m1_cmd_deg", "m2_cmd_deg", "m3_cmd_deg"], np.pi / 180.0), ["row 1", "radians"]),
    "out of range": (_cell(2, "m1_cmd_deg", "95"), ["row 2", "field 'm1_cmd_deg'", "range -35..80 deg"]),
    "metres": (_scale([f"t{k}_{a}" for k in (1, 2, 3) for a in "xyz"], 1e-3),
               ["row 1", "field 't1_x'", "metres"]),
    "half-blocked target": (_cell(3, "t2_y", ""), ["row 3", "field 't2_y'", "half empty"]),
    "duplicate id": (_cell(2, "pose_id", "P1"), ["row 2", "field 'pose_id'", "duplicate"]),
    "temperature in kelvin": (_add_column("temp_c", "293.15"), ["row 1", "field 'temp_c'", "kelvin"]),
}


@pytest.mark.parametrize("case", BAD_MEASUREMENTS)
def test_a_bad_measurement_file_is_one_line_naming_row_and_field(capsys, delta, tmp_path, case):
    folder, d = delta
    edit, says = BAD_MEASUREMENTS[case]
    bad = _edit_csv(d / "m.csv", tmp_path / "bad.csv", edit)
    line = one_line_error(capsys, "--machine", folder, "evaluate", d / "nominal.json", bad, "--json",
                          tmp_path / "e.json", says=says)
    assert str(bad) in line and not (tmp_path / "e.json").exists()


BAD_TARGETS = {
    "outside the workspace": (_cell(2, "z_mm", "-2000"), ["row 2", "field 'z_mm'", "workspace"]),
    "a task column of another machine": (_rename("z_mm", "theta_deg"), ["field 'theta_deg'"]),
    "missing column": (lambda lines: [r.pop(lines[0].index("y_mm")) for r in lines[::-1]], ["field 'y_mm'"]),
}


@pytest.mark.parametrize("case", BAD_TARGETS)
def test_a_bad_targets_file_is_one_line(capsys, delta, tmp_path, case):
    folder, d = delta
    edit, says = BAD_TARGETS[case]
    bad = _edit_csv(d / "tg.csv", tmp_path / "bad.csv", edit)
    one_line_error(capsys, "--machine", folder, "compensate", d / "nominal.json", "--targets", bad,
                   "-o", tmp_path / "s.csv", says=says)
    assert not (tmp_path / "s.csv").exists()


BAD_PARAMS = {
    "another machine": ({"mechanism": "ocpm_2dof", "params": {}}, ["field 'mechanism'", "ocpm_2dof"]),
    "unknown key": ({"mechanism": "delta_3dof", "params": {"L1.dbx": 0.1}}, ["field 'params.L1.dbx'"]),
    "implausible": ({"mechanism": "delta_3dof", "params": {"m1.dzero": 45.0}},
                    ["field 'params.m1.dzero'", "implausible"]),
    "not a number": ({"mechanism": "delta_3dof", "params": {"base.dx": "1"}}, ["field 'params.base.dx'"]),
    "nested 100 000 deep": ("[" * 100_000 + "]" * 100_000, ["p.json", "nest"]),      # was a RecursionError
}


@pytest.mark.parametrize("case", BAD_PARAMS)
def test_a_bad_parameters_file_is_one_line(capsys, delta, tmp_path, case):
    folder, d = delta
    doc, says = BAD_PARAMS[case]
    p = tmp_path / "p.json"
    p.write_text(doc if isinstance(doc, str) else json.dumps(doc))
    one_line_error(capsys, "--machine", folder, "compensate", p, "--targets", d / "tg.csv", "-o",
                   tmp_path / "s.csv", says=says)
    assert not (tmp_path / "s.csv").exists()


def test_a_table_is_refused_with_what_the_machine_gets_instead(capsys, delta, tmp_path):
    """The hexapod's six task coordinates are more than a table holds: one line, and what it gets instead."""
    _, d = delta
    hexapod = copy_machine("hexapod_6dof", tmp_path)
    line = one_line_error(capsys, "--machine", hexapod, "compensate", d / "nominal.json", "--table",
                          tmp_path / "t.json", says=["--table", "6 task coordinates", "offline compensation of target lists"])
    assert "--targets" in line and not (tmp_path / "t.json").exists()


def test_a_delta_table_over_its_table_axes(capsys, delta, tmp_path):
    """The Delta's [table] grid: a format-4 table of 3 axes and 3 motors, the nominal machine's commands."""
    from pmcal.bridge.comptable import CompTable

    folder, d = delta
    status, out, err = run(capsys, "--machine", folder, "compensate", d / "nominal.json", "--table",
                           tmp_path / "t.json", "--grid", "7,7,4", "--table-version", "5")
    assert status == 0, err
    assert "7x7x4 nodes over x_mm, y_mm, z_mm, 3 motors" in out and f"wrote {tmp_path / 't.csv'}" in out
    t = CompTable.load(tmp_path / "t.csv")
    assert (t.shape, t.n_motors, t.version, [m.column for m in t.motors]) == ((7, 7, 4), 3, 5,
                                                                              ["m1_deg", "m2_deg", "m3_deg"])
    one_line_error(capsys, "--machine", folder, "compensate", d / "nominal.json", "--table", tmp_path / "u.json",
                   "--grid", "3,3", says="--grid")
    big = copy_machine("delta_3dof", tmp_path)           # nodes from machine.toml, not --grid: the line says so
    _break(big, "machine.toml", "nodes = [13, 13, 9]", "nodes = [1000, 1000, 1000]")
    one_line_error(capsys, "--machine", big, "compensate", d / "nominal.json", "--table", tmp_path / "u.json",
                   says=[str(big / "machine.toml"), "field 'table.nodes'", "more than the PLC's 20000"])
    assert not (tmp_path / "u.json").exists()


def test_a_delta_table_holds_corrections_to_the_controllers_ik(capsys, delta, tmp_path):
    """By default the table holds m_identified - m_nominal (nReference 2): a zero offset of 0.2 deg on motor 1
    is a correction of exactly -0.2 deg of m1 at every node (the twin's convention: command = joint angle -
    dzero) and 0 on the others; --absolute writes the commands, nominal + correction; [table] bounds them;
    the commands' max_step applies to absolute tables only."""
    from pmcal.bridge.comptable import CompTable
    from pmcal.machines import Machine

    folder, d = delta
    (tmp_path / "p.json").write_text(json.dumps({"mechanism": "delta_3dof", "params": {"m1.dzero": 0.2}}))
    grid = ["--grid", "5,5,4", "--table-version", "6"]
    status, out, err = run(capsys, "--machine", folder, "compensate", tmp_path / "p.json", "--table",
                           tmp_path / "c.json", *grid)
    assert status == 0 and "corrections to add to the controller's nominal IK (nReference 2)" in out, err
    status, out, err = run(capsys, "--machine", folder, "compensate", tmp_path / "p.json", "--table",
                           tmp_path / "a.json", *grid, "--absolute")
    assert status == 0 and "absolute motor commands" in out, err
    c, a = CompTable.load(tmp_path / "c.csv"), CompTable.load(tmp_path / "a.json")
    assert (c.reference_code, a.reference_code) == (2, 0)
    assert c.columns()[3:] == ("dm1_deg", "dm2_deg", "dm3_deg")
    assert [(m.min, m.max, m.max_step) for m in c.motors] == [(-1.0, 1.0, 0.25)] * 3      # [table] defaults
    np.testing.assert_allclose(c.values[..., 0], -0.2, atol=1e-7)
    np.testing.assert_allclose(c.values[..., 1:], 0.0, atol=1e-7)
    twin = Machine.from_folder(folder).twin
    nominal = twin.inverse(c.nodes().reshape(-1, 3), None).reshape(c.values.shape)
    np.testing.assert_allclose(a.values, nominal + c.values, rtol=0, atol=1e-9)
    # a coarse grid: the commands step more than [table] max_step between nodes, the corrections do not
    coarse = ["--grid", "3,3,2", "--table-version", "6"]
    assert run(capsys, "--machine", folder, "compensate", tmp_path / "p.json", "--table", tmp_path / "k.json",
               *coarse)[0] == 0
    one_line_error(capsys, "--machine", folder, "compensate", tmp_path / "p.json", "--table", tmp_path / "k2.json",
                   *coarse, "--absolute", says=["exceeds max_step 15 deg"])

    toml = folder / "machine.toml"
    text = toml.read_text()

    def table_key(key, value):                  # machine.toml with [table] key = value (the Delta sets all)
        assert re.search(rf"^{key} = ", text, flags=re.M)
        toml.write_text(re.sub(rf"^{key} = [^#\n]*", f"{key} = {value} ", text, flags=re.M))
    try:
        table_key("max_correction", "0.1")
        line = one_line_error(capsys, "--machine", folder, "compensate", tmp_path / "p.json", "--table",
                              tmp_path / "x.json", *grid, says=["table node 1", "dm1_deg", "max_correction 0.1", "machine.toml"])
        assert "correction bounds" in line and not (tmp_path / "x.json").exists()
        table_key("max_correction", "6")
        one_line_error(capsys, "--machine", folder, "compensate", tmp_path / "p.json", "--table", tmp_path / "x.json",
                       *grid, says=["table.max_correction", "CORRECTION_ABS_MAX 5"])
        table_key("reference", '"nominal_ik"')
        one_line_error(capsys, "--machine", folder, "compensate", tmp_path / "p.json", "--table", tmp_path / "x.json",
                       *grid, says=["table.reference", "controller, none"])
        table_key("reference", '"none"')
        assert run(capsys, "--machine", folder, "compensate", tmp_path / "p.json", "--table", tmp_path / "n.json",
                   *grid)[0] == 0
        assert CompTable.load(tmp_path / "n.json").values.tobytes() == a.values.tobytes()
    finally:
        toml.write_text(text)
    one_line_error(capsys, "--machine", folder, "compensate", tmp_path / "p.json", "--targets", d / "tg.csv",
                   "-o", tmp_path / "s.csv", "--absolute", says="--absolute")


def test_twin_options_of_a_folder_machine(capsys, delta, tmp_path):
    """--errors none --noise 0 at explicit targets: the nominal machine's exact targets (evaluate: 0);
    --errors P.json: that machine; a value that is neither is one line."""
    folder, d = delta
    assert main(["-q", "--machine", str(folder), "twin", "measure", "--targets", str(d / "tg.csv"), "--errors",
                 "none", "--noise", "0", "-o", str(tmp_path / "m0.csv")]) == 0
    status, out, _ = run(capsys, "--machine", folder, "evaluate", d / "nominal.json", tmp_path / "m0.csv")
    assert status == 0 and "rms 0.0000 mm, max 0.0000 mm" in out
    text = (tmp_path / "m0.csv").read_text()
    assert "errors: none" in text and "true errors" not in text and text.count("\nP") == 5
    one_line_error(capsys, "--machine", folder, "twin", "measure", "--errors", "bogus", "-o", tmp_path / "x.csv",
                   says=["--errors", "neither random nor none nor a parameters file"])
    one_line_error(capsys, "--machine", folder, "twin", "measure", "--noise", "-1", "-o", tmp_path / "x.csv",
                   says="--noise")
    assert not (tmp_path / "x.csv").exists()


def test_identify_leaves_out_poses_with_a_blocked_target_and_says_so(capsys, delta, tmp_path):
    folder, d = delta

    def block(lines):
        for row in (2, 5):
            for a in "xyz":
                lines[row][lines[0].index(f"t2_{a}")] = ""
    meas = _edit_csv(d / "m.csv", tmp_path / "blocked.csv", block)
    status, out, err = run(capsys, "--machine", folder, "identify", meas, "-o", tmp_path / "p.json")
    assert status == 0 and "2 pose(s) with a blocked target left out (P2, P5)" in err
    assert json.loads((tmp_path / "p.json").read_text())["n_poses"] == 10


def test_nominal_compensation_reaches_the_targets_on_the_nominal_twin(capsys, delta, tmp_path):
    """With a parameters file of zero errors the setpoints are the nominal inverse kinematics: driving the
    nominal twin with them puts the task site on the targets."""
    from pmcal.io_chain import read_targets
    from pmcal.machines import Machine

    folder, d = delta
    status, out, _ = run(capsys, "--machine", folder, "compensate", d / "nominal.json", "--targets",
                         d / "tg.csv", "-o", tmp_path / "s.csv")
    assert status == 0 and out.strip().endswith(f"wrote {tmp_path / 's.csv'}")
    m = Machine.from_folder(folder)
    rows = [x.split(",") for x in (tmp_path / "s.csv").read_text().splitlines() if not x.startswith("#")]
    assert rows[0] == ["x_mm", "y_mm", "z_mm", "m1_deg", "m2_deg", "m3_deg"]
    values = np.array(rows[1:], float)
    np.testing.assert_allclose(values[:, :3], read_targets(d / "tg.csv", m.spec), atol=1e-6)
    np.testing.assert_allclose(m.twin.forward(values[:, 3:]), values[:, :3], atol=1e-4)


def test_the_api_gives_one_machine_object(tmp_path):
    import pmcal

    folder = copy_machine("delta_3dof", tmp_path)
    m = pmcal.Machine.from_folder(folder)
    assert (m.name, m.folder, m.legacy, m.app_name) == ("delta_3dof", folder.resolve(), False, "pmcal.apps.chain")
    assert m.spec.motor_columns == ("m1_cmd_deg", "m2_cmd_deg", "m3_cmd_deg")
    from pmcal.commands.routing import command_defaults
    assert command_defaults(m) == {"poses": 48, "sigma_mm": m.spec.sigma_mm, "errors": "random"}
    assert m._twin is None                              # compiled on first use only
    assert m.twin is m.twin and "m1.dzero" in m.twin.error_keys
    seeded = pmcal.Machine.builtin("ocpm_2dof")
    assert seeded.legacy and seeded.app_name == "pmcal.apps.ocpm" and command_defaults(seeded)["poses"] == 24
    from pmcal.errors import InputError
    with pytest.raises(InputError, match="dedicated twin"):
        seeded.twin
    with pytest.raises(InputError, match="no built-in machine"):
        pmcal.Machine.builtin(str(folder))


def test_ctrl_c_stops_a_long_campaign_with_130_and_nothing_written(delta, tmp_path):
    """A real SIGINT to a real process while it measures 2000 poses on the twin."""
    import os
    import signal
    import subprocess
    import sys

    folder, _ = delta
    out = tmp_path / "long.csv"
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    proc = subprocess.Popen([sys.executable, "-m", "pmcal.cli", "--verbose", "--machine", str(folder), "twin",
                             "measure", "--poses", "2000", "-o", str(out)], stderr=subprocess.PIPE, text=True,
                            env=env)
    seen = []
    try:
        for line in proc.stderr:
            seen.append(line)
            if "measuring 2000 poses" in line:
                break
        assert proc.poll() is None, f"the campaign ended before the signal: {''.join(seen)}"
        proc.send_signal(signal.SIGINT)
        rest = proc.stderr.read()
        status = proc.wait(timeout=120)
    finally:
        proc.kill()
    said = "".join(seen) + rest          # all of stderr, in the message when this fails
    assert status == 130, said
    assert "interrupted" in rest and "Traceback" not in rest, said
    assert not list(tmp_path.iterdir()), (list(tmp_path.iterdir()), said)


# ---------------------------------------------------------------- twin render of a folder machine
def test_render_of_a_folder_machine_draws_the_pose_it_reaches(delta, capsys):
    """``twin render --pose X,Y,Z`` on the Delta's copy: a PNG of the asked size, different at two poses
    150 mm apart (the platform moved), and one line + exit 2 for a pose with the wrong count or out of
    reach (nothing written)."""
    import matplotlib.image

    folder, d = delta
    images = []
    for pose in ("0,0,-800", "150,0,-800"):
        out = d / f"render_{pose.replace(',', '_')}.png"
        status, _, err = run(capsys, "--quiet", "--machine", folder, "twin", "render", "--pose", pose,
                             "--width", "160", "--height", "120", "-o", out)
        if status == 1 and "offscreen rendering is unavailable" in err:
            pytest.skip(err)
        assert status == 0, err
        assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        images.append(matplotlib.image.imread(out))
    assert images[0].shape[:2] == (120, 160)
    assert np.abs(images[0] - images[1]).max() > 0.2
    for pose, says in (("1,2", "expected 3 comma-separated numbers (x_mm,y_mm,z_mm)"),
                       ("0,0,-100", "no assembly of the chain reaches this target")):
        one_line_error(capsys, "--machine", folder, "twin", "render", "--pose", pose, "-o", d / "bad.png",
                       says=says)
        assert not (d / "bad.png").exists()


# ---------------------------------------------------------------- twin plan of a folder machine
def test_plan_is_measured_and_its_predicted_uncertainty_is_what_identify_reports(delta, capsys):
    """``twin plan`` on the Delta's copy: a plan CSV of the asked size in the machine's motor columns, which
    ``twin measure --plan`` measures pose for pose (same commands, same ids); the plan's predicted posterior
    uncertainty per base error (its design) agrees with the uncertainty ``identify`` reports for the
    campaign measured at it (both are the Fisher information of the same poses plus the same prior, the
    design's at the nominal machine, identify's at the identified one: within 10 %), and it determines the
    errors better than as many random poses (the predicted gain > 1.3 at 24 poses: 1.9 to 2.3 measured)."""
    from pmcal.chain import plan
    from pmcal.io_chain import read_measurements, read_plan
    from pmcal.machines import Machine

    folder, d = delta
    status, out, err = run(capsys, "--machine", folder, "twin", "plan", "--poses", "24", "--seed", "2",
                           "-o", d / "plan.csv")
    assert status == 0, err
    mach = Machine.from_folder(folder)
    ids, commands = read_plan(d / "plan.csv", mach.spec)
    assert len(ids) == 24 and commands.shape == (24, 3)
    gain = float(re.search(r"uncertainties ([\d.]+)x smaller", out)[1])
    assert gain > 1.3
    assert main(["--quiet", "--machine", str(folder), "twin", "measure", "--plan", str(d / "plan.csv"),
                 "--seed", "5", "-o", str(d / "mp.csv")]) == 0
    meas = read_measurements(d / "mp.csv", mach.spec)
    assert meas.pose_id == ids and np.abs(meas.commands - commands).max() < 1e-6
    assert main(["--quiet", "--machine", str(folder), "identify", str(d / "mp.csv"), "-o", str(d / "pp.json")]) == 0
    doc = json.loads((d / "pp.json").read_text())
    design = plan(mach, 24, seed=2)
    assert np.abs(design.commands - commands).max() < 1e-6
    # the two base sets may name other representatives of the weakly seen combinations (the plan's is chosen
    # on its pool of candidates, identify's on the 24 poses): compared by the uncertainty each gives the nests
    # at fresh poses, sqrt(diag(J C J^T)), which does not depend on the representatives at one machine
    held = mach.twin.sample_commands(20, np.random.default_rng(8))

    def nest_std(keys, cov, params=None):
        J = mach.twin.jacobian(held, params, keys).reshape(-1, len(keys))
        return np.sqrt(np.einsum("ij,jk,ik->i", J, np.asarray(cov), J))

    planned = nest_std(design.base, design.covariance)
    # identify's information on the measured poses at the nominal machine is the plan's, to rounding
    base = doc["identifiable"]
    Jb = mach.twin.jacobian(meas.commands, None, base).reshape(-1, len(base)) / doc["sigma_mm"]
    prior = np.asarray(doc["prior_covariance"])
    at_nominal = np.linalg.inv(Jb.T @ Jb + np.linalg.inv(prior))
    assert np.abs(nest_std(base, at_nominal) / planned - 1.0).max() < 1e-6
    # identify reports the posterior at the identified machine (errors of up to 2 mm move its Jacobian): the
    # same within 10 % on every nest (measured: 0.8 % median, 7 % at most; identify realises its base values
    # spread over the errors they regroup, so the representatives named do not matter)
    ratio = nest_std(base, doc["covariance"]) / planned - 1.0
    assert np.abs(ratio).max() < 0.10, ratio
    one_line_error(capsys, "--machine", folder, "twin", "plan", "--poses", "3", "-o", d / "p3.csv",
                   says="3 poses give 27 coordinates for 42 base errors: plan at least 5 poses")


# ---------------------------------------------------------------- demo of a folder machine
def test_demo_of_a_folder_machine(delta, capsys):
    """``pmcal --machine DIR demo`` on the Delta's copy: the folder with every step's file and the report;
    compensation takes the held-out position error from millimetres (the random errors) to the
    identification's prediction: the realised RMS over 60 targets is one draw of the parameter error
    (a few dominant directions, about chi with 5 degrees of freedom), so within 0.3..2 of the predicted RMS."""
    folder, d = delta
    out = d / "demo"
    status, stdout, err = run(capsys, "--machine", folder, "demo", "--out", out, "--seed", "4")
    assert status == 0, err
    assert {p.name for p in out.iterdir()} >= {"report.html", "summary.json", "plan.csv", "measurements.csv",
                                              "params.json", "targets.csv", "setpoints.csv", "table.json"}
    s = json.loads((out / "summary.json").read_text())
    assert s["position_rms_before_mm"] > 1.0                     # errors of 0.5 mm / 0.1 deg over a 1 m machine
    assert 0.3 < s["position_rms_after_mm"] / s["position_rms_predicted_mm"] < 2.0
    assert 0.7 < s["chi2_per_dof"] < 1.3                         # 432 coordinates: 1 +- 0.07
    html = (out / "report.html").read_text()
    assert "held-out targets" in html and "data:image/png;base64," in html
    assert f"{s['position_rms_after_mm']:.4f} mm RMS" in stdout
    # the table holds corrections to the controller's IK: its interpolation adds a few micrometres (the
    # 13 x 13 x 9 grid's bound is 0.007 mm, tests/test_delta_table_chain.py) to the exact IK's error
    t = s["table"]
    assert t["reference"] == "controller" and t["targets_inside"] >= 5
    assert t["position_rms_mm"] < s["position_rms_after_mm"] + 0.01
    assert (out / "table.json").is_file()


def test_demo_refuses_when_the_identified_machine_reaches_no_held_out_target(delta, capsys, monkeypatch):
    """A 5-motor leg described with six task coordinates (gepetto_cassie's first machine.toml, now refused at
    load) left the identified machine none of the held-out targets; the demo then stopped on "ValueError:
    cannot reshape array of size 0 ... (a bug: please report it)". When no held-out target is reached the demo
    says so in one line naming machine.toml."""
    import pmcal.studies.chain_demo as chain_demo

    folder, d = delta
    monkeypatch.setattr(chain_demo, "reachable_targets",
                        lambda machine, params, task: (task[:0], np.zeros((0, machine.twin.n_motors))))
    status, _, err = run(capsys, "--machine", folder, "demo", "--out", d / "demo_none", "--seed", "4")
    assert status == 2 and "a bug" not in err, err
    assert "reaches none of the 60 held-out targets" in err and "machine.toml" in err, err


def test_demo_warns_when_compensation_is_worse_than_predicted():
    """The demo's warning lines: an error family compensated to more than 3x the identification's prediction,
    errors no tracker reading sees that move the task, a barely seen combination of errors that carries the
    predicted task error (unless those errors are already named unseen), and a failed held-out check, each in one
    line; nothing when the figures hold."""
    from types import SimpleNamespace

    from pmcal.studies.chain_demo import ChainDemo

    def demo(after, passed, unseen=(), dominant=None):
        return SimpleNamespace(coordinates=("x_mm", "y_mm", "rz_deg"), WORSE_THAN_PREDICTED=3.0, unseen=unseen,
                               dominant=dominant,
                               result=SimpleNamespace(info={"held_out": {"passed": passed, "rms_mm": 0.03,
                                                                          "predicted_rms_mm": 0.01}}))

    good = {"position_rms_after_mm": 0.005, "position_rms_predicted_mm": 0.004,
            "orientation_rms_after_deg": 0.002, "orientation_rms_predicted_deg": 0.002}
    assert ChainDemo.warnings(demo(0.005, True), good) == []
    bad = dict(good, position_rms_after_mm=0.037)
    lines = ChainDemo.warnings(demo(0.037, False), bad)
    assert len(lines) == 2 and "9.2 times" in lines[0] and "0.0300 mm RMS where 0.0100 mm" in lines[1]
    lines = ChainDemo.warnings(demo(0.005, True, ["effector.dx", "effector.dz"]), good)
    assert len(lines) == 1 and lines[0].startswith("2 error(s) move the task point but no tracker reading (effector.dx")
    dominant = {"share": 0.96, "std": 0.017, "total": 0.0174, "unit": "mm", "seen_sigma": 0.31, "poses": 48,
                "poses_to_halve": 1661.0, "errors": {"eff.dry": 0.59, "effector.dry": -0.4}}
    lines = ChainDemo.warnings(demo(0.005, True, dominant=dominant), good)
    assert len(lines) == 1 and lines[0].startswith("one combination of errors carries 96 % of the predicted task "
                                                   "error (0.017 of 0.017 mm RMS; eff.dry +0.59, effector.dry -0.40")
    assert "48 poses see it at 0.31 tracker sigma" in lines[0] and "about 1661 to halve it" in lines[0]
    # already named as unseen: said once
    assert len(ChainDemo.warnings(demo(0.005, True, ["eff.dry"], dominant), good)) == 1


def test_ctrl_c_during_an_extension_import_is_an_interruption_not_a_bug(monkeypatch, capsys, tmp_path):
    """``import mujoco`` interrupted by Ctrl-C raises ``ImportError: initialization failed`` from the
    KeyboardInterrupt (seen in the test above, one run in three on an idle machine: the campaign's first
    line is printed before the twin imports MuJoCo): exit 130 and the interrupted line, not exit 1 and "a
    bug"; SIGTERM's the same with 143."""
    from pmcal import cli
    from pmcal.commands import targets

    monkeypatch.chdir(tmp_path)

    def interrupted_import(command, args, stop=KeyboardInterrupt):
        try:
            raise stop()
        except KeyboardInterrupt as exc:
            raise ImportError("initialization failed") from exc

    monkeypatch.setattr(targets, "dispatch", interrupted_import)
    assert cli.main(["targets", "-o", "t.csv"]) == 130
    assert capsys.readouterr().err.strip() == "pmcal: interrupted; nothing half-written"
    monkeypatch.setattr(targets, "dispatch", lambda c, a: interrupted_import(c, a, cli.Terminated))
    assert cli.main(["targets", "-o", "t.csv"]) == cli.TERMINATED_STATUS == 143
    assert not list(tmp_path.iterdir())


def test_ctrl_c_while_the_command_line_loads_is_one_line(tmp_path):
    """Ctrl-C in the first 0.4 s, while the console script imports pmcal.cli (numpy, ...) before run() can
    catch it: exit 130 and one line (was a traceback from inside numpy's import). The console script's own
    lines, with the interrupt raised where the first numpy import is."""
    import subprocess
    import sys

    script = ("import builtins\nreal = builtins.__import__\n"
              "def imp(name, *a, **k):\n"
              "    if name.startswith('numpy'):\n        raise KeyboardInterrupt\n    return real(name, *a, **k)\n"
              "builtins.__import__ = imp\nfrom pmcal.cli import run\nrun()\n")
    proc = subprocess.run([sys.executable, "-c", script, "targets", "-o", "t.csv"], cwd=tmp_path,
                          capture_output=True, text=True, timeout=60)
    assert (proc.returncode, proc.stderr) == (130, "pmcal: interrupted\n"), proc.stderr
    assert not list(tmp_path.iterdir())


def _console_entry() -> tuple[str, str]:
    """(module, function) of the ``pmcal`` console script, as pyproject declares it."""
    import tomllib

    from tests.layering import ROOT

    entry = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]["pmcal"]
    module, _, function = entry.partition(":")
    return module, function


@pytest.mark.parametrize("kill_at", ["pmcal.cli", "argparse", "numpy", "pmcal.option_ranges"])
def test_ctrl_c_from_the_first_moment_of_the_console_script_is_one_line(tmp_path, kill_at):
    """A real SIGINT, sent when the console script's import of ``kill_at`` starts (its audit event): exit 130,
    one line, no traceback, nothing written. Deterministic: the points are import steps, not delays. The
    import of pmcal.cli itself (before its own ``try``) gave a KeyboardInterrupt traceback from the console
    script's ``from pmcal.cli import run``; now pmcal.console's handler holds from its first line."""
    import subprocess
    import sys

    module, function = _console_entry()
    script = ("import os, signal, sys\n"
              "def hook(event, args):\n"
              f"    if event == 'import' and args[0] == {kill_at!r}:\n"
              "        os.kill(os.getpid(), signal.SIGINT)\n"
              "sys.addaudithook(hook)\n"
              f"from {module} import {function}\n"
              f"sys.exit({function}())\n")
    proc = subprocess.run([sys.executable, "-c", script, "targets", "-o", "t.csv"], cwd=tmp_path,
                          capture_output=True, text=True, timeout=60)
    assert (proc.returncode, proc.stderr) == (130, "pmcal: interrupted\n"), proc.stderr
    assert not list(tmp_path.iterdir())


def test_ctrl_c_at_early_delays_of_the_real_console_script(tmp_path):
    """The installed ``pmcal`` script, SIGINT at a few delays after its entry module has loaded (seen in
    Python's ``-v`` import lines: before that the interpreter's own start-up answers a signal, outside pmcal),
    during the imports and after: exit 130 and no traceback, whenever it lands; nothing written."""
    import os
    import signal
    import subprocess
    import sys
    import threading
    import time
    from pathlib import Path

    script = Path(sys.executable).parent / "pmcal"
    if not script.exists():
        pytest.skip("no installed pmcal console script beside this Python")
    module, _ = _console_entry()
    for delay in (0.0, 0.05, 0.25):
        proc = subprocess.Popen([str(script), "--machine", "planar_2dof", "twin", "measure", "--poses", "2000",
                                 "-o", "m.csv"], cwd=tmp_path, stderr=subprocess.PIPE, text=True,
                                env={**os.environ, "PYTHONVERBOSE": "1"})
        loaded, lines = threading.Event(), []

        def read(proc=proc, loaded=loaded, lines=lines):
            for line in proc.stderr:
                lines.append(line)
                if line.startswith(f"import '{module}'"):
                    loaded.set()

        reader = threading.Thread(target=read, daemon=True)
        reader.start()
        try:
            assert loaded.wait(30), "".join(lines)[-2000:]
            time.sleep(delay)
            assert proc.poll() is None, "".join(lines)[-2000:]
            proc.send_signal(signal.SIGINT)
            status = proc.wait(timeout=60)
        finally:
            proc.kill()
        reader.join(10)
        err = "".join(lines)
        assert status == 130 and "Traceback" not in err and "pmcal: interrupted" in err, (delay, err[-2000:])
        assert not list(tmp_path.iterdir())


# ---------------------------------------------------------------- directions the prior sets
def _identify_json(capsys, folder, poses, out):
    """A random campaign of ``poses`` on the machine's twin, identified: (JSON document, warnings)."""
    meas = out.parent / f"{out.stem}.csv"
    assert main(["--quiet", "--machine", str(folder), "twin", "measure", "--poses", str(poses), "--seed", "2",
                 "-o", str(meas)]) == 0
    capsys.readouterr()
    assert main(["--machine", str(folder), "identify", str(meas), "-o", str(out)]) == 0
    err = capsys.readouterr().err
    return json.loads(out.read_text()), [x for x in err.splitlines() if "set by the prior" in x]


def test_directions_the_prior_sets_are_counted_and_more_poses_advised_only_where_they_help(capsys, tmp_path):
    # gepetto_delta: a third of its base set lies along directions its two nests barely see; the warning
    # says more poses hardly help, and four times the poses (measured, not extrapolated) indeed leave most
    # of them to the prior. The Delta at 6 poses: more poses advised, and 12 poses determine every direction.
    corpus = Path(__file__).parent / "corpus" / "gepetto_delta"
    doc, warn = _identify_json(capsys, corpus, 48, tmp_path / "g48.json")
    k48 = doc["prior_set"]["count"]
    assert 1 <= k48 < doc["rank"] and doc["prior_set"]["poses_needed"] > 1000
    assert len(warn) == 1 and f"{k48} of the {doc['rank']} identifiable directions" in warn[0]
    assert "hardly help" in warn[0]
    doc4, _ = _identify_json(capsys, corpus, 192, tmp_path / "g192.json")
    assert doc4["prior_set"]["count"] >= k48 // 2 and doc4["prior_set"]["poses_needed"] > 1000
    delta = machine_dir("delta_3dof")
    doc6, warn6 = _identify_json(capsys, delta, 6, tmp_path / "d6.json")
    assert doc6["prior_set"]["count"] >= 1 and len(warn6) == 1 and "measure more poses" in warn6[0]
    doc12, warn12 = _identify_json(capsys, delta, 12, tmp_path / "d12.json")
    assert doc12["prior_set"] == {"count": 0, "poses_needed": 0} and not warn12
