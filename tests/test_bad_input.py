"""Every subcommand answers bad input with one line and the right exit status, never a traceback, and
never replaces or half-writes a file (issue 13's table of bad inputs, one test per row).

Run in-process through :func:`pmcal.cli.main`, the console script's entry point.
"""

import json
import stat
from pathlib import Path

import numpy as np
import pytest

from pmcal.cli import main
from tests.conftest import run_quietly_in

pytestmark = pytest.mark.filterwarnings("error::RuntimeWarning")    # no numpy warning reaches the user


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    """A campaign, its whole-chain and paper parameters, a planar campaign, targets, a table."""
    return run_quietly_in(
        tmp_path_factory.mktemp("bad"), ["targets", "-o", "targets.csv"],
        ["twin", "measure", "--preset", "paper-table2", "--poses", "24", "--seed", "1", "-o", "m.csv"],
        ["identify", "m.csv", "-o", "params.json"],
        ["identify", "m.csv", "-o", "paper.json", "--model", "paper"],
        ["compensate", "params.json", "--table", "table.json", "--table-version", "7"],
        ["--machine", "planar_2dof", "twin", "measure", "--preset", "group1", "--poses", "14", "-o", "planar.csv"],
        ["--machine", "planar_2dof", "identify", "planar.csv", "-o", "planar.json"])


def run(capsys, *argv) -> tuple[int, str]:
    capsys.readouterr()
    status = main([str(a) for a in argv])
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return status, err


def one_line_error(capsys, *argv, status=2, says=None) -> str:
    got, err = run(capsys, *argv)
    assert got == status, err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    if says:
        assert says in lines[0], lines[0]
    return lines[0]


def edited(work, src, name, change, bom=False) -> Path:
    doc = json.loads((work / src).read_text())
    change(doc)
    out = work / name
    out.write_text(json.dumps(doc), encoding="utf-8-sig" if bom else "utf-8")
    return out


def writers(w: Path, out: str, folder_out: str):
    """Every command that writes, with its output replaced by ``out`` (files) or ``folder_out`` (folders)."""
    return [
        ["targets", "-o", out],
        ["twin", "measure", "--poses", "2", "-o", out],
        ["twin", "render", "--width", "64", "--height", "48", "-o", out],
        ["identify", w / "m.csv", "-o", out],
        ["compensate", w / "params.json", "--targets", w / "targets.csv", "-o", out],
        ["compensate", w / "params.json", "--table", out],
        ["evaluate", w / "params.json", w / "m.csv", "--json", out],
        ["diagnose", w / "m.csv", "--json", out],
        ["diagnose", w / "m.csv", "--json", w / "never.json", "--report", folder_out],
        ["demo", "--out", folder_out],
        ["push", w / "table.json", "--modbus", "127.0.0.1:1", "--dry-run", "--json", out],
        ["--machine", "planar_2dof", "identify", w / "planar.csv", "-o", out],
        ["--machine", "planar_2dof", "twin", "measure", "-o", out],
    ]


# ---------------------------------------------------------------- every writer: bad output paths
def test_every_writer_refuses_a_read_only_folder_and_a_folder_as_output(work, capsys, tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    a_file = tmp_path / "a_file.txt"
    a_file.write_text("mine\n")
    try:
        for argv in writers(work, ro / "out.x", ro / "sub"):
            one_line_error(capsys, *argv, says="not writable")
        for argv in writers(work, tmp_path, a_file):
            one_line_error(capsys, *argv)
        for argv in writers(work, tmp_path / "missing" / "out.x", tmp_path / "missing" / "sub"):
            one_line_error(capsys, *argv, says="does not exist")
    finally:
        ro.chmod(0o755)
    assert a_file.read_text() == "mine\n" and not (work / "never.json").exists()


def test_every_writer_refuses_a_read_only_file(work, capsys, tmp_path):
    target = tmp_path / "keep.out"
    target.write_text("mine\n")
    target.chmod(stat.S_IRUSR | stat.S_IRGRP)
    for argv in writers(work, target, tmp_path / "unused"):
        if "--report" in argv or "demo" in argv:
            continue
        one_line_error(capsys, *argv, says="read-only")
    assert target.read_text() == "mine\n"


def test_a_folder_pmcal_did_not_write_is_never_replaced(work, capsys, tmp_path):
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "thesis.tex").write_text("years of work")
    one_line_error(capsys, "demo", "--out", mine, says="--force")
    one_line_error(capsys, "diagnose", work / "m.csv", "--json", tmp_path / "d.json", "--report", mine,
                   says="--force")
    assert (mine / "thesis.tex").read_text() == "years of work" and not (tmp_path / "d.json").exists()


