"""The planar robot's closed-form fast path (pmcal.mechanism.planar.chain.PlanarChainModel) against the generic
core's MuJoCo twin of the same folder (Newton on the MJCF's loop closures, IFT derivatives: a formulation that
shares no code with the closed forms), and the generic algorithms run on it against the paper's dedicated
linearised identification (calib.planar.identification) on the same readings.

Tolerances: the two formulations solve the same geometry to round-off (the twin's Newton stops at 1e-10 m);
derivatives agree to the twin's solve accuracy; the paper's eq. 29 is the same linear algebra on both paths.
"""

from __future__ import annotations

import numpy as np
import pytest

from pmcal.calib.chain_model import ChainModel, NamedModel
from pmcal.calib.closed_chain import crlb, identify_chain, reading_covariance
from pmcal.calib.planar.design import boundary_positions
from pmcal.calib.planar.identification import identify
from pmcal.mechanism.machine_spec import MachineSpec
from pmcal.mechanism.planar.chain import PlanarChainModel
from pmcal.mechanism.planar.geometry import Errors, Geometry, Workspace
from pmcal.mechanism.planar.kinematics import actual_position, inverse, mm_vector
from pmcal.mechanism.planar.noise import Noise
from pmcal.mjcf import machine_dir
from pmcal.twin.closed_chain import ClosedChainTwin

KEYS4 = ["dtheta1", "dtheta2", "drMx", "drMy"]


@pytest.fixture(scope="module")
def models():
    spec = MachineSpec.load(machine_dir("planar_2dof") / "chain")
    return PlanarChainModel(spec), NamedModel(ClosedChainTwin(spec), spec.names)


def _errors(rng) -> dict:
    fast = PlanarChainModel(MachineSpec.load(machine_dir("planar_2dof") / "chain"))
    return {k: float(rng.normal(0.0, 1.0 if u == "deg" else 0.3)) for k, u in zip(fast.error_keys,
                                                                                  fast.error_units())}


def test_protocol_and_names(models):
    fast, twin = models
    assert isinstance(fast, ChainModel)
    assert fast.error_keys == twin.error_keys
    assert fast.error_units() == twin.error_units()
    np.testing.assert_array_equal(fast.prior_std(), twin.prior_std())
    assert fast.reading_reference == twin.reading_reference == "previous"
    with pytest.raises(ValueError, match="unknown error key"):
        fast.observe(np.zeros((1, 2)) + [0.0, 180.0], {"dl3": 1.0})


@pytest.mark.parametrize("seed", [0, 1])
def test_same_machine_as_the_mujoco_twin(models, seed):
    fast, twin = models
    rng = np.random.default_rng(seed)
    p = _errors(rng)
    task = np.stack([rng.uniform(-240, 240, 12), rng.uniform(-782, -632, 12)], axis=1)
    cmd = fast.inverse(task, p)
    assert np.isfinite(cmd).all()
    np.testing.assert_allclose(cmd, twin.inverse(task, p), atol=1e-8)                      # deg
    np.testing.assert_allclose(fast.forward(cmd, p), task, atol=1e-9)                      # mm
    np.testing.assert_allclose(fast.targets(cmd, p), twin.targets(cmd, p), atol=1e-8)      # mm, world
    np.testing.assert_allclose(fast.observe(cmd, p), twin.observe(cmd, p), atol=1e-8)
    np.testing.assert_allclose(fast.jacobian(cmd, p), twin.jacobian(cmd, p), atol=1e-8)
    Jf, Jt = fast.observation_jacobian(cmd, p), twin.observation_jacobian(cmd, p)
    np.testing.assert_allclose(Jf, Jt, atol=1e-9 * np.abs(Jt).max())
    # the motor columns under their frame-error names (what reading_covariance asks for)
    np.testing.assert_allclose(fast.observation_jacobian(cmd, p, ["m1.dzero", "m2.dzero"]),
                               Jf[..., :2], rtol=0, atol=0)


def test_derivatives_are_those_of_the_readings(models):
    """Central differences of the closed-form readings (no derivative code involved), at a machine with
    errors: the Jacobian is exact at the real configuration, not the paper's first order at the nominal."""
    fast, _ = models
    rng = np.random.default_rng(5)
    p = _errors(rng)
    cmd = fast.inverse(np.array([[-200.0, -650.0], [30.0, -700.0], [220.0, -780.0]]), p)
    J = fast.observation_jacobian(cmd, p)[:, 0]
    for j, k in enumerate(fast.error_keys):
        h = 1e-4
        up, down = dict(p), dict(p)
        up[k] += h
        down[k] -= h
        fd = (fast.observe(cmd, up) - fast.observe(cmd, down))[:, 0] / (2 * h)
        np.testing.assert_allclose(J[:, j], fd, rtol=1e-6, atol=1e-8, err_msg=k)


