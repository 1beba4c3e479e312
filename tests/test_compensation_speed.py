"""The vectorised whole-chain compensation gives today's commands (reference saved before the speed-up) and
NaN, with a message, for targets out of reach instead of failing the batch."""

from pathlib import Path

import numpy as np
import pytest

from pmcal.compensators import FullCompensation
from pmcal.mechanism.ocpm.config import default_geometry
from pmcal.mechanism.ocpm.kinematics import nominal_ik
from pmcal.mechanism.ocpm.params import random_errors

REFERENCE = Path(__file__).parent / "data" / "fullchain_setpoints_6ec3c9e.csv"


def reference():
    lines = [line for line in REFERENCE.read_text().splitlines() if not line.startswith("#")]
    return np.genfromtxt(lines, delimiter=",", names=True)


@pytest.mark.parametrize("ratio", [1000.0, 100.0])
def test_commands_equal_the_reference_in_a_batch_and_one_by_one(ratio):
    d = reference()
    d = d[d["stiffness_ratio"] == ratio]
    ref = np.stack([d["m1_deg"], d["m2_deg"]], axis=1)
    comp = FullCompensation(random_errors(np.random.default_rng(7), 0.5, 0.1), ratio, default_geometry())
    batch = comp.commands_deg(d["phi_deg"], d["theta_deg"])
    assert np.array_equal(np.isnan(batch), np.isnan(ref))
    assert np.nanmax(np.abs(batch - ref)) < 1e-9
    assert "row 295 (phi 300, theta 89)" in comp.unreachable_message()
    some = np.r_[0:len(d):37, len(d) - 1]                 # one-target calls warm-start from each other
    single = np.concatenate([comp.commands_deg(d["phi_deg"][i:i + 1], d["theta_deg"][i:i + 1]) for i in some])
    assert np.array_equal(np.isnan(single), np.isnan(ref[some]))
    assert np.nanmax(np.abs(single - ref[some])) < 1e-9


def test_nominal_machine_commands_are_the_nominal_ik_and_unreachable_rows_are_nan():
    """Independent closed form: without errors the compensation is the nominal IK (seed eq. 12-13)."""
    rng = np.random.default_rng(3)
    phi, theta = rng.uniform(0, 360, 40), rng.uniform(0, 60, 40)
    phi[[5, 20]], theta[[5, 20]] = 45.0, 89.5               # beyond the workspace
    comp = FullCompensation({}, None, default_geometry())
    m = comp.commands_deg(phi, theta)
    expect = np.rad2deg(nominal_ik(np.deg2rad(phi), np.deg2rad(theta)))
    ok = np.ones(40, bool)
    ok[[5, 20]] = False
    # Newton stops at a pointing residual below 1e-7 deg: commands within a few 1e-7 deg
    assert np.abs(m[ok] - expect[ok]).max() < 1e-6
    assert np.isnan(m[~ok]).all() and list(comp.unreachable) == [5, 20]