def test_the_hidden_effect_demo_has_its_own_folder():
    from pmcal.cli import build_parser
    from pmcal.commands.machine_commands import _demo_defaults

    a = build_parser().parse_args(["demo"])
    b = build_parser().parse_args(["demo", "--hidden-effect", "random"])
    _demo_defaults(a)
    _demo_defaults(b)
    assert a.out == "pmcal-demo" and b.out == "pmcal-demo-hidden"


# ---------------------------------------------------------------- size
def _big_csv(src: Path, dst: Path, n: int, id_col: str = "pose_id") -> Path:
    lines = [line for line in src.read_text().splitlines() if not line.startswith("#")]
    header, rows = lines[0], lines[1:]
    out = [header] + [f"X{i}," + rows[i % len(rows)].split(",", 1)[1] for i in range(n)]
    dst.write_text("\n".join(out) + "\n")
    return dst


def test_huge_inputs_are_refused_with_a_clear_message(work, capsys, tmp_path):
    big = _big_csv(work / "m.csv", tmp_path / "big.csv", 100_000)
    one_line_error(capsys, "identify", big, "-o", tmp_path / "p.json", says="100000 data rows, more than the 2000 this command reads")
    one_line_error(capsys, "diagnose", big, "--json", tmp_path / "d.json", says="100000 data rows, more than the 2000 this command reads")
    pbig = _big_csv(work / "planar.csv", tmp_path / "pbig.csv", 100_000)
    one_line_error(capsys, "--machine", "planar_2dof", "identify", pbig, "-o", tmp_path / "p.json",
                   says="100000 data rows, more than the 2000 this command reads")
    one_line_error(capsys, "--machine", "planar_2dof", "evaluate", work / "planar.json", pbig,
                   says="100000 data rows, more than the 2000 this command reads")
    assert not list(tmp_path.glob("*.json"))


def test_a_large_input_reports_its_steps_also_when_piped(work, capsys, tmp_path):
    """Above LONG_POSES poses identify says what it does on stderr (captured = not a terminal)."""
    from pmcal.ocpm.io import LONG_POSES

    big = _big_csv(work / "m.csv", tmp_path / "long.csv", LONG_POSES + 16)
    capsys.readouterr()
    assert main(["identify", str(big), "-o", str(tmp_path / "p.json")]) == 0
    cap = capsys.readouterr()
    assert f"identifying the whole closed chain from {LONG_POSES + 16} poses" in cap.err
    assert cap.out.splitlines()[1:] == [f"pmcal: wrote {tmp_path / 'p.json'}"]
    assert cap.out.startswith("identified 54 parameters (whole chain)")
    assert main(["identify", str(work / "m.csv"), "-o", str(tmp_path / "q.json")]) == 0    # 24 poses: silent
    assert capsys.readouterr().err == ""
    assert main(["--quiet", "identify", str(big), "-o", str(tmp_path / "r.json")]) == 0
    assert capsys.readouterr() == ("", "")


def _cell_replaced(src: Path, dst: Path, column: str, value: str) -> Path:
    """``src`` with the first data row's ``column`` set to ``value``."""
    lines = src.read_text().splitlines()
    head = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    k = lines[head].split(",").index(column)
    cells = lines[head + 1].split(",")
    cells[k] = value
    lines[head + 1] = ",".join(cells)
    dst.write_text("\n".join(lines) + "\n")
    return dst