def test_out_of_range_targets_are_nan(models):
    fast, twin = models
    task = np.array([[0.0, -707.0], [0.0, -5000.0], [3000.0, -707.0]])
    cmd = fast.inverse(task)
    assert np.isfinite(cmd[0]).all() and np.isnan(cmd[1:]).all()
    assert np.isnan(twin.inverse(task)[1:]).all()


def _campaign(rng, errors: Errors, noise: Noise):
    geom = Geometry()
    r = boundary_positions(Workspace(), 3)
    cmd = inverse(geom, r)
    held = cmd + rng.normal(0.0, noise.servo, cmd.shape)
    length = np.linalg.norm(mm_vector(geom.perturbed(errors), actual_position(geom, errors, held)), axis=-1)
    return geom, r, cmd, np.diff(length) + rng.normal(0.0, noise.scale, len(r) - 1)


@pytest.mark.parametrize("weighted", [False, True])
def test_the_papers_estimator_on_the_generic_core(models, weighted):
    """The paper's eq. 29 (one linearisation at the nominal machine, TSVD at full rank; GLS with the noise
    model) run by identify_chain on the fast path gives the dedicated code's estimate on the same readings."""
    fast, _ = models
    noise = Noise()
    errors = Errors.from_interface({"dtheta1": 2.0, "dtheta2": -1.0, "de1x": 0.03, "dl2": -0.02, "drMx": 1.0,
                                    "drMy": 0.5})
    for seed in range(5):
        geom, r, cmd, readings = _campaign(np.random.default_rng(seed), errors, noise)
        ded = identify(geom, r, readings, model="simplified", method="gls" if weighted else "tsvd", noise=noise)
        cov = reading_covariance(fast, np.rad2deg(cmd), [np.rad2deg(noise.servo)] * 2, noise.scale) \
            if weighted else None
        gen = identify_chain(fast, np.rad2deg(cmd), readings, noise.scale, KEYS4, prior=False, covariance=cov,
                             method="tsvd", rank=4, max_iter=1)
        assert gen.base == KEYS4 or sorted(gen.base) == sorted(KEYS4)
        np.testing.assert_allclose([gen.params["dtheta1"], gen.params["dtheta2"]], np.rad2deg(ded.x[:2]),
                                   atol=1e-9)                                           # deg
        np.testing.assert_allclose([gen.params["drMx"], gen.params["drMy"]], ded.x[2:], atol=1e-9)  # mm


def test_exact_fit_recovers_the_machine_and_the_twin_agrees(models):
    """Noise-free readings of a machine with only the four unknowns: the exact fit (LM on the fast path)
    recovers them where the paper's linearisation is biased by ~0.1-0.2 deg; the MuJoCo twin gives the same fit."""
    fast, twin = models
    truth = {"dtheta1": 2.0, "dtheta2": -1.0, "drMx": 1.0, "drMy": 0.5}
    geom, r, cmd, _ = _campaign(np.random.default_rng(0), Errors(), Noise())
    readings = np.diff(fast.observe(np.rad2deg(cmd), truth)[:, 0])
    fit = identify_chain(fast, np.rad2deg(cmd), readings, 1e-3, KEYS4, prior=False)
    np.testing.assert_allclose([fit.params[k] for k in KEYS4], [truth[k] for k in KEYS4], atol=1e-6)
    lin = identify(geom, r, readings, model="simplified")
    assert np.max(np.abs(np.rad2deg(lin.x[:2]) - [2.0, -1.0])) > 0.05
    slow = identify_chain(twin, np.rad2deg(cmd), readings, 1e-3, KEYS4, prior=False)
    np.testing.assert_allclose([slow.params[k] for k in KEYS4], [fit.params[k] for k in KEYS4], atol=1e-6)
    np.testing.assert_allclose(crlb(fast, np.rad2deg(cmd), truth, KEYS4, 1e-3),
                               crlb(twin, np.rad2deg(cmd), truth, KEYS4, 1e-3), rtol=1e-6)
