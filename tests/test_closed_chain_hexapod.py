"""The generic closed-chain twin on the Gough-Stewart hexapod (mjcf/hexapod_6dof, data only) against its
leg-length inverse kinematics and a separately written Newton forward kinematics (tests/chain_references.py)."""

import numpy as np
import pytest

from chain_references import central_differences, hexapod_fk, hexapod_ik, rpy_matrix
from pmcal.calib.closed_chain import identify_chain
from pmcal.mechanism.machine_spec import MachineSpec
from pmcal.mjcf import machine_dir
from pmcal.twin.closed_chain import ClosedChainTwin

# The MJCF's leg directions are written with 10 significant digits: the model agrees with the exact
# geometry to ~1e-7 mm.
TOL_MM = 1e-6


@pytest.fixture(scope="module")
def twin():
    return ClosedChainTwin(MachineSpec.load(machine_dir("hexapod_6dof")))


@pytest.fixture(scope="module")
def poses(twin):
    return twin.sample_task(12, np.random.default_rng(5))


def test_structure(twin):
    assert twin.n_motors == 6 and twin.n_equations == 18 and len(twin.passive) == 18
    assert [m.unit for m in twin.spec.motors] == ["mm"] * 6
    assert twin.spec.motor_columns[0] == "m1_cmd_mm"


def test_inverse_is_the_leg_lengths(twin, poses):
    np.testing.assert_allclose(twin.inverse(poses), hexapod_ik(poses), atol=TOL_MM)


def test_forward_matches_newton_on_leg_lengths(twin, poses):
    lengths = hexapod_ik(poses)
    task = twin.forward(lengths)
    ref = hexapod_fk(lengths)
    np.testing.assert_allclose(task[:, :3], ref[:, :3], atol=TOL_MM)
    np.testing.assert_allclose(task[:, 3:], ref[:, 3:], atol=1e-7)          # deg
    np.testing.assert_allclose(ref, poses, atol=1e-9)


def test_nests_ride_on_the_platform(twin, poses):
    """Nest k sits at 120 mm radius, 30 + 120 (k - 1) deg, 30 mm above the platform frame (README.md)."""
    y = twin.targets(hexapod_ik(poses))
    for n, (x, yy, z, rx, ry, rz) in enumerate(poses):
        R = rpy_matrix(rx, ry, rz)
        for k, ang in enumerate((30.0, 150.0, 270.0)):
            local = np.array([120 * np.cos(np.deg2rad(ang)), 120 * np.sin(np.deg2rad(ang)), 30.0])
            np.testing.assert_allclose(y[n, k], [x, yy, z] + R @ local, atol=TOL_MM)


def test_leg_zero_offset_is_a_length_error(twin, poses):
    """m3.dzero = +0.2 mm lengthens leg 3 by 0.2 mm at the same command."""
    lengths = hexapod_ik(poses[:3])
    task = twin.forward(lengths, {"m3.dzero": 0.2})
    true_lengths = lengths.copy()
    true_lengths[:, 2] += 0.2
    ref = hexapod_fk(true_lengths)
    np.testing.assert_allclose(task[:, :3], ref[:, :3], atol=TOL_MM)
    np.testing.assert_allclose(task[:, 3:], ref[:, 3:], atol=1e-7)


def test_ift_jacobian_matches_central_differences(twin):
    rng = np.random.default_rng(4)
    cmd = twin.sample_commands(3, rng)
    keys = twin.error_keys
    params = dict(zip(keys, rng.normal(0.0, 1.0, len(keys)) * twin.prior_std(keys)))
    J = twin.jacobian(cmd, params)
    worst = float(np.max(np.abs(central_differences(lambda p: twin.targets(cmd, p), params, keys) - J)))
    assert worst < 1e-6, worst


def test_identification_recovers_the_base_set(twin):
    rng = np.random.default_rng(8)
    true = {k: float(rng.uniform(0.05, 0.1) if u == "deg" else rng.uniform(0.1, 0.5)) * rng.choice([-1, 1])
            for k, u in zip(twin.error_keys, twin.error_units())}
    cmd = twin.sample_commands(48, rng)
    res = identify_chain(twin, cmd, twin.measure(cmd, true, rng))
    z = (res.x - res.basis.combination_values(true)) / np.array([res.std[k] for k in res.base])
    assert res.success and 0.65 < np.sqrt(np.mean(z**2)) < 1.35 and np.max(np.abs(z)) < 4.0, z
    assert abs(res.chi2_per_dof - 1.0) < 5 * np.sqrt(2.0 / res.dof)


def test_task_jacobian_matches_central_differences(twin):
    """d (x, y, z mm, rx, ry, rz deg) / d errors at fixed leg lengths, against differences of forward()."""
    rng = np.random.default_rng(1)
    cmd = twin.sample_commands(3, rng)
    keys = twin.error_keys[::5]
    params = dict(zip(twin.error_keys, rng.normal(0.0, 0.2, len(twin.error_keys))))
    J = twin.task_jacobian(cmd, params, keys)
    np.testing.assert_allclose(J, central_differences(lambda p: twin.forward(cmd, p), params, keys), atol=1e-6)
    assert np.abs(J).max() > 0.5


def test_pose_from_nests_by_rigid_fit(twin, poses):
    """measure = "pose": a rigid fit of the nests onto their task-frame coordinates gives the platform pose."""
    from pmcal.mechanism.rigid import fit_pose
    from pmcal.mechanism.task_space import rpy_angles

    X = twin.targets_in_task_frame()
    np.testing.assert_allclose(X[0], [120 * np.cos(np.deg2rad(30)), 60.0, 30.0], atol=TOL_MM)
    r, R, rms = fit_pose(twin.targets(hexapod_ik(poses)), X)
    np.testing.assert_allclose(r, poses[:, :3], atol=TOL_MM)
    np.testing.assert_allclose(np.rad2deg(rpy_angles(R)), poses[:, 3:], atol=1e-7)
    assert np.all(rms < 1e-6)