def test_digits_grouped_with_underscores_are_refused_in_every_csv(work, capsys, tmp_path):
    """``1_0`` was read as 10 (Python's float takes underscores): now refused naming file, row and field, nothing
    written; blanks around a number and 1e1 stay accepted, inf and nan stay refused."""
    targets = _cell_replaced(work / "targets.csv", tmp_path / "t.csv", "phi_deg", "1_0")
    line = one_line_error(capsys, "compensate", work / "params.json", "--targets", targets, "-o", tmp_path / "s.csv")
    assert f"{targets}, row 1, field 'phi_deg'" in line and "without '_'" in line
    meas = _cell_replaced(work / "m.csv", tmp_path / "m.csv", "m1_cmd_deg", "-4_0.5")
    one_line_error(capsys, "identify", meas, "-o", tmp_path / "p.json", says=f"{meas}, row 1, field 'm1_cmd_deg'")
    bad_table = _cell_replaced(work / "table.csv", tmp_path / "bad_table.csv", "dm1_deg", "1_0")
    one_line_error(capsys, "push", bad_table, "--modbus", "127.0.0.1:1", "--json", tmp_path / "r.json",
                   says=f"{bad_table}, row 1, field 'dm1_deg'")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad_table.csv", "m.csv", "t.csv"]
    for value, status in ((" 1e1 ", 0), ("inf", 2), ("nan", 2)):
        ok = _cell_replaced(work / "targets.csv", tmp_path / "t.csv", "phi_deg", value)
        assert run(capsys, "compensate", work / "params.json", "--targets", ok, "-o", tmp_path / "s.csv")[0] == status


# ---------------------------------------------------------------- planar plausibility
def test_planar_readings_in_metres_are_refused(work, capsys, tmp_path):
    lines = (work / "planar.csv").read_text().splitlines()
    out = []
    for line in lines:
        c = line.split(",")
        if not line.startswith(("#", "pose_id")) and c[3]:
            c[3] = repr(float(c[3]) / 1000.0)
        out.append(",".join(c))
    metres = tmp_path / "metres.csv"
    metres.write_text("\n".join(out) + "\n")
    one_line_error(capsys, "--machine", "planar_2dof", "identify", metres, "-o", tmp_path / "p.json",
                   says="metres")
    assert not (tmp_path / "p.json").exists()


def test_planar_full_model_rank_deficiency_is_reported(work, capsys, tmp_path):
    out = tmp_path / "full.json"
    one_line_error(capsys, "--machine", "planar_2dof", "identify", work / "planar.csv", "-o", out,
                   "--model", "full", status=1, says="rank 9 of 12")
    doc = json.loads(out.read_text())
    assert doc["success"] is False and len(doc["null_space"]) == 3
    for vec in doc["null_space"]:                  # unit vectors
        assert np.linalg.norm(list(vec.values())) == pytest.approx(1.0, abs=1e-5)


# ---------------------------------------------------------------- parameter files: one schema
def _times_1000(doc):
    doc["params"] = {k: v * 1000 if k.split(".")[1] in ("dtheta", "dalpha", "dgamma") else v
                     for k, v in doc["params"].items()}


def test_angles_times_1000_are_refused_by_every_reader(work, capsys, tmp_path):
    bad = edited(work, "params.json", "x1000.json", _times_1000)
    for argv in (["evaluate", bad, work / "m.csv"],
                 ["diagnose", work / "m.csv", "--json", tmp_path / "d.json", "--params", bad],
                 ["loop", "--errors", bad, "--targets", "2"],
                 ["compensate", bad, "--targets", work / "targets.csv", "-o", tmp_path / "s.csv"],
                 ["twin", "measure", "--errors", bad, "--poses", "2", "-o", tmp_path / "m.csv"]):
        line = one_line_error(capsys, *argv, says="x1000.json")
        assert "implausible" in line and "targets" not in line.split("x1000.json")[0]
    assert not list(tmp_path.iterdir())


def test_a_link_length_error_of_500_mm_is_refused_without_leaving_files(work, capsys, tmp_path, monkeypatch):
    bad = edited(work, "params.json", "dl500.json", lambda d: d["params"].update({"L1.dl1": 500.0}))
    monkeypatch.chdir(tmp_path)
    one_line_error(capsys, "evaluate", bad, work / "m.csv", says="L1.dl1")
    assert not list(tmp_path.iterdir())          # no MUJOCO_LOG.TXT


