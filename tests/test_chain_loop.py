"""Twin in the loop for a machine folder (``pmcal --machine DIR loop``, pmcal/apps/chain_loop.py): a copy of
the Delta's folder with random geometric errors of its [errors] sizes, the demo's planned campaign and
identification, the 3-axis table of corrections pushed over ADS and over Modbus to the strict mock PLCs, and
at held-out targets inside the grid the command the integrator drives: the controller's nominal IK plus the
PLC's looked-up correction (FB_CompTableLookup, interpreted ST, read back over the transport).

Tolerances (mm, per target):
- before the push (nominal table: every correction 0) the command is the nominal IK (to 1e-9 deg: the IK's
  Newton iteration ends within ~1e-13 deg of itself from another warm start), so the true error equals the
  nominal IK's on the true twin (to 1e-9 mm); > 1 mm for the Delta's default error sizes (0.5 mm / 0.1 deg
  per frame);
- after the push: at most the exact identified IK's own error (direct, no table) plus the interpolation
  bound of the correction field (tests/table_bounds.py, as tests/test_delta_table_chain.py) + 1e-6;
- the direct error < 0.05 mm (tracker noise 0.01 mm over 48 planned poses leaves a few micrometres);
- the tracker's reading of the task site (the rigid fit of the 3 nests, 50 mm from the platform's axis; the
  TCP 20 mm below their plane) differs from the true one by the fit's noise: per coordinate about 0.7 sigma
  (the nests' centroid sigma/sqrt(3), the tilt over the 20 mm lever), so by < 5 sigma = 0.05 mm in distance.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from pmcal.apps.chain_loop import (PUSHED_VERSION, TARGET_SEED, calibrate, grid_targets, nominal_table,
                                   run_chain_loop)
from pmcal.bridge.simulator.ads_mock import AdsMockPlc
from pmcal.bridge.simulator.modbus_mock import ModbusMockPlc
from pmcal.cli import main
from pmcal.machines import Machine
from pmcal.mjcf import machine_dir
from tests.bridge_fixtures import running
from tests.chain_references import DELTA, delta_ik
from tests.table_bounds import interpolation_bound_mm


def _copy(name: str, dest):
    folder = dest / f"my_{name}"
    shutil.copytree(machine_dir(name), folder)
    return folder


@pytest.fixture(scope="module")
def delta(tmp_path_factory):
    """A copy of the Delta's folder elsewhere and the loop's calibration of its twin (seed 1, default grid)."""
    folder = _copy("delta_3dof", tmp_path_factory.mktemp("loop"))
    machine = Machine.from_folder(folder)
    return machine, calibrate(machine, seed=1)


@pytest.mark.parametrize("mock", [AdsMockPlc, ModbusMockPlc], ids=["ads", "modbus"])
def test_the_pushed_table_brings_the_true_twin_to_the_held_out_targets(mock, delta):
    machine, cal = delta
    twin, truth, params = machine.twin, cal.truth, cal.result.params
    with running(mock(lifetime_s=120.0)) as plc:
        res = run_chain_loop(plc, machine, cal, n_targets=12, seed=4)
    assert res.push.result == "ok" and res.table_version == PUSHED_VERSION and res.by_tracker
    assert res.extra["plc_equals_table_lookup"]                 # the PLC's trilinear = the Python one
    task = res.task
    lo, hi = (np.array([getattr(a, k) for a in cal.table.axes]) for k in ("min", "max"))
    assert np.all((task >= lo) & (task <= hi))                  # inside the grid

    nominal = twin.inverse(task, None)
    # correction 0: the controller as commissioned (the IK's Newton ends within 1e-12 of itself, from any start)
    np.testing.assert_allclose(res.before.commands, nominal, rtol=0, atol=1e-9)
    np.testing.assert_allclose(nominal, delta_ik(task - [0.0, 0.0, DELTA["tcp"]]), rtol=0, atol=1e-6)
    e_nominal = np.linalg.norm(twin.forward(nominal, truth) - task, axis=1)
    np.testing.assert_allclose(res.before.true_mm, e_nominal, rtol=0, atol=1e-9)
    assert e_nominal.min() > 1.0

    np.testing.assert_allclose(res.direct.commands, twin.inverse(task, params), rtol=0, atol=1e-9)
    assert res.direct.true_mm.max() < 0.05
    bound = interpolation_bound_mm(twin, params, truth, cal.table, task, res.after.commands)
    print(f"\n{res.transport}: true error before {res.before.true_mm.min():.4g}..{res.before.true_mm.max():.4g} mm, "
          f"after max {res.after.true_mm.max():.4g} mm, direct max {res.direct.true_mm.max():.4g} mm, "
          f"interpolation bound max {bound.max():.4g} mm")
    assert np.all(res.after.true_mm <= res.direct.true_mm + bound + 1e-6), (res.after.true_mm, res.direct.true_mm,
                                                                           bound)
    assert res.after.true_mm.max() < e_nominal.min() / 50      # the table carries the calibration
    for state in (res.before, res.after, res.direct):          # the tracker sees it within its noise
        assert np.abs(state.measured_mm - state.true_mm).max() < 5 * machine.spec.sigma_mm


@pytest.mark.slow
def test_a_table_of_absolute_commands_starts_from_the_nominal_ik_table(tmp_path):
    """[table] reference = "none": the nominal table holds the nominal IK's commands at the nodes, the pushed
    one the identified IK's; after the push the error is the direct one plus the interpolation bound of the
    identified IK itself (a few tenths of a mm on the Delta's grid, tests/table_bounds.py)."""
    folder = _copy("delta_3dof", tmp_path)
    toml = folder / "machine.toml"
    toml.write_text(toml.read_text().replace('reference = "controller"', 'reference = "none"'))
    machine = Machine.from_folder(folder)
    cal = calibrate(machine, seed=1)
    assert cal.table.reference is None
    with running(AdsMockPlc(lifetime_s=120.0)) as plc:
        res = run_chain_loop(plc, machine, cal, n_targets=8, seed=4)
    twin, task = machine.twin, res.task
    assert res.push.result == "ok" and res.extra["plc_equals_table_lookup"]
    nominal = nominal_table(machine, cal.table)
    np.testing.assert_allclose(nominal.values.reshape(-1, 3), twin.inverse(
        nominal.nodes().reshape(-1, 3), None), rtol=0, atol=1e-9)
    np.testing.assert_allclose(res.before.commands, nominal.lookup(task), rtol=0, atol=1e-9)   # IK made again
    np.testing.assert_array_equal(res.after.commands, cal.table.lookup(task))
    bound = interpolation_bound_mm(twin, cal.result.params, cal.truth, cal.table, task, res.after.commands)
    assert np.all(res.after.true_mm <= res.direct.true_mm + bound + 1e-6)
    assert res.after.true_mm.max() > 10 * res.direct.true_mm.max()   # the interpolation shows: the test can fail


def test_loop_command_prints_and_writes_the_summary(delta, tmp_path, capsys):
    """``--errors P.json``: the twin has those errors (the fixture's); the targets are drawn from seed 2 + 1000
    inside the table's box, so the nominal IK's error before the push follows from them alone."""
    machine, cal = delta
    out, errors = tmp_path / "loop.json", tmp_path / "truth.json"
    errors.write_text(json.dumps({"mechanism": machine.name, "params": cal.truth}))
    assert main(["--machine", str(machine.folder), "loop", "--transport", "modbus", "--targets", "6",
                 "--grid", "7,7,5", "--seed", "2", "--errors", str(errors), "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "before push (nominal table)" in text and "after push" in text and "without table" in text
    doc = json.loads(out.read_text())
    assert {"machine", "transport", "targets", "grid", "axes", "reference", "table_version", "before", "after",
            "direct_no_table", "push", "identification", "plc_equals_table_lookup", "timings_s"} <= set(doc)
    assert (doc["transport"], doc["targets"], doc["grid"], doc["reference"], doc["push"]["result"]) == \
        ("modbus", 6, [7, 7, 5], "controller", "ok")
    for key in ("before", "after", "direct_no_table"):
        assert set(doc[key]) == {"rms_mm", "max_mm", "true_rms_mm", "true_max_mm"}
    task = grid_targets(machine, cal.table, 6, np.random.default_rng(2 + TARGET_SEED))
    e_nominal = np.linalg.norm(machine.twin.forward(machine.twin.inverse(task, None), cal.truth) - task, axis=1)
    assert doc["before"]["true_rms_mm"] == pytest.approx(np.sqrt(np.mean(e_nominal ** 2)), abs=1e-9)
    assert doc["before"]["true_rms_mm"] > 1.0 and doc["after"]["true_rms_mm"] < 0.05
    assert doc["plc_equals_table_lookup"]


@pytest.mark.parametrize("argv, says", [
    (["loop"], ["no compensation table for machine hexapod_6dof", "6 task coordinates", "compensate",
                "--targets"]),
    (["loop", "--targets", "0"], ["no compensation table"]),       # the machine first: no work at all
])
def test_a_machine_without_a_table_is_refused_in_one_line(argv, says, tmp_path, capsys):
    folder = _copy("hexapod_6dof", tmp_path)
    out = tmp_path / "loop.json"
    assert main(["--machine", str(folder), *argv, "--json", str(out)]) == 2
    cap = capsys.readouterr()
    lines = [x for x in cap.err.splitlines() if x.strip()]
    assert len(lines) == 1 and all(s in lines[0] for s in says), cap.err
    assert cap.out == "" and not out.exists()


def test_bad_loop_input_is_one_line(delta, tmp_path, capsys):
    machine, _ = delta
    for argv, says in ((["--targets", "0"], "field '--targets'"), (["--grid", "7,x"], "field '--grid'"),
                       (["--errors", str(tmp_path / "none.json")], "field '--errors'")):
        assert main(["--machine", str(machine.folder), "loop", *argv]) == 2
        lines = [x for x in capsys.readouterr().err.splitlines() if x.strip()]
        assert len(lines) == 1 and says in lines[0], lines
