"""The one output guard (issue 33): no output is, contains or sits inside an input, the working folder,
a parent of it or the machine folder, whatever --force says; side files replace only pmcal's own files;
a folder is replaced only when empty or pmcal's own, swapped in without deleting first; SIGTERM cleans
up as Ctrl-C does.

Every refusal: one line, exit 2, and every file of the user byte-identical afterwards (the tree above
the working folder is hashed before and after).
"""

from __future__ import annotations

import hashlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from pmcal.cli import main
from pmcal.errors import InputError
from pmcal.fileio import MARKER, atomic_directory, check_output
from tests.conftest import run_quietly_in

pytestmark = pytest.mark.filterwarnings("error::RuntimeWarning")


def digest(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def user(tmp_path_factory):
    """root/keep.txt, root/machines/my_delta (a copy of the Delta), root/work: a campaign m.csv, its
    parameters, sub/m.csv, a tracker campaign t.csv, a Delta campaign and parameters."""
    import pmcal.mjcf

    root = tmp_path_factory.mktemp("guard")
    (root / "keep.txt").write_text("mine\n")
    copy = root / "machines" / "my_delta"
    import shutil
    shutil.copytree(pmcal.mjcf.machine_dir("delta_3dof"), copy)
    (copy / "delta_3dof.xml").rename(copy / "my_delta.xml")
    toml = (copy / "machine.toml").read_text()
    (copy / "machine.toml").write_text(toml.replace('name = "delta_3dof"', 'name = "my_delta"')
                                       .replace('model = "delta_3dof.xml"', 'model = "my_delta.xml"'))
    (copy / "scene.xml").write_text((copy / "scene.xml").read_text().replace("delta_3dof.xml", "my_delta.xml"))
    work = root / "work"
    (work / "sub").mkdir(parents=True)
    run_quietly_in(work, ["twin", "measure", "--preset", "paper-table2", "--poses", "24", "--seed", "1", "-o", "m.csv"],
                   ["identify", "m.csv", "-o", "params.json"],
                   ["--machine", "../machines/my_delta", "twin", "measure", "--seed", "3", "-o", "d.csv"],
                   ["--machine", "../machines/my_delta", "identify", "d.csv", "-o", "dp.json"])
    shutil.copy(work / "m.csv", work / "sub" / "m.csv")
    shutil.copy(work / "m.csv", work / "t.csv")
    return root


def refused_in(root: Path, capsys, *argv, says: str) -> str:
    """Run ``pmcal argv`` in root/work: exit 2, one line holding ``says``, nothing under root changed."""
    before = digest(root)
    cwd = os.getcwd()
    os.chdir(root / "work")
    try:
        capsys.readouterr()
        status = main([str(a) for a in argv])
    finally:
        os.chdir(cwd)
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert status == 2 and len(lines) == 1, err
    assert says in lines[0], lines[0]
    assert digest(root) == before
    assert not [p for p in root.rglob(".*")], "staging left behind"
    return lines[0]


@pytest.mark.parametrize("argv, says", [
    (["diagnose", "m.csv", "--json", "d.json", "--report", ".", "--force"], "is the working folder"),
    (["diagnose", "m.csv", "--json", "d.json", "--report", "..", "--force"], "contains the working folder"),
    (["diagnose", "sub/m.csv", "--json", "d.json", "--report", "sub", "--force"], "contains the input MEAS.csv"),
    (["diagnose", "m.csv", "--json", "d.json", "--report", "sub"], "holds m.csv, which pmcal did not write"),
    (["demo", "--out", ".", "--force"], "is the working folder"),
    (["demo", "--out", "../..", "--force"], "contains the working folder"),
    (["--machine", "../machines/my_delta", "demo", "--out", "../machines/my_delta", "--force"], "is the machine folder"),
    (["--machine", "../machines/my_delta", "demo", "--out", "../machines/my_delta/out"], "is inside the machine folder"),
    (["compensate", "params.json", "--table", "m.json"], "m.csv would be written beside this output"),
    (["--machine", "../machines/my_delta", "compensate", "dp.json", "--table", "d.json"], "d.csv would be written"),
    (["--machine", "../machines/my_delta", "export-model", "dp.json", "-o", "../machines/my_delta/machine.xml"],
     "is inside the machine folder"),
    (["--machine", "../machines/my_delta", "export-model", "dp.json", "-o", "../machines/my_delta/my_delta.xml"],
     "is inside the machine folder"),
    (["compensate", "params.json", "--targets", "t.csv", "-o", "./t.csv"], "is also the input --targets"),
    # outputs with a side file: the side file's name comes from the output's (was a ValueError, exit 1)
    (["compensate", "params.json", "--table", "."], "is the working folder"),
    (["compensate", "params.json", "--table", ""], "empty output path"),
    (["--machine", "../machines/my_delta", "export-model", "dp.json", "-o", "/"], "contains the working folder"),
])
def test_no_output_may_lose_the_users_files(user, capsys, argv, says):
    refused_in(user, capsys, *argv, says=says)


def test_a_side_file_of_the_users_is_never_replaced_by_export_model(user, capsys):
    (user / "work" / "cal.toml").write_text("mine = 1\n")
    try:
        refused_in(user, capsys, "--machine", "../machines/my_delta", "export-model", "dp.json", "-o", "cal.xml",
                   says="cal.toml would be written beside this output")
    finally:
        (user / "work" / "cal.toml").unlink()


def test_the_api_save_guards_its_side_file(user, tmp_path):
    """README's API: ``table.save("t.json")`` beside a tracker campaign t.csv is refused; beside a table
    CSV of pmcal's it replaces it."""
    from pmcal.bridge.comptable import CompTable

    table = CompTable.load(_table(user, tmp_path))
    campaign = tmp_path / "t.csv"
    campaign.write_bytes((user / "work" / "t.csv").read_bytes())
    with pytest.raises(InputError, match="t.csv would be written beside"):
        table.save(tmp_path / "t.json")
    assert campaign.read_bytes() == (user / "work" / "t.csv").read_bytes() and not (tmp_path / "t.json").exists()
    table.save(tmp_path / "u.json")
    table.save(tmp_path / "u.json")                       # its own CSV: replaced
    assert CompTable.load(tmp_path / "u.csv").sha256() == table.sha256()


def _table(user: Path, tmp_path: Path) -> Path:
    cwd = os.getcwd()
    os.chdir(user / "work")
    try:
        assert main(["--quiet", "compensate", "params.json", "--table", str(tmp_path / "made.json"),
                     "--grid", "37,7", "--table-version", "3"]) == 0
    finally:
        os.chdir(cwd)
    return tmp_path / "made.json"


def test_check_output_refuses_the_working_folder_and_its_parents(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    for p in (".", "..", "/", str(tmp_path)):
        with pytest.raises(InputError, match="working folder"):
            check_output(p, folder=True, force=True)
    check_output("out", folder=True)                      # a new folder in the working folder: fine


def test_a_folder_is_replaced_only_when_pmcal_wrote_all_of_it(tmp_path):
    """The marker lists the files written; a file the user added later makes the folder the user's."""
    out = tmp_path / "report"
    with atomic_directory(out) as d:
        (d / "a.txt").write_text("1")
        (d / "deep").mkdir()
        (d / "deep" / "b.txt").write_text("2")
    assert (out / MARKER).read_text().splitlines()[1:] == ["a.txt", "deep/b.txt"]
    with atomic_directory(out) as d:                      # pmcal's own: replaced
        (d / "a.txt").write_text("3")
    assert (out / "a.txt").read_text() == "3" and not (out / "deep").exists()
    (out / "mine.tex").write_text("the user's")
    with pytest.raises(InputError, match="mine.tex, which pmcal did not write"):
        with atomic_directory(out) as d:
            (d / "a.txt").write_text("4")
    assert (out / "mine.tex").read_text() == "the user's" and (out / "a.txt").read_text() == "3"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report"]        # no staging left


def test_a_failed_swap_leaves_the_previous_folder(tmp_path, monkeypatch):
    """Built aside, the old folder renamed aside, the new one renamed in: if that last rename fails, the
    previous folder is back in place and nothing else is left."""
    out = tmp_path / "report"
    with atomic_directory(out) as d:
        (d / "a.txt").write_text("old")
    real = os.replace
    calls = []

    def failing(src, dst):
        calls.append((src, dst))
        if len(calls) == 2:                              # the new folder into place
            raise OSError(28, "No space left on device")
        return real(src, dst)

    monkeypatch.setattr(os, "replace", failing)
    with pytest.raises(OSError):
        with atomic_directory(out) as d:
            (d / "a.txt").write_text("new")
    monkeypatch.setattr(os, "replace", real)
    assert (out / "a.txt").read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report"]


def test_sigterm_cleans_up_as_ctrl_c_does(tmp_path):
    """SIGTERM during the Delta demo (the staging folder exists): exit 143, one line, nothing left."""
    env = dict(os.environ, MUJOCO_GL="egl")
    proc = subprocess.Popen([sys.executable, "-c", "from pmcal.cli import run; run()", "--machine", "delta_3dof",
                             "demo"], cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    for _ in range(1200):                                 # wait (at most 120 s) for the staging folder
        if list(tmp_path.glob(".pmcal-demo.*")) or proc.poll() is not None:
            break
        time.sleep(0.1)
    assert proc.poll() is None, proc.communicate()
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 143, err
    assert err.strip() == "pmcal: terminated; nothing half-written"
    assert list(tmp_path.iterdir()) == []


def test_identify_history_into_a_read_only_folder_writes_nothing(user, capsys):
    hist = user / "work" / "hist"
    hist.mkdir()
    hist.chmod(0o555)
    try:
        refused_in(user, capsys, "identify", "m.csv", "-o", "new.json", "--history", "hist",
                   says="field '--history': cannot write hist/record.json: the folder hist is not writable")
    finally:
        hist.chmod(0o755)
        hist.rmdir()