def test_paper_params_without_model_are_the_paper_model(work, capsys, tmp_path):
    def strip(d):
        d.pop("model")
    nomodel = edited(work, "paper.json", "paper_nomodel.json", strip)
    assert run(capsys, "compensate", nomodel, "--targets", work / "targets.csv", "-o", tmp_path / "a.csv")[0] == 0
    assert run(capsys, "compensate", work / "paper.json", "--targets", work / "targets.csv",
               "-o", tmp_path / "b.csv")[0] == 0
    assert (tmp_path / "a.csv").read_text().splitlines()[2:] == (tmp_path / "b.csv").read_text().splitlines()[2:]


def test_unknown_model_and_non_numeric_stiffness_ratio_are_refused(work, capsys, tmp_path):
    banana = edited(work, "params.json", "banana.json", lambda d: d.update(model="banana"))
    high = edited(work, "params.json", "high.json", lambda d: d.update(stiffness_ratio="high"))
    pbanana = edited(work, "planar.json", "pbanana.json", lambda d: d.update(model="banana"))
    phigh = edited(work, "planar.json", "phigh.json", lambda d: d.update(stiffness_ratio="high"))
    for bad, field in ((banana, "model"), (high, "stiffness_ratio")):
        one_line_error(capsys, "twin", "measure", "--errors", bad, "--poses", "2", "-o", tmp_path / "m.csv",
                       says=field)
        one_line_error(capsys, "diagnose", work / "m.csv", "--json", tmp_path / "d.json", "--params", bad,
                       says=field)
    for bad, field in ((pbanana, "model"), (phigh, "stiffness_ratio")):
        one_line_error(capsys, "--machine", "planar_2dof", "evaluate", bad, work / "planar.csv", says=field)
        one_line_error(capsys, "--machine", "planar_2dof", "compensate", bad, "--targets", work / "targets.csv",
                       "-o", tmp_path / "s.csv", says=field)
    assert not list(tmp_path.iterdir())


# ---------------------------------------------------------------- push, diagnose, BOM, render
def test_push_of_a_folder_is_one_line(work, capsys, tmp_path):
    one_line_error(capsys, "push", tmp_path, "--modbus", "127.0.0.1:1", "--dry-run")


def test_diagnose_report_that_is_a_file_writes_nothing(work, capsys, tmp_path):
    report = tmp_path / "report"
    report.write_text("x")
    one_line_error(capsys, "diagnose", work / "m.csv", "--json", tmp_path / "d.json", "--report", report,
                   says="not a folder")
    assert not (tmp_path / "d.json").exists() and report.read_text() == "x"


def test_utf8_bom_is_accepted_in_parameter_files(work, capsys, tmp_path):
    bom = edited(work, "params.json", "bom.json", lambda d: None, bom=True)
    assert bom.read_bytes().startswith(b"\xef\xbb\xbf")
    assert run(capsys, "evaluate", bom, work / "m.csv")[0] == 0
    assert run(capsys, "compensate", bom, "--targets", work / "targets.csv", "-o", tmp_path / "s.csv")[0] == 0
    pbom = edited(work, "planar.json", "pbom.json", lambda d: None, bom=True)
    assert run(capsys, "--machine", "planar_2dof", "evaluate", pbom, work / "planar.csv")[0] == 0


def test_utf8_bom_is_accepted_in_a_table(work, capsys, tmp_path):
    table = tmp_path / "bom_table.json"
    table.write_bytes(b"\xef\xbb\xbf" + (work / "table.json").read_bytes())
    status, err = run(capsys, "push", table, "--modbus", "127.0.0.1:1", "--dry-run", "--attempts", "1",
                      "--timeout", "0.2")
    assert "JSON" not in err and "format" not in err


def test_render_size_is_checked_with_the_right_message(work, capsys, tmp_path):
    for width in ("0", "2000"):
        line = one_line_error(capsys, "twin", "render", "--width", width, "-o", tmp_path / "x.png",
                              says="--width")
        assert "EGL" not in line
    assert not list(tmp_path.iterdir())


