"""The library API reads the same for every machine (INTERFACES.md, "Python API"): read the campaign with
its machine, identify, setpoints for task targets, the PLC table where the machine has one, save and load.

The folder machines' campaigns come from the second simulator (tests/crosssim_chain: plain MuJoCo and
scipy, its own error parameterisation and loop solver), with random errors of machine.toml's sizes and
0.01 mm tracker noise on 48 planned poses; the setpoints are judged by driving that simulator. At this noise
the task error pmcal predicts after calibration is about 0.004 mm (benchmarks/corpus_crosssim_bench.py,
benchmarks/large_errors_bench.py); the bound below, 0.02 mm (and 0.01 deg), is five times that, for the
largest of 8 targets. ocpm_2dof's campaign comes from its twin (tests/test_api.py has the detail).
"""

from __future__ import annotations

import numpy as np
import pytest

import pmcal
from pmcal import chain
from pmcal.errors import InputError
from pmcal.io_chain import ChainMeasurements, write_measurements
from tests.crosssim_chain.machine import SimMachine

NOISE_MM = 0.01
BOUND_MM, BOUND_DEG = 0.02, 0.01


def _simulated_campaign(machine, path, seed: int) -> SimMachine:
    """The second simulator's machine with random errors, measured at pmcal's 48 planned poses into ``path``."""
    rng = np.random.default_rng(seed)
    sim = SimMachine(machine.folder)
    sim = SimMachine(machine.folder, sim.random_errors(rng))
    commands = chain.plan(machine, 48, seed=seed).commands
    nests = sim.nests(commands) + rng.normal(0.0, NOISE_MM, (len(commands), len(machine.spec.targets), 3))
    write_measurements(path, machine.spec, ChainMeasurements(
        pose_id=[f"P{i + 1}" for i in range(len(commands))], commands=commands, targets=nests))
    return sim


@pytest.mark.parametrize("name", ["delta_3dof", "hexapod_6dof"])
def test_the_same_lines_calibrate_a_folder_machine(name, tmp_path):
    machine = pmcal.Machine.builtin(name)
    sim = _simulated_campaign(machine, tmp_path / "m.csv", seed=5)
    task = chain.sample_targets(machine, 8, seed=3)

    meas = pmcal.read_measurements(tmp_path / "m.csv", machine)
    cal = pmcal.identify(meas)
    commands = cal.setpoints(task)
    cal.save(tmp_path / "p.json")
    again = pmcal.load_calibration(tmp_path / "p.json", machine)

    assert isinstance(cal, pmcal.ChainCalibration) and cal.usable, cal.quality
    after, before = sim.task(commands) - task, sim.task(machine.twin.inverse(task, None)) - task
    position = [i for i, c in enumerate(machine.spec.task.coordinates) if c.endswith("_mm")]
    angle = [i for i, c in enumerate(machine.spec.task.coordinates) if c.endswith("_deg")]
    assert np.abs(after[:, position]).max() < BOUND_MM, after
    assert np.abs(after[:, angle]).max(initial=0.0) < BOUND_DEG, after
    assert np.abs(before[:, position]).max() > 20 * np.abs(after[:, position]).max()
    assert again.params == cal.params
    np.testing.assert_allclose(again.setpoints(task), commands, rtol=0, atol=1e-9)
    if machine.spec.table_axes:
        table = cal.compensation_table(version=7, grid=[3] * len(machine.spec.table_axes))
        assert table.version == 7 and table.machine == machine.name
        node = table.nodes().reshape(-1, len(table.axes))[1:2]                      # a node: the correction is calibrated - nominal IK
        np.testing.assert_allclose(table.values.reshape(-1, table.n_motors)[1],
                                   (cal.setpoints(node) - machine.twin.inverse(node, None))[0], atol=1e-9)
    else:
        with pytest.raises(InputError):
            cal.compensation_table(version=7)


def test_ocpm_takes_its_targets_as_one_array_like_every_machine(tmp_path):
    from pmcal.io_ocpm import write_measurements as write_ocpm
    from pmcal.twin.campaign import plan_campaign, run_campaign
    from pmcal.twin.machine import Twin
    from pmcal.twin.tracker import LaserTracker
    from pmcal.mechanism.ocpm.params import PAPER_TABLE2

    write_ocpm(tmp_path / "m.csv", run_campaign(Twin(PAPER_TABLE2), plan_campaign(24, 60.0, 3),
                                                 LaserTracker(NOISE_MM, np.random.default_rng(4))))
    cal = pmcal.identify(pmcal.read_measurements(tmp_path / "m.csv", pmcal.Machine.builtin("ocpm_2dof")))
    task = np.array([[0.0, 10.0], [45.0, 30.0]])
    np.testing.assert_allclose(cal.setpoints(task), cal.setpoints(task[:, 0], task[:, 1]), rtol=0, atol=1e-9)
    # the frame as the second positional argument, as before machines
    assert len(pmcal.read_measurements(tmp_path / "m.csv", "tracker")) == 24


def test_a_machine_without_a_library_api_is_named_and_a_campaign_without_its_machine_refused(tmp_path):
    with pytest.raises(InputError, match="planar_2dof"):
        pmcal.read_measurements(tmp_path / "m.csv", "planar_2dof")
    meas, _ = chain.campaign(pmcal.Machine.builtin("delta_3dof"), 12, seed=1)
    orphan = ChainMeasurements(pose_id=meas.pose_id, commands=meas.commands, targets=meas.targets)
    with pytest.raises(InputError, match="does not know its machine"):
        pmcal.identify(orphan)
    with pytest.raises(InputError, match="sigma_mm"):
        pmcal.identify(meas, model="paper")
