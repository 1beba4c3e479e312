"""The Delta robot's whole chain to a pushed 3-axis table, as a user runs it: ``pmcal --machine <copy of
mjcf/delta_3dof> twin measure``, ``identify``, ``compensate --table``, ``pmcal push`` to ``pmcal mock-plc``
(ADS, a subprocess), then the PLC's lookup (FB_CompTableLookup, interpreted ST) at held-out targets drives
the *true* (error-perturbed) twin.

Tolerance, per target t (mm):
  e(t) <= e_direct(t) + |J| * e_interp + 1e-6
- e_direct: the exact identified inverse kinematics' own error on the true machine (what the identification
  leaves: tracker noise 0.01 mm over 48 poses gives a few micrometres; asserted < 0.05 mm, 5 sigma);
- e_interp: the trilinear interpolation bound per motor, sum over axes of h_a^2 / 8 * |d2m/dx_a^2| (h_a the
  node spacing, the second derivative by central differences of the identified IK over +-h_a/2 at t, times 2
  for its variation over the cell), as a vector norm over the motors (deg);
- |J|: the 2-norm of d task / d commands of the true machine at t (mm/deg, central differences).
The test can fail: the nominal IK (no calibration) misses the targets by far more (asserted > 10x e_direct),
and the table's error must stay below a quarter of the nominal IK's (13 x 13 x 9 grid, 25 mm spacing).
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
    table = CompTable.load("t.json")
    assert (table.n_axes, table.n_motors, table.reference) == (3, 3, None)

    proc = subprocess.Popen([sys.executable, "-m", "pmcal.cli", "mock-plc", "--ads", "--seconds", "120"],
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
                assert (out.result, out.n_motors, out.table_version) == (LookupResult.OK, 3, 11)
                plc.append(out.m)
    finally:
        proc.terminate()
        proc.communicate(timeout=10)
    plc = np.array(plc)
    reached = twin.forward(plc, truth)
    err = np.linalg.norm(reached - held, axis=1)

    direct = twin.inverse(held, params)                     # exact identified IK, no table
    e_direct = np.linalg.norm(twin.forward(direct, truth) - held, axis=1)
    e_nominal = np.linalg.norm(twin.forward(twin.inverse(held, None), truth) - held, axis=1)
    h = (hi - lo) / (np.array(table.shape) - 1)
    curv = np.zeros((len(held), 3))
    for a in range(3):
        d = np.zeros(3)
        d[a] = h[a] / 2
        second = (twin.inverse(held + d, params) - 2 * direct + twin.inverse(held - d, params)) / (h[a] / 2) ** 2
        curv += 2.0 * h[a] ** 2 / 8.0 * np.abs(second)
    e_interp = np.linalg.norm(curv, axis=1)                 # deg
    jac = np.zeros((len(held), 3, 3))
    for k in range(3):
        dm = np.zeros(3)
        dm[k] = 1e-3
        jac[:, :, k] = (twin.forward(plc + dm, truth) - twin.forward(plc - dm, truth)) / 2e-3
    gain = np.linalg.norm(jac, ord=2, axis=(1, 2))          # mm / deg
    tol = e_direct + gain * e_interp + 1e-6
    print(f"\ntable error max {err.max():.4g} mm, direct {e_direct.max():.4g} mm, interpolation bound "
          f"{(gain * e_interp).max():.4g} mm, nominal IK {e_nominal.min():.4g}..{e_nominal.max():.4g} mm")
    assert e_direct.max() < 0.05, e_direct
    assert np.all(err <= tol), (err, tol)
    assert e_nominal.min() > 10 * e_direct.max()             # the calibration matters: the test can fail
    assert err.max() < e_nominal.min() / 4                    # and the table carries it to the machine
