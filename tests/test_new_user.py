"""A new user loses nothing and is never told "success" for a useless result (issue 25).

Each bad input: its one line on stderr, exit status 2, and every file the user had byte-identical
afterwards. Numpy RuntimeWarnings are errors in this module: none may reach the user.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
from pathlib import Path

import pytest

from pmcal.bridge.simulator.modbus_mock import ModbusMockPlc
from pmcal.cli import main
from tests.bridge_fixtures import running
from tests.conftest import run_quietly_in

pytestmark = pytest.mark.filterwarnings("error::RuntimeWarning")


def _rows(path: Path) -> tuple[list[str], list[str]]:
    lines = path.read_text().splitlines()
    head = [line for line in lines if line.startswith("#")]
    return head, [line for line in lines if not line.startswith("#")]


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    """A good campaign (24 planned poses, the acceptance's) and a useless one (one pose measured 30 times),
    each identified; targets; a table."""
    d = run_quietly_in(
        tmp_path_factory.mktemp("user"), ["targets", "-o", "targets.csv"],
        ["twin", "measure", "--preset", "paper-table2", "--poses", "24", "--seed", "1", "-o", "m.csv"],
        ["twin", "measure", "--preset", "paper-table2", "--poses", "24", "--seed", "2", "-o", "m2.csv"],
        ["identify", "m.csv", "-o", "params.json"],
        ["compensate", "params.json", "--table", "table.json", "--table-version", "7"])
    head, rows = _rows(d / "m.csv")
    one = rows[4].split(",", 1)[1]
    (d / "same.csv").write_text("\n".join(head + [rows[0]] + [f"S{i},{one}" for i in range(30)]) + "\n")
    return run_quietly_in(d, ["identify", "same.csv", "-o", "same.json"])


def digest(folder: Path) -> dict[str, str]:
    """Content hash of every file under ``folder`` (the sentinels)."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def refused(capsys, *argv, says: str, status: int = 2) -> str:
    """Run ``pmcal argv``: exit ``status``, exactly one line on stderr holding ``says``, nothing on stdout."""
    capsys.readouterr()
    got = main([str(a) for a in argv])
    cap = capsys.readouterr()
    lines = [line for line in cap.err.splitlines() if line.strip()]
    assert got == status, cap.err
    assert len(lines) == 1 and "Traceback" not in cap.err, cap.err
    assert says in lines[0], lines[0]
    assert "pmcal: wrote" not in cap.out
    return lines[0]


# ---------------------------------------------------------------- 1. no output may be an input
def test_no_output_may_be_an_input(work, capsys, tmp_path):
    for name in ("m.csv", "params.json", "targets.csv"):
        (tmp_path / name).write_bytes((work / name).read_bytes())
    (tmp_path / "m_link.csv").symlink_to(tmp_path / "m.csv")
    os.link(tmp_path / "m.csv", tmp_path / "m_hard.csv")
    before = digest(tmp_path)
    t = tmp_path
    cases = [
        (["identify", t / "m.csv", "-o", t / "m.csv"], "-o"),
        (["identify", t / "m.csv", "-o", t / "m.csv", "--frame", "base"], "MEAS.csv"),
        (["identify", t / "m_link.csv", "-o", t / "m.csv"], "MEAS.csv"),            # through a symlink
        (["identify", t / "m.csv", "-o", t / "m_hard.csv"], "MEAS.csv"),            # a hard link
        (["identify", t / "m.csv", "-o", t / "sub" / ".." / "m.csv"], "MEAS.csv"),  # another spelling
        (["compensate", t / "params.json", "--table", t / "params.json"], "PARAMS.json"),
        (["compensate", t / "params.json", "--targets", t / "targets.csv", "-o", t / "targets.csv"], "--targets"),
        # the CSV written beside the table is the targets file
        (["compensate", t / "params.json", "--targets", t / "targets.csv", "-o", t / "s.csv", "--table",
          t / "targets.json"], "--targets"),
        (["evaluate", t / "params.json", t / "m.csv", "--json", t / "params.json"], "PARAMS.json"),
        (["diagnose", t / "m.csv", "--json", t / "d.json", "--params", t / "params.json", "--report", t / "params.json"],
         "params.json"),
        (["twin", "measure", "--targets", t / "targets.csv", "-o", t / "targets.csv"], "--targets"),
    ]
    (t / "sub").mkdir()
    for argv, says in cases:
        for force in ([], ["--force"]):
            if force and argv[0] not in ("compensate", "diagnose"):
                continue
            refused(capsys, *argv, *force, says=says)
    (t / "sub").rmdir()
    assert digest(tmp_path) == before


def test_no_output_may_be_the_pushed_table(work, capsys, tmp_path):
    table = tmp_path / "table.json"
    table.write_bytes((work / "table.json").read_bytes())
    before = digest(tmp_path)
    refused(capsys, "push", table, "--modbus", "127.0.0.1:1", "--dry-run", "--audit", table, says="TABLE")
    refused(capsys, "push", table, "--modbus", "127.0.0.1:1", "--dry-run", "--json", table, says="TABLE")
    assert digest(tmp_path) == before


# ---------------------------------------------------------------- 2. campaign quality
def test_identify_says_how_much_a_campaign_determines(work, capsys, tmp_path):
    good, bad = (json.loads((work / f).read_text())["quality"] for f in ("params.json", "same.json"))
    assert good["usable"] is True and good["why"] is None
    assert good["determined_directions"] > good["parameters"] / 2
    assert bad["usable"] is False and "parameter directions" in bad["why"]
    assert bad["determined_directions"] < bad["parameters"] / 4        # one pose: its 6 coordinates at most
    # the prediction against an independent measure: each calibration evaluated on a second campaign
    errs = {}
    for name in ("params", "same"):
        capsys.readouterr()
        assert main(["evaluate", str(work / f"{name}.json"), str(work / "m2.csv"), "--json",
                     str(tmp_path / f"{name}_e.json")]) == 0
        errs[name] = json.loads((tmp_path / f"{name}_e.json").read_text())["pointing_error_deg"]["rms"]
    # the useless calibration points far off, the good one within noise of the tracker
    assert errs["same"] > 0.1 and errs["params"] < 0.02
    # predicted 1-sigma pointing uncertainty: the same order as the error the calibration leaves
    assert 0.3 < bad["predicted_pointing_std_deg"]["rms"] / errs["same"] < 3.0
    assert good["predicted_pointing_std_deg"]["rms"] < errs["params"]
    # printed when piped: the result line, and the warning for the useless one
    capsys.readouterr()
    assert main(["identify", str(work / "same.csv"), "-o", str(tmp_path / "p.json")]) == 0
    cap = capsys.readouterr()
    assert cap.out.splitlines()[0].startswith("identified ")
    assert f"{bad['determined_directions']} of {bad['parameters']} parameter directions determined" in cap.out
    warn = [line for line in cap.err.splitlines() if line.startswith("pmcal: warning:")]
    assert len(warn) == 1 and "not usable" in warn[0] and "pmcal twin plan" in warn[0]
    # the paper's per-limb model: one pose fixes one motor equation a limb
    for src, usable in (("same.csv", False), ("m.csv", True)):
        assert main(["--quiet", "identify", str(work / src), "-o", str(tmp_path / "paper.json"), "--model", "paper",
                     "--method", "lm"]) == 0
        q = json.loads((tmp_path / "paper.json").read_text())["quality"]
        assert q["usable"] is usable and (q["determined_directions"] <= 2 if not usable else
                                          q["determined_directions"] >= 18), q


def test_compensate_and_push_refuse_a_useless_calibration(work, capsys, tmp_path):
    before = digest(work)
    t = tmp_path
    fix = "pmcal twin plan"
    refused(capsys, "compensate", work / "same.json", "--targets", work / "targets.csv", "-o", t / "s.csv", says=fix)
    refused(capsys, "compensate", work / "same.json", "--table", t / "tab.json", says=fix)
    assert not list(t.iterdir())
    # the good campaign of the acceptance is not refused
    capsys.readouterr()
    assert main(["compensate", str(work / "params.json"), "--targets", str(work / "targets.csv"),
                 "-o", str(t / "good.csv")]) == 0
    # --force: done, and the table says where it came from; push refuses it before any request
    assert main(["compensate", str(work / "same.json"), "--table", str(t / "forced.json"), "--force"]) == 0
    assert json.loads((t / "forced.json").read_text())["quality"]["usable"] is False
    with running(ModbusMockPlc(lifetime_s=60.0)) as plc:
        refused(capsys, "push", t / "forced.json", "--modbus", plc.target, says=fix)
        assert plc.requests == 0
        capsys.readouterr()
        assert main(["push", str(t / "forced.json"), "--modbus", plc.target, "--force", "--no-audit"]) == 0
    assert digest(work) == before


def test_push_refuses_a_table_for_another_machine_before_any_request(work, capsys, tmp_path):
    before = digest(work)
    with running(ModbusMockPlc(lifetime_s=60.0)) as plc:
        line = refused(capsys, "--machine", "planar_2dof", "push", work / "table.json", "--modbus", plc.target,
                       says="field 'machine'")
        assert "ocpm_2dof" in line and "planar_2dof" in line
        assert plc.requests == 0
    assert digest(work) == before and not (work / "bridge_audit.log").exists()


# ---------------------------------------------------------------- 3. ranges at the edge
def _csv(path: Path, text: str, encoding: str = "utf-8") -> Path:
    path.write_bytes(text.encode(encoding))
    return path


def test_bad_values_name_file_row_and_field(work, capsys, tmp_path):
    t = tmp_path
    far = _csv(t / "far.csv", "phi_deg,theta_deg\n10,30\n1e20,30\n")
    tilt = _csv(t / "tilt.csv", "phi_deg,theta_deg\n10,86\n")
    semi = _csv(t / "semi.csv", "phi_deg;theta_deg\n10;30\n")
    latin = _csv(t / "latin.csv", "# mesuré à 20 °C\nphi_deg,theta_deg\n10,30\n", "latin-1")
    head, rows = _rows(work / "m.csv")
    header = rows[0].split(",")
    cells = rows[2].split(",")
    cells[header.index("t3_z")] = "1e300"
    huge = _csv(t / "huge.csv", "\n".join(head + [rows[0], rows[1], ",".join(cells)] + rows[3:]) + "\n")
    latin_json = _csv(t / "latin.json", '{"params": {}, "note": "Prüfstand"}', "latin-1")
    before = digest(t)
    p = work / "params.json"
    refused(capsys, "compensate", p, "--targets", far, "-o", t / "s.csv", says="far.csv, row 2, field 'phi_deg'")
    refused(capsys, "compensate", p, "--targets", tilt, "-o", t / "s.csv", says="tilt.csv, row 1, field 'theta_deg'")
    refused(capsys, "compensate", p, "--targets", semi, "-o", t / "s.csv", says="comma-separated")
    refused(capsys, "compensate", p, "--targets", latin, "-o", t / "s.csv", says="save it as UTF-8")
    refused(capsys, "identify", latin, "-o", t / "p.json", says="save it as UTF-8")
    refused(capsys, "identify", huge, "-o", t / "p.json", says="huge.csv, row 2, field 't3_z'")
    refused(capsys, "diagnose", huge, "--json", t / "d.json", says="field 't3_z'")
    refused(capsys, "compensate", latin_json, "--table", t / "x.json", says="save it as UTF-8")
    assert digest(t) == before


def test_counts_grids_and_output_names_are_checked(work, capsys, tmp_path):
    t = tmp_path
    p = work / "params.json"
    refused(capsys, "twin", "measure", "--poses", "10000000", "-o", t / "m.csv", says="--poses")
    refused(capsys, "--machine", "planar_2dof", "twin", "measure", "--poses", "10000000", "-o", t / "m.csv",
            says="--poses")
    for grid in ("-5,10", "5,x", "5", "200,10"):
        refused(capsys, "compensate", p, "--table", t / "tab.json", "--grid", grid, says="field '--grid'")
    refused(capsys, "loop", "--grid", "-5,10", says="field '--grid'")
    for argv, says in ((["twin", "render", "-o", t / "x.txt"], ".png"),
                       (["identify", work / "m.csv", "-o", t / "x.csv"], ".json"),
                       (["compensate", p, "--table", t / "tab.csv"], ".json"),
                       (["compensate", p, "--targets", work / "targets.csv", "-o", t / "s.json"], ".csv"),
                       (["targets", "-o", t / "t.txt"], ".csv"),
                       (["twin", "measure", "--poses", "2", "-o", t / "m.json"], ".csv"),
                       (["evaluate", p, work / "m.csv", "--json", t / "e.csv"], ".json")):
        refused(capsys, *argv, says=says)
    assert not list(t.iterdir())


# ---------------------------------------------------------------- 4. results where the user looks
def test_push_says_it_wrote_the_audit_log(work, capsys, tmp_path):
    table = tmp_path / "table.json"
    table.write_bytes((work / "table.json").read_bytes())
    with running(ModbusMockPlc(lifetime_s=60.0)) as plc:
        capsys.readouterr()
        assert main(["push", str(table), "--modbus", plc.target, "--dry-run"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("dry_run: ") and out[1:] == [f"pmcal: wrote {tmp_path / 'bridge_audit.log'}"]
    assert len((tmp_path / "bridge_audit.log").read_text().splitlines()) == 1


def test_diagnose_says_its_verdict_first(work, capsys, tmp_path):
    capsys.readouterr()
    assert main(["diagnose", str(work / "m.csv"), "--json", str(tmp_path / "d.json")]) == 0
    out = capsys.readouterr().out.splitlines()
    doc = json.loads((tmp_path / "d.json").read_text())
    assert doc["effects"] == []             # the twin had no effect: the model explains the data
    assert out[0].startswith("no missing effect: the model explains the data to the noise level; held-out gap")


def test_progress_bar_is_drawn_on_a_terminal_that_reports_no_size(monkeypatch):
    """A pty without a window size (``script``, CI terminals) reports 0 x 0: tqdm alone would draw
    nothing; the bar must still show, one line updated in place."""
    from pmcal import progress

    class Tty(io.StringIO):
        def isatty(self):
            return True

    err = Tty()
    monkeypatch.setattr("sys.stderr", err)
    progress.set_quiet(False)
    with progress.progress(total=3, desc="pmcal demo", unit="step") as bar:
        for name in ("campaign", "identify", "report"):
            bar.set_description(f"pmcal demo: {name}")
            bar.update(1)
    text = err.getvalue()
    assert "pmcal demo: identify" in text and "\r" in text and text.count("\n") <= 1
    # piped: nothing
    piped = io.StringIO()
    monkeypatch.setattr("sys.stderr", piped)
    with progress.progress(total=3, desc="pmcal demo", unit="step") as bar:
        bar.update(3)
    assert piped.getvalue() == ""


def test_planar_identify_records_its_rank_and_compensate_refuses_a_flagged_file(capsys, tmp_path):
    d = run_quietly_in(tmp_path, ["--machine", "planar_2dof", "twin", "measure", "--preset", "group1", "-o", "p.csv"],
                       ["--machine", "planar_2dof", "identify", "p.csv", "-o", "p.json"],
                       ["--machine", "planar_2dof", "targets", "-o", "t.csv"])
    doc = json.loads((d / "p.json").read_text())
    assert doc["quality"]["usable"] is True and doc["quality"]["determined_directions"] == doc["rank"] == 4
    doc["quality"].update(usable=False, why="only 1 of 4 parameter directions are determined by the campaign")
    (d / "weak.json").write_text(json.dumps(doc))
    before = digest(d)
    refused(capsys, "--machine", "planar_2dof", "compensate", d / "weak.json", "--targets", d / "t.csv", "-o",
            d / "s.csv", says="weak.json, field 'quality'")
    assert digest(d) == before
    assert main(["--quiet", "--machine", "planar_2dof", "compensate", str(d / "weak.json"), "--targets",
                 str(d / "t.csv"), "-o", str(d / "s.csv"), "--force"]) == 0


def test_a_reader_that_stops_early_ends_the_command_quietly(tmp_path):
    """``pmcal mock-plc ... | head -1``: when the reader of stdout closes the pipe, pmcal stops without an
    error line, with the status a shell reports for a command SIGPIPE ended (141)."""
    import subprocess
    import sys

    proc = subprocess.Popen([sys.executable, "-c", "from pmcal.cli import run; run()",        # the console script
                             "mock-plc", "--modbus", "--seconds", "5"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=tmp_path)
    proc.stdout.close()                         # the reader is gone before the first line
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=30) == 141
    assert "Broken pipe" not in err and "Traceback" not in err, err
