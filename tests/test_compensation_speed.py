"""The whole-chain compensation gives the commands of the previous, independent solver (per-target Newton
on the assembled forward model, pmcal at 6ec3c9e) and NaN, with a message, for targets out of reach
instead of failing the batch.

Two saved references of that solver: ``fullchain_setpoints_6ec3c9e.csv`` stopped at a pointing residual
below 1e-7 deg (its residuals reach 9.97e-8 deg, so its commands are only that close to the solution),
``..._tight.csv`` the same targets converged below 1e-11 deg (tools/tight_reference.py)."""

from pathlib import Path

import numpy as np
import pytest

from pmcal.calib.ocpm.fullchain import chain_commands_deg, platform_normals
from pmcal.ocpm.compensators import FullCompensation
from pmcal.mechanism.rotations import tilt_torsion
from pmcal.twin.ocpm.machine import Twin
from pmcal.mechanism.ocpm.config import default_geometry
from pmcal.mechanism.ocpm.kinematics import nominal_ik
from pmcal.mechanism.ocpm.params import random_errors

REFERENCE = Path(__file__).parent / "data" / "fullchain_setpoints_6ec3c9e.csv"
TIGHT = Path(__file__).parent / "data" / "fullchain_setpoints_6ec3c9e_tight.csv"


def reference(path=REFERENCE):
    lines = [line for line in path.read_text().splitlines() if not line.startswith("#")]
    return np.genfromtxt(lines, delimiter=",", names=True)


def pointing_residual_deg(comp, m_deg, phi_deg, theta_deg):
    """Largest offset (deg) of the platform normal from the target normal, the twin assembled cold at the
    commands and the normal fitted to its targets (the old solver's own measure)."""
    twin = Twin(comp.errors, comp.geom, stiffness_ratio=comp.ratio)
    st = twin.reach(m_deg)
    w = platform_normals(st.targets, comp.geom.targets)
    Rt = tilt_torsion(np.deg2rad(phi_deg), np.deg2rad(theta_deg))
    return np.rad2deg(np.abs(np.einsum("nik,ni->nk", Rt[:, :, :2], w)).max())


@pytest.mark.parametrize("ratio", [1000.0, 100.0])
def test_commands_equal_the_reference_in_a_batch_and_one_by_one(ratio):
    d, loose = reference(TIGHT), reference()
    d, loose = d[d["stiffness_ratio"] == ratio], loose[loose["stiffness_ratio"] == ratio]
    ref = np.stack([d["m1_deg"], d["m2_deg"]], axis=1)
    comp = FullCompensation(random_errors(np.random.default_rng(7), 0.5, 0.1), ratio, default_geometry())
    batch = comp.commands_deg(d["phi_deg"], d["theta_deg"])
    assert np.array_equal(np.isnan(batch), np.isnan(ref))
    assert np.nanmax(np.abs(batch - ref)) < 1e-9
    ok = np.isfinite(batch).all(axis=1)
    assert pointing_residual_deg(comp, batch[ok], d["phi_deg"][ok], d["theta_deg"][ok]) < 1e-10
    # the reference saved at 1e-7 deg: as close as its own residual (<= 1e-7 deg) allows
    assert np.nanmax(np.abs(batch - np.stack([loose["m1_deg"], loose["m2_deg"]], axis=1))) < 2e-7
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
    # solved tighter than 1e-10 deg; the closed form is exact to ~1e-13 rad
    assert np.abs(m[ok] - expect[ok]).max() < 1e-9
    assert np.isnan(m[~ok]).all() and list(comp.unreachable) == [5, 20]


class _NewtonOnly:
    """The twin's forward model without its direct solve: chain_commands_deg falls back to Newton."""

    def __init__(self, model):
        self._m = model

    def __getattr__(self, name):
        if name == "aim_commands_deg":
            raise AttributeError(name)
        return getattr(self._m, name)

    @property
    def stiffness_ratio(self):
        return self._m.stiffness_ratio


def test_newton_on_the_forward_model_gives_the_same_commands():
    """The generic path (any ForwardModel) and the twin's bordered Newton agree with the tight reference."""
    from pmcal.calib.ocpm.forward_model import AimingModel
    from pmcal.mechanism.ocpm.params import ErrorSet
    from pmcal.twin.ocpm.forward import FullChainModel

    d = reference(TIGHT)
    d = d[(d["stiffness_ratio"] == 1000.0) & np.isfinite(d["m1_deg"])][::9]
    ref = np.stack([d["m1_deg"], d["m2_deg"]], axis=1)
    geom = default_geometry()
    e = ErrorSet.from_dict(random_errors(np.random.default_rng(7), 0.5, 0.1), geom.n_limbs, geom.actuated)
    model = _NewtonOnly(FullChainModel(geom))
    assert not isinstance(model, AimingModel) and isinstance(model._m, AimingModel)
    m = chain_commands_deg(model, e, d["phi_deg"], d["theta_deg"], 1000.0)
    assert np.abs(m - ref).max() < 1e-9


def test_the_twin_declines_to_aim_under_gravity():
    """With gravity (or motor springs) the bordered solve does not hold: the model says so and
    chain_commands_deg runs Newton on its predictions instead."""
    from pmcal.twin.ocpm.forward import FullChainModel

    model = FullChainModel(default_geometry())
    model.twin.assembler.gravity = True
    assert model.aim_commands_deg([10.0], [20.0]) is None
