"""The diagnosis of a machine folder (:mod:`pmcal.calib.chain_diagnose`) on campaigns of the Delta made by an
independent simulator (tests/chain_effects.py: closed-form kinematics, effects in their own physical form):
each effect gets its own name and value, a clean campaign none, and effects shaped unlike every family
get no name but "unexplained" with what they follow. 96 poses, tracker noise 0.01 mm, one seed per case
(the 20-seed rates: benchmarks/chain_diagnose_bench.py)."""

import json
import shutil

import numpy as np
import pytest

from pmcal.calib.chain_diagnose import diagnose_chain
from pmcal.calib.closed_chain import identify_chain
from pmcal.cli import main
from pmcal.io_chain import ChainMeasurements, write_measurements
from pmcal.machines import Machine
from pmcal.mechanism.motion import approach_from_order
from pmcal.mjcf import machine_dir
from tests.chain_effects import delta_campaign, last_move

SIGMA = 0.01


@pytest.fixture(scope="module")
def delta():
    return Machine.builtin("delta_3dof")


def diagnose(delta, seed=0, **effects):
    cmd, y, t, temp = delta_campaign(96, np.random.default_rng(seed), sigma=SIGMA, **effects)
    base = identify_chain(delta.twin, cmd, y, SIGMA)
    return diagnose_chain(delta.twin, cmd, y, base, time_s=t, temp_c=temp)


def test_approach_signs_agree_with_the_simulators():
    cmd = np.random.default_rng(1).uniform(-30, 60, size=(40, 3))
    cmd[5, 1] = cmd[4, 1]                                   # a motor that does not move keeps its sign
    assert np.array_equal(approach_from_order(cmd), last_move(cmd))


def test_clean_campaign_names_nothing(delta):
    dg = diagnose(delta)
    assert dg.verdict == "noise" and not dg.named, dg.summary()


@pytest.mark.parametrize("effects, name, motors, label, value", [
    (dict(backlash=(0.0, 0.03, 0.0)), "backlash", ["m2"], "m2.dead_band", 0.03),
    (dict(drift=(0.02, 0.0, 0.0)), "zero_drift", ["m1"], "m1.rate", 0.02),
    (dict(frame=(0.05, -0.03, 0.02, 0.0, 0.0, 0.002)), "frame_drift", [], "v_x", 0.05),
    (dict(alpha=20e-6), "thermal_expansion", [], "alpha", 20e-6),
])
def test_each_effect_gets_its_name_motor_and_value(delta, effects, name, motors, label, value):
    dg = diagnose(delta, **effects)
    assert [e.name for e in dg.named] == [name], dg.summary()
    e = dg.named[0]
    assert e.motors == motors
    i = e.labels.index(label)
    assert abs(e.values[i] - value) < 4.0 * e.std[i], (e.values[i], e.std[i])     # 4 sigma: one seed per case
    assert e.held_out_share > 0.5 and dg.gap_after < 1.2 * SIGMA * 1.1


@pytest.mark.parametrize("effects, follows", [(dict(sag=0.05), "distance from the z axis"),
                                              (dict(harmonic=0.01), None)])
def test_effects_unlike_every_family_are_not_named(delta, effects, follows):
    dg = diagnose(delta, **effects)
    assert not dg.named and dg.verdict == "unexplained", dg.summary()
    assert dg.unexplained["excess_mm"] > 0.3 * SIGMA
    if follows:
        assert follows in dg.unexplained["correlates"][0]["context"]


def test_diagnose_command_on_a_machine_folder(tmp_path, capsys):
    """``pmcal --machine DIR diagnose``: one line naming the effect and its motor, the JSON with per-motor
    values and intervals."""
    folder = tmp_path / "my_delta"
    shutil.copytree(machine_dir("delta_3dof"), folder)
    spec = Machine.from_folder(folder).spec
    cmd, y, t, temp = delta_campaign(96, np.random.default_rng(3), backlash=(0.04, 0.0, 0.0), sigma=SIGMA)
    write_measurements(tmp_path / "m.csv", spec, ChainMeasurements([f"P{i + 1}" for i in range(96)], cmd, y,
                                                                   time_s=t, temp_c=temp))
    capsys.readouterr()
    assert main(["--machine", str(folder), "diagnose", str(tmp_path / "m.csv"), "--json", str(tmp_path / "d.json")]) == 0
    out = capsys.readouterr().out
    assert out.startswith("backlash (m1): m1.dead_band 0.0")
    doc = json.loads((tmp_path / "d.json").read_text())
    assert doc["verdict"] == "named" and doc["named"][0]["motors"] == ["m1"]
    v = doc["named"][0]["values"]["m1.dead_band"]
    lo, hi = v["interval"]
    assert abs(hi - lo - 2 * 1.96 * v["std"]) < 1e-12 and abs(v["value"] - 0.04) < 4 * v["std"]
