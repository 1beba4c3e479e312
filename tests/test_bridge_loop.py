"""Twin in the loop: the MuJoCo twin with the paper's Table 2 errors asks a mock PLC for its motor
targets, before and after the compensation table is pushed, and a virtual tracker measures."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pmcal.bridge.simulator.ads_mock import AdsMockPlc
from pmcal.apps.ocpm.plc_loop import DEFAULT_GRID, compensation_table, run_loop
from pmcal.bridge.simulator.modbus_mock import ModbusMockPlc
from pmcal.mechanism.ocpm.config import default_geometry
from pmcal.mechanism.ocpm.params import PAPER_TABLE2, ErrorSet
from pmcal.cli import main
from tests.bridge_fixtures import running

GEOM = default_geometry()
ERRORS = ErrorSet.from_dict(PAPER_TABLE2, GEOM.n_limbs, GEOM.actuated)
#: pointing noise of one tracker-measured pose: sigma / target lever (~100 mm) rad, in deg
NOISE_DEG = np.rad2deg(GEOM.sigma_mm / 100.0)


@pytest.fixture(scope="module")
def table():
    return compensation_table(ERRORS, DEFAULT_GRID, version=2, geom=GEOM)


@pytest.mark.parametrize("mock", [AdsMockPlc, ModbusMockPlc], ids=["ads", "modbus"])
def test_pointing_error_before_and_after_the_push(mock, table):
    with running(mock(lifetime_s=120.0)) as plc:
        res = run_loop(plc, ERRORS, table, n_targets=24, seed=3)
    assert res.push.result == "ok" and res.table_version == 2
    assert res.extra["plc_equals_table_interpolation"]           # the PLC's bilinear = the Python one
    before, after, direct = res.before.summary(), res.after.summary(), res.direct.summary()
    assert before["true_rms_deg"] > 0.5                         # paper Table 2 errors, nominal controller
    assert after["true_rms_deg"] < before["true_rms_deg"] / 20   # the table does its job ...
    assert direct["true_max_deg"] < 1e-4                         # ... up to its interpolation error
    assert after["true_max_deg"] < 0.1
    for p in (res.before, res.after, res.direct):                # the tracker sees it within its noise
        assert np.abs(p.measured_deg - p.true_deg).max() < 6 * NOISE_DEG


def test_loop_command_reports_before_and_after(tmp_path, capsys):
    out = tmp_path / "loop.json"
    assert main(["loop", "--transport", "modbus", "--targets", "8", "--grid", "37,13", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "before push (nominal table)" in text and "after push" in text
    doc = json.loads(out.read_text())
    assert doc["before"]["rms_deg"] > 5 * doc["after"]["rms_deg"] and doc["plc_equals_table_interpolation"]
