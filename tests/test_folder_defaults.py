"""Defaults that work (issue 34). A compensation table on machine.toml's defaults: a workspace box whose
corners the machine does not reach, and no ``[table]`` span or ``max_correction`` (the Delta's folder with
those lines removed and the workspace widened to x, y in [-400, 400] mm).

- The default box is the largest (uniform scaling about the workspace's centre, to 1 %) whose nodes the
  nominal machine reaches inside its motor ranges: every node is reached; 3 % larger, one is not.
- The default correction bound is 5 standard deviations of the correction random errors of the toml's sizes
  call for (linearised): checked against the corrections of 8 random error sets drawn here and put through the
  twin's exact inverse kinematics (the bound exceeds them all; the linearised sigma matches their spread
  within the sampling error of 8 draws).
- A refusal names machine.toml.
- The demo leaves out a held-out target the identified machine does not reach, with a warning naming it.
"""

import json
import re
import shutil

import numpy as np
import pytest

from pmcal.bridge.comptable import CompTable
from pmcal.chain import CORRECTION_SIGMAS, TABLE_RANGE_MARGIN, compensate, random_errors
from pmcal.cli import main
from pmcal.machines import Machine
from pmcal.mjcf import machine_dir


@pytest.fixture(scope="module")
def wide(tmp_path_factory):
    folder = tmp_path_factory.mktemp("tables") / "wide_delta"
    shutil.copytree(machine_dir("delta_3dof"), folder)
    toml = folder / "machine.toml"
    text = toml.read_text()
    table = text.index("[table]")
    head, tail = text[:table], text[table:]
    tail = re.sub(r"^(x_mm|y_mm|z_mm|max_correction) = .*\n", "", tail, flags=re.M)
    head = head.replace("x_mm = [-250.0, 250.0]", "x_mm = [-400.0, 400.0]")
    head = head.replace("y_mm = [-250.0, 250.0]", "y_mm = [-400.0, 400.0]")
    toml.write_text(head + tail)
    return folder


def _nodes(table: CompTable) -> np.ndarray:
    return table.nodes().reshape(-1, table.n_axes)


def test_default_box_is_the_largest_reachable_and_bound_follows_the_errors(wide, tmp_path, capsys):
    (tmp_path / "p.json").write_text(json.dumps({"mechanism": "delta_3dof", "params": {}}))
    assert main(["--quiet", "--machine", str(wide), "compensate", str(tmp_path / "p.json"), "--table",
                 str(tmp_path / "t.json"), "--grid", "5,5,4"]) == 0
    table = CompTable.load(tmp_path / "t.json")
    machine = Machine.from_folder(wide)
    twin, spec = machine.twin, machine.spec
    ws = spec.workspace
    lo = np.array([a.min for a in table.axes])
    hi = np.array([a.max for a in table.axes])
    assert np.all(lo >= [ws[a.column][0] for a in table.axes]) and np.all(hi <= [ws[a.column][1] for a in table.axes])
    assert hi[0] - lo[0] < 800.0                                       # the corners were out of reach
    rng_ = np.array([m.range for m in spec.motors])
    inner = rng_ + np.outer(np.ptp(rng_, axis=1) * TABLE_RANGE_MARGIN, [1, -1])

    def reached(nodes):
        cmd = twin.inverse(nodes, None)
        return np.isfinite(cmd).all() and np.all((cmd >= inner[:, 0]) & (cmd <= inner[:, 1]))

    assert reached(_nodes(table))
    centre = (np.array([ws[a.column][0] for a in table.axes]) + [ws[a.column][1] for a in table.axes]) / 2
    assert not reached(centre + (_nodes(table) - centre) * 1.03)

    # the bound against corrections of random error sets through the exact IK (not the linearisation)
    bound = table.motors[0].max
    assert 1.0 < bound < 5.0
    nodes = _nodes(CompTable.load(tmp_path / "t.json"))[::7]
    nominal = twin.inverse(nodes, None)
    rng = np.random.default_rng(5)
    corr = np.array([compensate(machine, random_errors(machine, rng), nodes) - nominal for _ in range(8)])
    assert np.isfinite(corr).all() and np.abs(corr).max() < bound
    spread = np.sqrt(np.mean(corr ** 2, axis=0)).max()                 # the largest RMS correction over nodes
    assert 0.5 < spread / (bound / CORRECTION_SIGMAS) < 2.0            # 8 draws: RMS to about +-25 %


def test_a_refused_table_names_machine_toml(wide, tmp_path, capsys):
    toml = wide / "machine.toml"
    text = toml.read_text()
    try:
        toml.write_text(text.replace("max_correction_step = 0.25", "max_correction = 0.01\nmax_correction_step = 0.25"))
        (tmp_path / "p.json").write_text(json.dumps({"mechanism": "delta_3dof", "params": {"m1.dzero": 0.2}}))
        assert main(["--machine", str(wide), "compensate", str(tmp_path / "p.json"), "--table",
                     str(tmp_path / "t.json"), "--grid", "3,3,2"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "machine.toml" in err[0] and "table node" in err[0] and "max_correction 0.01" in err[0]
    finally:
        toml.write_text(text)


def test_demo_leaves_out_an_unreachable_held_out_target_naming_it(capsys):
    """A held-out target the identified machine does not reach (here one 2 m below the Delta) is left out
    of the demo's evaluation with one warning line naming it and its coordinates, not the end of the demo."""
    from pmcal.studies.chain_demo import reachable_targets

    machine = Machine.resolve("delta_3dof")
    task = np.array([[0.0, 0.0, -800.0], [0.0, 0.0, -2800.0], [50.0, 0.0, -750.0]])
    kept, commands = reachable_targets(machine, {}, task)
    np.testing.assert_array_equal(kept, task[[0, 2]])
    np.testing.assert_allclose(commands, machine.twin.inverse(task[[0, 2]], None), atol=1e-9)
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "held-out target 2" in err[0] and "z_mm=-2800" in err[0] and "warning" in err[0]
