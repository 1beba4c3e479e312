"""The Delta robot's whole chain to a pushed 3-axis correction table, as a user runs it: ``pmcal --machine
<copy of mjcf/delta_3dof> twin measure``, ``identify``, ``compensate --table`` (default: corrections to the
controller's own nominal IK, nReference = 2), ``pmcal push`` to ``pmcal mock-plc`` (ADS, a subprocess), then
at held-out targets the integrator's command: the controller's nominal IK (here the Delta's textbook closed
form, tests/chain_references.py ``delta_ik``, written independently of pmcal) plus the PLC's looked-up
correction (FB_CompTableLookup, interpreted ST), driving the *true* (error-perturbed) twin.

Tolerance, per target t (mm): e(t) <= e_direct(t) + |J| * e_interp(t) + 1e-6 (tests/table_bounds.py): the
exact identified inverse kinematics' own error on the true machine (what the identification leaves: tracker
noise 0.01 mm over 48 poses gives a few micrometres; asserted < 0.05 mm, 5 sigma) plus the trilinear
interpolation bound of the correction field carried to the task by the machine's Jacobian.
The test can fail: the nominal IK (no calibration) misses the targets by far more (asserted > 10x e_direct),
and the same grid of absolute commands (``compensate --table --absolute``, 0.21 mm) misses them by more
than 10x the correction table's largest error.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pmcal.bridge.ads import AdsLink
from pmcal.bridge.ads_map import AdsTarget
from pmcal.bridge.comptable import CompTable
from pmcal.bridge.plc_types import LOOKUP_WRITES, LookupResult
from pmcal.cli import main as cli
from pmcal.io_chain import read_params
from pmcal.machines import Machine
from tests.bridge_fixtures import ROOT_DIR
from tests.chain_references import DELTA, delta_ik
from tests.table_bounds import interpolation_bound_mm
from tests.test_mock_plc_cli import _expect, _lines


def _true_errors(meas: Path) -> dict[str, float]:
    line = next(x for x in meas.read_text().splitlines() if x.startswith("# true errors"))
    return {k: float(v) for k, v in re.findall(r"([\w.]+)=([-+0-9.eE]+)", line.split(":", 1)[1])}


def test_delta_measure_identify_table_push_lookup_reaches_held_out_targets(tmp_path, monkeypatch):
    folder = tmp_path / "elsewhere" / "mydelta"
    shutil.copytree(Path(ROOT_DIR) / "mjcf" / "delta_3dof", folder)
    monkeypatch.chdir(tmp_path)
    m = ["--machine", str(folder)]
    assert cli([*m, "twin", "measure", "--poses", "48", "--seed", "3", "-o", "m.csv"]) == 0
    assert cli([*m, "identify", "m.csv", "-o", "p.json"]) == 0
    assert cli([*m, "compensate", "p.json", "--table", "t.json", "--table-version", "11"]) == 0
    assert cli([*m, "compensate", "p.json", "--table", "abs.json", "--table-version", "11", "--absolute"]) == 0
    table, absolute = CompTable.load("t.json"), CompTable.load("abs.json")
    assert (table.n_axes, table.n_motors, table.reference_code, absolute.reference) == (3, 3, 2, None)

    proc = subprocess.Popen([sys.executable, "-m", "pmcal.cli", *m, "mock-plc", "--ads", "--seconds", "120"],
                            cwd=ROOT_DIR, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=dict(os.environ, MUJOCO_GL="egl"))
    try:
        q = _lines(proc)
        target = _expect(q, "mock PLC (ads) at").split(" at ")[1].split(" for ")[0]
        assert cli([*m, "push", "t.json", "--ads", target]) == 0
        machine = Machine.from_folder(folder)
        twin = machine.twin
        truth = _true_errors(Path("m.csv"))
        params, _ = read_params("p.json", machine.spec, dict(zip(twin.error_keys, twin.error_units())))
        rng = np.random.default_rng(23)                     # held-out targets inside the table box, off nodes
        lo = np.array([a.min for a in table.axes])
        hi = np.array([a.max for a in table.axes])
        held = lo + (0.05 + 0.9 * rng.random((12, 3))) * (hi - lo)
        with AdsLink(AdsTarget.parse(target), timeout_s=2.0, writes=LOOKUP_WRITES) as link:
            plc = []
            for x in held:
                out = link.lookup(*x)
                assert (out.result, out.n_motors, out.table_version, out.correction) == (LookupResult.OK, 3, 11, True)
                plc.append(out.m)
    finally:
        proc.terminate()
        proc.communicate(timeout=10)
    tcp = np.array([0.0, 0.0, DELTA["tcp"]])
    controller = delta_ik(held - tcp)                       # the integrator's own nominal IK (deg)
    np.testing.assert_allclose(controller, twin.inverse(held, None), rtol=0, atol=1e-7)   # the same machine
    plc = controller + np.array(plc)                        # nominal IK + the PLC's correction
    reached = twin.forward(plc, truth)
    err = np.linalg.norm(reached - held, axis=1)
    err_absolute = np.linalg.norm(twin.forward(absolute.lookup(held), truth) - held, axis=1)

    direct = twin.inverse(held, params)                     # exact identified IK, no table
    e_direct = np.linalg.norm(twin.forward(direct, truth) - held, axis=1)
    e_nominal = np.linalg.norm(twin.forward(twin.inverse(held, None), truth) - held, axis=1)
    bound = interpolation_bound_mm(twin, params, truth, table, held, plc)
    tol = e_direct + bound + 1e-6
    print(f"\ncorrection table error max {err.max():.4g} mm, direct {e_direct.max():.4g} mm, interpolation "
          f"bound {bound.max():.4g} mm; absolute table {err_absolute.max():.4g} mm; nominal IK "
          f"{e_nominal.min():.4g}..{e_nominal.max():.4g} mm")
    assert e_direct.max() < 0.05, e_direct
    assert np.all(err <= tol), (err, tol)
    assert e_nominal.min() > 10 * e_direct.max()             # the calibration matters: the test can fail
    assert err.max() < err_absolute.max() / 10               # and the correction table carries it, not the IK
