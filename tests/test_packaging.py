"""The wheel a user installs: one import name, the models and PLC sources inside, and it runs.

Builds the wheel (not editable), installs it into a fresh virtual environment outside the repository and
runs ``pmcal twin measure``, ``pmcal identify`` and the README's API snippet there. The new environment
borrows the test environment's third-party packages through a path entry (the network may not be
there, and a fresh download of MuJoCo would cost minutes); pmcal itself comes only from the wheel: an
editable install's finder is not active through a plain path entry, and the test checks where pmcal
was imported from.
"""

from __future__ import annotations

import os
import subprocess
import sys
import sysconfig
import tomllib
import venv
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())


def test_package_list_covers_every_folder():
    tool = PYPROJECT["tool"]["setuptools"]
    expected = set()
    for name, folder in tool["package-dir"].items():
        for init in (ROOT / folder).rglob("__init__.py"):
            rel = init.parent.relative_to(ROOT / folder).parts
            expected.add(".".join((name, *rel)))
    assert set(tool["packages"]) == expected


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("wheel")
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w",
                    str(out), str(ROOT)], check=True, capture_output=True, timeout=300)
    (whl,) = out.glob("pmcal-*.whl")
    return whl


def test_wheel_owns_one_import_name_and_ships_its_data(wheel):
    names = zipfile.ZipFile(wheel).namelist()
    top = {n.split("/")[0] for n in names if not n.split("/")[0].endswith(".dist-info")}
    assert top == {"pmcal"}
    for need in ("pmcal/mjcf/ocpm_2dof/ocpm_2dof.xml", "pmcal/mjcf/ocpm_2dof/machine.toml",
                 "pmcal/mjcf/planar_2dof/scene.xml", "pmcal/plc/POUs/FB_CompTableLookup.TcPOU",
                 "pmcal/plc/GVLs/GVL_CompTable.TcGVL", "pmcal/plc/DUTs/ST_CompTableHeader.TcDUT",
                 "pmcal/calib/ocpm/fullchain.py", "pmcal/twin/ocpm/forward.py", "pmcal/mechanism/ocpm/config.py",
                 "pmcal/bridge/simulator/plc_runtime/library.st", "pmcal/bridge/simulator/plc_runtime/compiler.py"):
        assert need in names, need


SNIPPET = """
import pmcal
from pmcal.bridge.simulator.ads_mock import AdsMockPlc
meas = pmcal.read_measurements("m.csv")
cal = pmcal.identify(meas)
m = cal.setpoints([0.0, 90.0], [10.0, 30.0])
table = cal.compensation_table(version=7)
table.save("t.json")
with AdsMockPlc(lifetime_s=60.0) as plc:
    report = pmcal.push(table, ads=plc.target)
print(pmcal.__file__, m.shape, report.result, report.version)
"""


def test_wheel_runs_outside_the_repository(wheel, tmp_path):
    env_dir = tmp_path / "venv"
    venv.EnvBuilder(with_pip=False).create(env_dir)
    py = env_dir / "bin" / "python"
    site = Path(subprocess.run([py, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                               check=True, capture_output=True, text=True).stdout.strip())
    (site / "borrowed.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    subprocess.run([sys.executable, "-m", "pip", "--python", str(py), "install", "--no-deps", "-q", str(wheel)],
                   check=True, capture_output=True, timeout=300)
    work = tmp_path / "user"
    work.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    env["MUJOCO_GL"] = env.get("MUJOCO_GL", "egl")
    pmcal_cli = env_dir / "bin" / "pmcal"

    def run(*args):
        return subprocess.run(args, cwd=work, env=env, capture_output=True, text=True, timeout=300)

    r = run(pmcal_cli, "twin", "measure", "--preset", "paper-table2", "--poses", "24", "--seed", "1", "-o", "m.csv")
    assert r.returncode == 0, r.stderr
    r = run(pmcal_cli, "identify", "m.csv", "-o", "params.json")
    assert r.returncode == 0, r.stderr
    r = run(py, "-c", SNIPPET)
    assert r.returncode == 0, r.stderr
    where, *rest = r.stdout.split()
    assert Path(where).is_relative_to(site) and rest == ["(2,", "2)", "ok", "7"]
    assert (work / "t.json").is_file()
