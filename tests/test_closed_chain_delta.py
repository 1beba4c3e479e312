"""The generic closed-chain twin on the Delta (mjcf/delta_3dof, data only) against the Delta's closed form
(tests/chain_references.py), and its IFT Jacobian against central differences."""

import numpy as np
import pytest

from chain_references import DELTA, central_differences, delta_fk, delta_ik
from pmcal.mechanism.machine_spec import MachineSpec
from pmcal.mjcf import machine_dir
from pmcal.twin.closed_chain import ClosedChainTwin

TCP = np.array([0.0, 0.0, DELTA["tcp"]])


@pytest.fixture(scope="module")
def twin():
    return ClosedChainTwin(MachineSpec.load(machine_dir("delta_3dof")))


@pytest.fixture(scope="module")
def commands(twin):
    return twin.sample_commands(24, np.random.default_rng(11))


def test_structure_read_from_the_model(twin):
    assert [c.name for c in twin.closures] == [f"closure_{i}{s}" for i in (1, 2, 3) for s in "ab"]
    assert twin.n_equations == 18 and twin.n_motors == 3 and twin.n_targets == 3
    assert len(twin.passive) == 18                    # 6 rods x 2 (universal) + the floating platform's 6
    assert "m1.dzero" in twin.error_keys and "arm1.drz" in twin.error_keys
    assert not any(k.startswith("platform.") for k in twin.error_keys)       # free body: no frame error
    assert not any(k.startswith("nest") for k in twin.error_keys)          # nests define the platform frame


def test_home_keyframe_is_assembled(twin):
    p = twin.forward(twin.home_commands)[0] - TCP
    np.testing.assert_allclose(p, delta_fk(np.zeros((1, 3)))[0], atol=1e-9)
    np.testing.assert_allclose(twin.home_commands, 0.0, atol=1e-12)


def test_forward_matches_trilateration(twin, commands):
    task = twin.forward(commands)
    np.testing.assert_allclose(task - TCP, delta_fk(commands), atol=1e-8)     # mm
    nests = twin.targets(commands)
    for k, offset in enumerate(DELTA["nests"]):
        np.testing.assert_allclose(nests[:, k], delta_fk(commands) + offset, atol=1e-8)


def test_inverse_matches_closed_form(twin, commands):
    task = delta_fk(commands) + TCP
    np.testing.assert_allclose(twin.inverse(task), delta_ik(task - TCP), atol=1e-9)      # deg
    np.testing.assert_allclose(delta_ik(task - TCP), commands, atol=1e-9)


def test_inverse_out_of_reach_says_why(twin):
    """z = -2000 mm: farther than arm + rod; z = -490 mm (tcp; platform at -450): the closed form needs
    -46.3 deg on every motor, below the -35 deg limit of machine.toml. The motor is named by its column (m1)
    and by the joint machine.toml gave it: a user of LAAS's Talos-like leg read "m6 command -17.186 deg", six
    [[motors]] entries down from the joint names they wrote."""
    cmd, why = twin.inverse_report(np.array([[0.0, 0.0, -2000.0], [0.0, 0.0, -490.0], [0.0, 0.0, -700.0],
                                             [0.0, np.nan, -700.0]]))
    assert np.isnan(cmd[[0, 1, 3]]).all() and np.isfinite(cmd[2]).all() and why[2] == ""
    assert "missing (NaN)" in why[3]
    assert "no assembly" in why[0]
    assert why[1].startswith("m1 (joint arm1_motor) command -46.28") and "outside its range [-35, 80]" in why[1]


def test_samples_respect_workspace_and_motor_ranges(twin, commands):
    assert commands.shape == (24, 3)
    lo, hi = twin.motor_range[:, 0], twin.motor_range[:, 1]
    assert np.all((commands >= lo) & (commands <= hi))
    task = twin.forward(commands)
    for c, (a, b) in zip(task.T, (twin.spec.workspace[k] for k in twin.spec.task.coordinates)):
        assert np.all((c >= a - 1e-6) & (c <= b + 1e-6))


def test_motor_zero_offset_acts_like_a_command_shift(twin, commands):
    y1 = twin.targets(commands[:4], {"m2.dzero": 0.05})
    shifted = commands[:4].copy()
    shifted[:, 1] += 0.05
    np.testing.assert_allclose(y1, twin.targets(shifted), atol=1e-9)


def test_ift_jacobian_matches_central_differences(twin, commands):
    """Exact at a machine with errors (not only at nominal): every key, 4 poses, step 1e-4 (mm / deg)."""
    rng = np.random.default_rng(2)
    keys = twin.error_keys
    params = dict(zip(keys, rng.normal(0.0, 1.0, len(keys)) * twin.prior_std(keys)))
    cmd = commands[:4]
    J = twin.jacobian(cmd, params)
    worst = float(np.max(np.abs(central_differences(lambda p: twin.targets(cmd, p), params, keys) - J)))
    # central differences: truncation ~ h^2 * third derivative (~1e-8 mm per unit), round-off ~ 1e-13 m / h
    assert worst < 1e-6, worst
    assert np.abs(J).max() > 1.0                      # a real Jacobian, not zeros


def test_unknown_error_key_is_named(twin):
    with pytest.raises(KeyError, match="unknown error key 'arm9.dx'"):
        twin.targets(np.zeros((1, 3)), {"arm9.dx": 0.1})


def test_body_based_closure_is_the_same_machine(tmp_path):
    """One rod closed body-based (MuJoCo derives the platform's anchor from qpos0): converted on load to two
    sites at the compiled anchors, the Delta is the same machine, nominal and with errors on the closure
    points (named after the equality), to the file's rounding of the platform height."""
    import shutil

    folder = tmp_path / "d"
    shutil.copytree(machine_dir("delta_3dof"), folder)
    xml = folder / "delta_3dof.xml"
    site = '<connect name="closure_3b" site1="rod3b_tip" site2="platform_3b"/>'
    assert site in xml.read_text()
    xml.write_text(xml.read_text().replace(site, '<connect name="closure_3b" body1="rod3b" body2="platform" '
                                                 'anchor="0 0 -0.8"/>'))
    body = ClosedChainTwin.from_folder(folder)
    site_twin = ClosedChainTwin.from_folder(machine_dir("delta_3dof"))
    assert {"closure_3b_site1.dx", "closure_3b_site2.dz"} <= set(body.error_keys)
    cmd = site_twin.sample_commands(10, np.random.default_rng(2))
    # MuJoCo derives the platform's anchor from qpos0, where the file gives the platform's height to 0.1 um
    # (-0.6323765 m): the two forms differ by that rounding, nothing more
    assert np.abs(body.targets(cmd) - site_twin.targets(cmd)).max() < 1e-4
    errors = {"rod3b_tip.dx": 0.2, "platform_3b.dz": -0.3, "arm1.dy": 0.1}
    renamed = {"closure_3b_site1.dx": 0.2, "closure_3b_site2.dz": -0.3, "arm1.dy": 0.1}
    assert np.abs(body.targets(cmd, renamed) - site_twin.targets(cmd, errors)).max() < 1e-4


def test_seeded_machines_are_not_chain_twins():
    with pytest.raises(ValueError, match="seeded machine"):
        ClosedChainTwin.from_folder(machine_dir("ocpm_2dof"))