# ---------------------------------------------------------------- CLI conventions
@pytest.mark.parametrize("machine", ["ocpm_2dof", "planar_2dof"])
def test_every_argument_has_help(machine):
    import argparse

    from pmcal.cli import _named_subparsers, build_parser

    parser = build_parser(machine)
    missing = [f"{name} {a.dest}" for name, sp in _named_subparsers(parser) for a in sp._actions
               if not isinstance(a, (argparse._HelpAction, argparse._SubParsersAction)) and not a.help]
    assert not missing
    assert "--version" in parser.format_help()


def _commands(work, d):
    """Successful calls of every kind of command: (argv, number of result lines, outputs written)."""
    w = work
    return [
        (["targets", "-o", d / "t.csv"], 1, [d / "t.csv"]),
        (["twin", "measure", "--poses", "24", "--seed", "2", "-o", d / "m.csv"], 1, [d / "m.csv"]),
        (["identify", w / "m.csv", "-o", d / "p.json"], 1, [d / "p.json"]),
        (["compensate", w / "params.json", "--targets", w / "targets.csv", "-o", d / "s.csv", "--table",
          d / "tab.json"], 1, [d / "s.csv", d / "tab.json", d / "tab.csv"]),
        (["export-model", w / "params.json", "-o", d / "cal.xml"], 1, [d / "cal.xml", d / "cal.toml"]),
        (["--machine", "delta_3dof", "targets", "-o", d / "dt.csv"], 1, [d / "dt.csv"]),
        (["--machine", "planar_2dof", "twin", "measure", "-o", d / "pm.csv"], 1, [d / "pm.csv"]),
        (["evaluate", w / "params.json", w / "m.csv", "--json", d / "e.json"], 1, [d / "e.json"]),
        (["diagnose", w / "m.csv", "--json", d / "d.json", "--report", d / "rep"], 1, [d / "d.json", d / "rep"]),
        (["--machine", "planar_2dof", "identify", w / "planar.csv", "-o", d / "pl.json"], 1, [d / "pl.json"]),
        (["--machine", "planar_2dof", "evaluate", w / "planar.json", w / "planar.csv"], 1, []),
    ]


def test_each_command_prints_its_result_then_one_line_per_output(work, capsys, tmp_path):
    """docs/formats.md, "What the commands print"; a folder is one output (PATH/), a table brings its CSV."""
    for argv, results, outputs in _commands(work, tmp_path):
        capsys.readouterr()
        assert main([str(a) for a in argv]) == 0, argv
        lines = capsys.readouterr().out.splitlines()
        wrote = [f"pmcal: wrote {p}{'/' if p.name == 'rep' else ''}" for p in outputs]
        assert len(lines) == results + len(wrote) and lines[results:] == wrote, (argv, lines)
        assert not any(line.startswith("pmcal: wrote") for line in lines[:results]), lines


def test_quiet_prints_nothing_but_errors_for_every_command(work, capsys, tmp_path):
    for argv, _, outputs in _commands(work, tmp_path):
        capsys.readouterr()
        assert main([str(a) for a in argv] + ["--quiet"]) == 0, argv
        cap = capsys.readouterr()
        assert cap.out == "" and cap.err == "", (argv, cap)
        assert all(p.exists() for p in outputs), argv
    one_line_error(capsys, "--quiet", "identify", tmp_path / "nope.csv", "-o", tmp_path / "x.json",
                   says="file not found")
    assert capsys.readouterr().out == ""


def test_quiet_and_verbose_are_accepted_after_the_subcommand(work, capsys, tmp_path):
    status, _ = run(capsys, "targets", "-o", tmp_path / "t.csv", "--quiet")
    assert status == 0 and capsys.readouterr().out == ""
    assert main(["targets", "-o", str(tmp_path / "t2.csv"), "--verbose"]) == 0
    assert capsys.readouterr().out.splitlines()[-1] == f"pmcal: wrote {tmp_path / 't2.csv'}"

