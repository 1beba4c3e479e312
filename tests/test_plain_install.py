"""A plain install (``pip install pmcal``, without the ``sim`` extra) has no ST parser: it still identifies,
compensates, runs the demo and pushes a table to a real PLC; only the simulated PLC (mock servers,
``pmcal loop``) needs the extra, and says so in one line.

The commands run in a fresh interpreter in which ``blark`` cannot be imported (as in an environment that
never installed it); the PLC they push to is a mock served by this test process (which has the simulator),
standing for the real one.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from pmcal.bridge.simulator.modbus_mock import ModbusMockPlc
from pmcal.bridge.simulator.plc_runtime.source import SIMULATOR_MISSING
from tests.bridge_fixtures import running

ROOT = Path(__file__).resolve().parent.parent
WITHOUT_BLARK = "import sys\nsys.modules['blark'] = None\nfrom pmcal.cli import run\nsys.argv = ['pmcal'] + sys.argv[1:]\nrun()\n"


def pmcal_without_simulator(*args, cwd) -> subprocess.CompletedProcess:
    """``pmcal ARGS`` in a fresh interpreter without blark, and without the compiled-ST cache a session with
    the simulator may have left (``XDG_CACHE_HOME``: a plain install never had one)."""
    return subprocess.run([sys.executable, "-c", WITHOUT_BLARK, *args], cwd=cwd, capture_output=True, text=True,
                          timeout=600, env={**os.environ, "MUJOCO_GL": "egl", "XDG_CACHE_HOME": str(cwd / "cache")})


def test_the_st_parser_is_an_extra_and_the_tests_install_it():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert not any(d.startswith("blark") for d in project["dependencies"])
    assert any(d.startswith("blark") for d in project["optional-dependencies"]["sim"])
    assert "pmcal[sim]" in project["optional-dependencies"]["test"]


def test_identify_compensate_and_push_to_a_plc_without_the_simulator(tmp_path):
    def ok(*args):
        out = pmcal_without_simulator("--machine", "delta_3dof", *args, cwd=tmp_path)
        assert out.returncode == 0, out.stderr
        return out

    ok("twin", "measure", "--poses", "24", "-o", "m.csv")
    ok("identify", "m.csv", "-o", "p.json")
    ok("compensate", "p.json", "--table", "t.json", "--grid", "3,3,3", "--table-version", "5")
    with running(ModbusMockPlc(lifetime_s=120.0)) as plc:
        import numpy as np

        from pmcal.bridge.comptable import CompTable

        table = CompTable.load(tmp_path / "t.json")
        plc.twin.configure_for(table)
        out = pmcal_without_simulator("--machine", "delta_3dof", "push", "t.json", "--modbus", plc.target, "--no-audit",
                                      cwd=tmp_path)
        assert out.returncode == 0, out.stderr
        assert "version 5 active" in out.stdout
        assert np.array_equal(plc.twin.active_table()[1], table.values)


@pytest.mark.parametrize("args", [["loop", "--targets", "2"], ["mock-plc", "--modbus", "--seconds", "1"]])
def test_the_simulated_plc_says_what_to_install(tmp_path, args):
    out = pmcal_without_simulator(*args, cwd=tmp_path)
    assert out.returncode == 2
    assert out.stderr.strip().splitlines()[-1] == f"pmcal: error: {SIMULATOR_MISSING}"
